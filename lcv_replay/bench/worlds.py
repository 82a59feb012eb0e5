"""Generated pose-graph worlds: a benchmark that cannot be overfitted (issue 16).

A world is a robot driving a road network for ``poses`` steps of about 1 m. Its ground truth, its
noisy odometry, and a loop candidate wherever it revisits a place are written as a g2o graph plus
a ground-truth vertex file; outliers are then injected by the g2o recorder, the Vertigo way
(:func:`recorders.g2o.inject_outliers`), so a generated case is built exactly like a Vertigo one.

Layouts (:data:`LAYOUTS`):

``grid``
    A square grid city (blocks of ``block_m``), driven as a random walk through its intersections:
    straight ahead more often than a turn, never a U-turn. City10000 and Manhattan are of this kind.
``ring``
    A grid city inside a ring road, joined to it by four radial roads; the walk alternates between
    laps of the ring and the city streets (Vertigo's ringCity is of this kind).

Noise models (:data:`NOISE_MODELS`), for odometry steps and loop measurements alike:

``gaussian``
    Gaussian with the declared covariances.
``heavy``
    A multivariate Student-t with 3 degrees of freedom whose scale is the declared covariance:
    the bulk is as declared, the tail is not.
``misdeclared``
    Gaussian, but the declared covariances are off by a factor drawn per world, log-uniform in
    0.1 to 10, separately for the odometry and the loops (the data are then 10 times more or less
    precise than the graph says, as with Manhattan).
``anisotropic``
    Gaussian, but each axis of each declared covariance (x, y, yaw; odometry and loops) is off by
    its own factor, log-uniform in 0.1 to 10 (ringCity declares its odometry's sideways and yaw
    noise ten times too large and its x noise right).

Revisits: a frame gets one loop candidate to the nearest earlier frame at least
``min_loop_gap_frames`` older and closer than ``revisit_radius_m`` (in the ground truth), with
probability ``loop_probability``; its measurement is the true relative pose plus loop noise. Every
such loop is true; the recorder labels them when it injects outliers.

Everything is a pure function of the :class:`WorldSpec` (its ``seed`` included).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from lcv_replay import se2
from lcv_replay.errors import ConfigError

Layout = Literal["grid", "ring"]
NoiseModel = Literal["gaussian", "heavy", "misdeclared", "anisotropic"]

LAYOUTS: tuple[str, ...] = ("grid", "ring")
#: The noise models of the built-in suites (``anisotropic`` is available too).
NOISE_MODELS: tuple[str, ...] = ("gaussian", "heavy", "misdeclared")
ALL_NOISE_MODELS: tuple[str, ...] = NOISE_MODELS + ("anisotropic",)

#: Bumped whenever the generator's output for a given spec changes (part of the suite's log cache key).
WORLD_VERSION = 1
#: Version of how a world's outliers are injected (in the suite's log names, not in the world's
#: seed): 2 keeps them out of the revisit radius (version 1 labelled some real revisits false).
WORLD_OUTLIERS_VERSION = 2

#: Degrees of freedom of the ``heavy`` noise model's Student-t.
HEAVY_DOF = 3.0
#: ``misdeclared``: declared covariance = true covariance x a factor log-uniform in this range.
MISDECLARED_RANGE = (0.1, 10.0)


@dataclass(frozen=True)
class WorldSpec:
    """A generated world (see the module docstring). Units in the names; angles in radians.

    Attributes:
        layout: ``grid`` or ``ring``.
        poses: number of poses (frames), 1,000 to 10,000 in the suites.
        noise: ``gaussian``, ``heavy`` or ``misdeclared``.
        seed: seeds the road network walk, the noise and the revisits.
        step_m: distance driven per pose.
        block_m: side of a city block.
        odometry_sigmas: true per-step odometry sigmas ``(x_m, y_m, yaw_rad)`` (the scale for ``heavy``).
        loop_sigmas: true loop measurement sigmas ``(x_m, y_m, yaw_rad)``.
        revisit_radius_m: a frame closer than this to an earlier one is a revisit.
        min_loop_gap_frames: a revisit must be at least this many frames older.
        loop_probability: chance that a revisit becomes a loop candidate.
    """

    layout: Layout = "grid"
    poses: int = 2000
    noise: NoiseModel = "gaussian"
    seed: int = 0
    step_m: float = 1.0
    block_m: float = 8.0
    odometry_sigmas: tuple[float, float, float] = (0.05, 0.02, 0.01)
    loop_sigmas: tuple[float, float, float] = (0.1, 0.1, 0.02)
    revisit_radius_m: float = 1.5
    min_loop_gap_frames: int = 50
    loop_probability: float = 0.5

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ConfigError(f"unknown world layout '{self.layout}'", fix=f"use one of {', '.join(LAYOUTS)}")
        if self.noise not in ALL_NOISE_MODELS:
            raise ConfigError(f"unknown world noise model '{self.noise}'", fix=f"use one of {', '.join(ALL_NOISE_MODELS)}")
        if not 100 <= self.poses <= 1_000_000:
            raise ConfigError(f"world poses = {self.poses} is out of range", fix="use 100 to 1,000,000 poses")
        for name in ("step_m", "block_m", "revisit_radius_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"world {name} = {getattr(self, name)} must be > 0")
        if self.block_m < 2 * self.step_m:
            raise ConfigError(f"world block_m = {self.block_m} is shorter than two steps", fix="use block_m >= 2 * step_m")
        if not all(s > 0 for s in (*self.odometry_sigmas, *self.loop_sigmas)):
            raise ConfigError("world sigmas must all be > 0")
        if not 0.0 < self.loop_probability <= 1.0:
            raise ConfigError(f"world loop_probability = {self.loop_probability} must be in (0, 1]")
        if self.min_loop_gap_frames < 2:
            raise ConfigError(f"world min_loop_gap_frames = {self.min_loop_gap_frames} must be >= 2")

    @property
    def name(self) -> str:
        """``grid-2k-gaussian-s0``-style short name."""
        size = f"{self.poses // 1000}k" if self.poses % 1000 == 0 else str(self.poses)
        return f"{self.layout}-{size}-{self.noise}-s{self.seed}"


@dataclass(frozen=True)
class World:
    """A generated world.

    Attributes:
        spec: what it was generated from.
        truth: ``(N, 3)`` ground-truth poses ``[x_m, y_m, yaw_rad]``.
        odometry: ``(N, 3)`` cumulative noisy odometry (frame 0 at the truth's first pose).
        odometry_information: ``(3, 3)`` declared information of one odometry step.
        loops: ``(L, 2)`` int ``(query, match)`` frame pairs, query > match.
        loop_measurements: ``(L, 3)`` measured ``T_match_query``.
        loop_information: ``(3, 3)`` declared information of every loop.
        declared_factors: ``(odometry, loops)`` declared covariance / true covariance (for
            ``anisotropic``, the geometric mean of the three axes).
    """

    spec: WorldSpec
    truth: np.ndarray
    odometry: np.ndarray
    odometry_information: np.ndarray
    loops: np.ndarray
    loop_measurements: np.ndarray
    loop_information: np.ndarray
    declared_factors: tuple[float, float]


# ---------------------------------------------------------------------------------------------
# Road networks and the walk
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RoadNetwork:
    """Junctions ``(J, 2)`` in metres and directed roads: ``roads[(a, b)]`` is the ``(K, 2)``
    polyline from junction ``a`` to ``b`` (both ends included); every road exists both ways."""

    junctions: np.ndarray
    roads: dict[tuple[int, int], np.ndarray]

    def exits(self, junction: int) -> list[int]:
        return [b for (a, b) in self.roads if a == junction]


def _grid_network(side_blocks: int, block_m: float, origin: tuple[float, float] = (0.0, 0.0)) -> RoadNetwork:
    n = side_blocks + 1
    ij = np.array([(i, j) for j in range(n) for i in range(n)], dtype=np.float64)
    junctions = np.asarray(origin) + block_m * ij
    roads: dict[tuple[int, int], np.ndarray] = {}
    for j in range(n):
        for i in range(n):
            a = j * n + i
            for di, dj in ((1, 0), (0, 1)):
                if i + di < n and j + dj < n:
                    b = (j + dj) * n + (i + di)
                    roads[(a, b)] = junctions[[a, b]]
                    roads[(b, a)] = junctions[[b, a]]
    return RoadNetwork(junctions, roads)


def _ring_network(side_blocks: int, block_m: float) -> RoadNetwork:
    """A grid city centred at the origin inside a ring road, four radial roads joining them."""
    half = side_blocks * block_m / 2.0
    grid = _grid_network(side_blocks, block_m, (-half, -half))
    n = side_blocks + 1
    radius = 2.0 * half + 2.0 * block_m
    ring_count = 16
    angles = 2.0 * np.pi * np.arange(ring_count) / ring_count
    ring = radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    junctions = np.concatenate([grid.junctions, ring])
    roads = dict(grid.roads)
    offset = len(grid.junctions)
    arc = np.linspace(0.0, 1.0, 9)[:, None]
    for k in range(ring_count):
        a0, a1 = angles[k], angles[k] + 2.0 * np.pi / ring_count
        theta = a0 + (a1 - a0) * arc[:, 0]
        line = radius * np.stack([np.cos(theta), np.sin(theta)], axis=1)
        a, b = offset + k, offset + (k + 1) % ring_count
        roads[(a, b)] = line
        roads[(b, a)] = line[::-1].copy()
    # radial roads from the middle of each side of the grid to the ring junction facing it
    mid = side_blocks // 2
    sides = {
        0: mid * n + (n - 1),  # east edge, row mid
        ring_count // 4: (n - 1) * n + mid,  # north edge
        ring_count // 2: mid * n,  # west edge
        3 * ring_count // 4: mid,  # south edge
    }
    for ring_k, g in sides.items():
        a, b = g, offset + ring_k
        line = np.stack([junctions[a], junctions[b]])
        roads[(a, b)] = line
        roads[(b, a)] = line[::-1].copy()
    return RoadNetwork(junctions, roads)


def _network(spec: WorldSpec) -> RoadNetwork:
    # Size the city so that a walk of ``poses`` steps drives each street about 4 times.
    street_m = spec.poses * spec.step_m / 4.0
    side = max(3, int(round(math.sqrt(street_m / (2.0 * spec.block_m)))))
    if spec.layout == "grid":
        return _grid_network(side, spec.block_m)
    return _ring_network(max(2, side - 1), spec.block_m)


def _walk(network: RoadNetwork, length_m: float, rng: np.random.Generator, *, ring_layout: bool) -> np.ndarray:
    """Polyline ``(K, 2)`` of a random walk at least ``length_m`` long (no U-turns, straight
    ahead preferred; on the ring, carrying on round the ring is preferred)."""
    junction = 0
    previous = -1
    points = [network.junctions[junction]]
    driven = 0.0
    heading = None
    while driven < length_m:
        exits = [b for b in network.exits(junction) if b != previous] or network.exits(junction)
        weights = []
        for b in exits:
            road = network.roads[(junction, b)]
            d = road[1] - road[0]
            h = math.atan2(d[1], d[0])
            turn = 0.0 if heading is None else abs((h - heading + math.pi) % (2 * math.pi) - math.pi)
            w = 2.0 if turn < math.pi / 4 else 1.0
            if ring_layout and len(road) > 2:  # a ring arc: keep lapping
                w *= 3.0
            weights.append(w)
        w = np.asarray(weights) / np.sum(weights)
        nxt = exits[int(rng.choice(len(exits), p=w))]
        road = network.roads[(junction, nxt)]
        points.extend(road[1:])
        driven += float(np.sum(np.linalg.norm(np.diff(road, axis=0), axis=1)))
        d = road[-1] - road[-2]
        heading = math.atan2(d[1], d[0])
        previous, junction = junction, nxt
    return np.asarray(points)


def _resample(polyline: np.ndarray, count: int, step_m: float) -> np.ndarray:
    """``count`` poses every ``step_m`` along ``polyline``; yaw is the direction of travel."""
    seg = np.diff(polyline, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    keep = lengths > 1e-9
    seg, lengths, starts = seg[keep], lengths[keep], polyline[:-1][keep]
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
    s = np.arange(count) * step_m
    k = np.clip(np.searchsorted(cumulative, s, side="right") - 1, 0, len(seg) - 1)
    t = (s - cumulative[k]) / lengths[k]
    xy = starts[k] + t[:, None] * seg[k]
    yaw = np.arctan2(seg[k, 1], seg[k, 0])
    return np.column_stack([xy, yaw])


# ---------------------------------------------------------------------------------------------
# Noise
# ---------------------------------------------------------------------------------------------


def _noise(rng: np.random.Generator, sigmas: np.ndarray, count: int, model: NoiseModel) -> np.ndarray:
    """``(count, 3)`` noise with scale ``sigmas``: Gaussian, or Student-t (``heavy``)."""
    z = rng.normal(size=(count, 3)) * sigmas
    if model == "heavy":
        z *= np.sqrt(HEAVY_DOF / rng.chisquare(HEAVY_DOF, size=(count, 1)))
    return z


def generate_world(spec: WorldSpec) -> World:
    """The world of ``spec`` (deterministic)."""
    rng = np.random.default_rng([spec.seed, WORLD_VERSION, LAYOUTS.index(spec.layout), ALL_NOISE_MODELS.index(spec.noise), spec.poses])
    network = _network(spec)
    path = _walk(network, (spec.poses + 2) * spec.step_m, rng, ring_layout=spec.layout == "ring")
    truth = _resample(path, spec.poses, spec.step_m)

    odo_sigmas = np.asarray(spec.odometry_sigmas, dtype=np.float64)
    loop_sigmas = np.asarray(spec.loop_sigmas, dtype=np.float64)
    steps = se2.between(truth[:-1], truth[1:])
    noisy = se2.compose(steps, _noise(rng, odo_sigmas, len(steps), spec.noise))
    odometry = se2.compose_chain(noisy, truth[0])

    # revisits: nearest earlier frame at least min_loop_gap_frames older, within the radius
    from scipy.spatial import cKDTree

    tree = cKDTree(truth[:, :2])
    pairs = []
    for q, neighbours in enumerate(tree.query_ball_point(truth[:, :2], spec.revisit_radius_m)):
        older = [m for m in neighbours if m <= q - spec.min_loop_gap_frames]
        if older and rng.random() < spec.loop_probability:
            d = np.linalg.norm(truth[older, :2] - truth[q, :2], axis=1)
            pairs.append((q, older[int(np.argmin(d))]))
    loops = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    relative = se2.between(truth[loops[:, 1]], truth[loops[:, 0]])
    measured = se2.compose(relative, _noise(rng, loop_sigmas, len(loops), spec.noise))

    odo_factor, loop_factor = np.ones(3), np.ones(3)
    low, high = np.log(MISDECLARED_RANGE)
    if spec.noise == "misdeclared":
        odo_factor, loop_factor = np.full(3, np.exp(rng.uniform(low, high))), np.full(3, np.exp(rng.uniform(low, high)))
    elif spec.noise == "anisotropic":
        odo_factor, loop_factor = np.exp(rng.uniform(low, high, 3)), np.exp(rng.uniform(low, high, 3))
    odo_info = np.diag(1.0 / (odo_factor * odo_sigmas**2))
    loop_info = np.diag(1.0 / (loop_factor * loop_sigmas**2))
    factors = (float(np.exp(np.mean(np.log(odo_factor)))), float(np.exp(np.mean(np.log(loop_factor)))))
    return World(spec, truth, odometry, odo_info, loops, measured, loop_info, factors)


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------


def _upper6(info: np.ndarray) -> str:
    return " ".join(f"{v:.9g}" for v in (info[0, 0], info[0, 1], info[0, 2], info[1, 1], info[1, 2], info[2, 2]))


def write_world(world: World, folder: str | Path) -> tuple[Path, Path]:
    """Write ``<name>.g2o`` (odometry vertices, chain and loop edges) and ``<name>_gt.g2o``
    (ground-truth vertices) into ``folder`` atomically; returns both paths."""
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.verification.measurements import odometry_between

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    name = world.spec.name
    spec_line = "# lcv-replay generated world " + " ".join(f"{k}={v}" for k, v in asdict(world.spec).items())
    odo_info, loop_info = _upper6(world.odometry_information), _upper6(world.loop_information)
    lines = [spec_line, f"# declared covariance / true covariance: odometry {world.declared_factors[0]:.4g}, loops {world.declared_factors[1]:.4g}"]
    lines += [f"VERTEX_SE2 {k} {x:.9g} {y:.9g} {t:.9g}" for k, (x, y, t) in enumerate(world.odometry.tolist())]
    lines += [f"EDGE_SE2 {k} {k + 1} {x:.9g} {y:.9g} {t:.9g} {odo_info}" for k, (x, y, t) in enumerate(odometry_between(world.odometry).tolist())]
    lines += [
        f"EDGE_SE2 {m} {q} {x:.9g} {y:.9g} {t:.9g} {loop_info}"
        for (q, m), (x, y, t) in zip(world.loops.tolist(), world.loop_measurements.tolist())
    ]
    graph = folder / f"{name}.g2o"
    truth = folder / f"{name}_gt.g2o"
    write_text_atomic(graph, "\n".join(lines) + "\n")
    write_text_atomic(truth, "\n".join([spec_line] + [f"VERTEX_SE2 {k} {x:.9g} {y:.9g} {t:.9g}" for k, (x, y, t) in enumerate(world.truth.tolist())]) + "\n")
    return graph, truth
