"""The one place that talks to GTSAM: planar pose graphs of odometry plus loop constraints.

Conventions:

* Frame ``k`` is GTSAM key ``k`` (a plain integer). Poses are ``(N, 3)`` float64 arrays
  ``[x_m, y_m, yaw_rad]`` (``T_world_base`` of frames 0..N-1).
* Factor order in every graph built by :func:`build_graph`: factor 0 is the prior on frame 0
  (fixes the gauge at the first odometry pose), factors ``1..N-1`` are the odometry steps
  ``(k, k+1)``, factors ``N..N+C-1`` are the loop constraints in the order given. So
  ``odometry_factor_indices(N) = range(N)`` are the known inliers of a GNC solve, and
  ``loop_factor_index(N, c) = N + c``.
* A loop constraint ``(query, match)`` is ``BetweenFactorPose2(match, query, T_match_query)``.
  Candidates without a relative pose (place recognition says "same place") use the identity with
  the config's ``loop_default_information``.
* Chi-square values are GTSAM's: ``chi2 = r^T Ω r`` with ``r = Logmap(z⁻¹ · (x_i⁻¹ x_j))``,
  i.e. ``2 × factor.error``; :func:`lcv_replay.se2.between_chi2` reproduces it without building a
  graph, for scoring many hypotheses cheaply.

The numpy side (SE(2) algebra in :mod:`lcv_replay.se2`; information matrices, loop measurements and
the odometry chain in :mod:`lcv_replay.verification.measurements`) lives outside this module.
``gtsam`` is imported lazily inside the functions that need it, so importing this module is cheap.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Literal, Mapping, NamedTuple, Sequence, TypeVar

import numpy as np

from lcv_replay import se2
from lcv_replay.errors import VerificationError
from lcv_replay.verification.measurements import (
    OdometryChain,
    as_information_matrix,
    check_poses,
    describe_constraint,
    loop_measurement,
    odometry_between,
)

if TYPE_CHECKING:  # pragma: no cover
    import gtsam

    from lcv_replay.verification.base import Constraint

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Standard deviation of the prior that fixes frame 0 (gauge freedom), metres and radians.
PRIOR_SIGMA = 1e-6

KernelKind = Literal["dcs", "gm", "cauchy", "huber", "tukey", "welsch"]


class OptimisationFailed(VerificationError):
    """GTSAM could not solve a pose graph (e.g. an indeterminant linear system)."""


@dataclass(frozen=True)
class RobustKernel:
    """An M-estimator wrapped around every loop factor's Gaussian noise model.

    Attributes:
        kind: ``"dcs"`` (dynamic covariance scaling, scale = Φ), ``"gm"`` (Geman-McClure,
            scale = c), ``"cauchy"`` (scale = c), ``"huber"``, ``"tukey"``, ``"welsch"``
            (scale = k), all as in ``gtsam.noiseModel.mEstimator``.
        scale: the kernel parameter, in whitened units.
    """

    kind: KernelKind
    scale: float

    def __post_init__(self) -> None:
        if self.kind not in ("dcs", "gm", "cauchy", "huber", "tukey", "welsch"):
            raise VerificationError(
                f"unknown robust kernel '{self.kind}'",
                fix="use one of dcs, gm, cauchy, huber, tukey, welsch",
            )
        if not self.scale > 0:
            raise VerificationError(f"robust kernel scale {self.scale!r} must be > 0")

    def estimator(self):
        """The ``gtsam.noiseModel.mEstimator`` instance."""
        import gtsam

        m = gtsam.noiseModel.mEstimator
        make = {
            "dcs": m.DCS,
            "gm": m.GemanMcClure,
            "cauchy": m.Cauchy,
            "huber": m.Huber,
            "tukey": m.Tukey,
            "welsch": m.Welsch,
        }[self.kind]
        return make.Create(self.scale)


@dataclass(frozen=True)
class PoseGraphSolution:
    """A solved pose graph.

    Attributes:
        poses: ``(N, 3)`` ``[x_m, y_m, yaw_rad]`` of frames 0..N-1.
        error: GTSAM's graph error at the solution (``0.5 × Σ chi2``, robust loss if robust).
        iterations: optimiser iterations, ``None`` where GTSAM does not report them (GNC).
    """

    poses: np.ndarray
    error: float
    iterations: int | None

    @property
    def chi2(self) -> float:
        """Total whitened chi-square, ``2 × error``."""
        return 2.0 * self.error


def information_to_noise(information, *, what: str = "factor"):
    """A ``gtsam.noiseModel.Gaussian`` from a ``(3, 3)`` (or upper-6) information matrix.

    Raises:
        VerificationError: naming ``what`` when the matrix is singular / not positive definite.
    """
    import gtsam

    return gtsam.noiseModel.Gaussian.Information(as_information_matrix(information, what=what))


# ----------------------------------------------------------------------------------------------
# GTSAM graphs and solvers
# ----------------------------------------------------------------------------------------------


def odometry_factor_indices(num_frames: int) -> list[int]:
    """Indices of the prior and odometry factors in a graph from :func:`build_graph`."""
    return list(range(num_frames))


def loop_factor_index(num_frames: int, position: int) -> int:
    """Index of the ``position``-th loop constraint's factor in a graph from :func:`build_graph`."""
    return num_frames + position


def build_graph(
    odom_poses: np.ndarray,
    odom_information: np.ndarray,
    constraints: Sequence["Constraint"],
    *,
    loop_default_information: np.ndarray,
    robust: RobustKernel | None = None,
    odometry_robust: RobustKernel | None = None,
    odometry_variance_factors: Mapping[int, float] | None = None,
):
    """Pose graph of odometry plus ``constraints`` (see the module docstring for factor order).

    Args:
        odom_poses: ``(N, 3)`` cumulative odometry, N >= 1; the prior fixes frame 0 there.
        odom_information: ``(3, 3)`` information of one odometry step.
        constraints: loop constraints with both frames in ``0..N-1``.
        loop_default_information: ``(3, 3)`` information of a candidate that carries none.
        robust: kernel wrapped around every loop factor, or ``None`` for plain Gaussian.
        odometry_robust: kernel wrapped around every odometry factor (heavy-tailed odometry:
            wheel slips, poor scan matches), or ``None`` for plain Gaussian.
        odometry_variance_factors: ``{k: f}``: the step from frame ``k`` to ``k + 1`` has ``f``
            times the covariance of the others (a slip's, loosened).

    Returns:
        ``gtsam.NonlinearFactorGraph`` with ``N + len(constraints)`` factors.

    Raises:
        VerificationError: a constraint references a frame outside ``0..N-1``, or an
            information matrix is singular (naming the constraint).
    """
    import gtsam

    odom = check_poses(odom_poses, "odom_poses")
    n = len(odom)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
    odom_noise = information_to_noise(odom_information, what="odometry")
    if odometry_robust is not None:
        odom_noise = gtsam.noiseModel.Robust.Create(odometry_robust.estimator(), odom_noise)
    loosened = {}
    for k, factor in (odometry_variance_factors or {}).items():
        noise = information_to_noise(np.asarray(odom_information, dtype=np.float64) / float(factor), what="odometry")
        loosened[int(k)] = noise if odometry_robust is None else gtsam.noiseModel.Robust.Create(odometry_robust.estimator(), noise)
    for k, step in enumerate(odometry_between(odom)):
        graph.add(gtsam.BetweenFactorPose2(k, k + 1, gtsam.Pose2(*step), loosened.get(k, odom_noise)))
    for c in constraints:
        if not (0 <= c.match_frame < n and 0 <= c.query_frame < n):
            raise VerificationError(
                f"{describe_constraint(c)} references a frame outside 0..{n - 1}",
                fix="add the frames before the constraints that reference them",
            )
    add_loop_factors(graph, [loop_factor(c, loop_default_information) for c in constraints], robust=robust)
    return graph


def add_loop_factors(graph, loops: Sequence["LoopFactor"], *, robust: RobustKernel | None = None) -> None:
    """Append ``BetweenFactorPose2(match, query, measured)`` for each loop to ``graph`` (in order)."""
    import gtsam

    estimator = robust.estimator() if robust is not None else None
    for loop in loops:
        noise = gtsam.noiseModel.Gaussian.Information(loop.information)
        if estimator is not None:
            noise = gtsam.noiseModel.Robust.Create(estimator, noise)
        graph.add(gtsam.BetweenFactorPose2(int(loop.match_frame), int(loop.query_frame), gtsam.Pose2(*loop.measured), noise))


class LoopFactor(NamedTuple):
    """A loop factor ready for a graph: ``BetweenFactorPose2(match_frame, query_frame, measured)``.

    ``measured`` is ``(3,)`` ``T_match_query``; ``information`` is ``(3, 3)``.
    """

    match_frame: int
    query_frame: int
    measured: np.ndarray
    information: np.ndarray


def loop_factor(constraint: "Constraint", default_information: np.ndarray) -> LoopFactor:
    """The :class:`LoopFactor` of a constraint (see :func:`loop_measurement`)."""
    measured, omega = loop_measurement(constraint, default_information)
    return LoopFactor(constraint.match_frame, constraint.query_frame, np.asarray(measured, dtype=np.float64), omega)


def build_reduced_graph(chain: OdometryChain, node_frames: np.ndarray, loops: Sequence[LoopFactor]):
    """Pose graph on ``node_frames`` only: the odometry between consecutive nodes is composed
    into one factor (exact measurement ``O_a⁻¹ O_b``, covariance from
    :meth:`OdometryChain.segment_covariance`, first order), plus the loops.

    Solving it gives the poses of the nodes; :meth:`OdometryChain.interpolate` gives the other
    frames. With the nodes at the loop endpoints this is the full graph's solution to first order,
    at a cost that depends on the number of loops, not of frames.

    Args:
        chain: the odometry.
        node_frames: ``(K,)`` strictly increasing, ``node_frames[0] == 0``, containing every
            endpoint of ``loops``.
        loops: loop factors.

    Returns:
        ``gtsam.NonlinearFactorGraph``: prior on frame 0, ``K - 1`` chain factors, then the loops.
    """
    import gtsam

    node_frames = np.asarray(node_frames, dtype=np.int64)
    if len(node_frames) == 0 or node_frames[0] != 0 or np.any(np.diff(node_frames) <= 0) or node_frames[-1] >= len(chain):
        raise VerificationError(f"reduced graph nodes must be increasing frames from 0 to < {len(chain)}")
    odom = chain.poses
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
    a, b = node_frames[:-1], node_frames[1:]
    if len(a):
        steps = se2.between(odom[a], odom[b])
        covariances = chain.segment_covariance(a, b)
        for k in range(len(a)):
            noise = gtsam.noiseModel.Gaussian.Covariance(0.5 * (covariances[k] + covariances[k].T))
            graph.add(gtsam.BetweenFactorPose2(int(a[k]), int(b[k]), gtsam.Pose2(*steps[k]), noise))
    nodes = set(node_frames.tolist())
    for loop in loops:
        if loop.match_frame not in nodes or loop.query_frame not in nodes:
            raise VerificationError(f"loop ({loop.query_frame}, {loop.match_frame}) has an endpoint that is not a node")
    add_loop_factors(graph, loops)
    return graph


def relative_covariances(graph, poses: np.ndarray, keys: Sequence[int], match: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Laplace covariances of relative poses ``x_m⁻¹ x_q`` from GTSAM's marginals of ``graph``
    linearised at ``poses``.

    With ``x = x̄ Exp(δ)`` (GTSAM's right perturbation), ``x_m⁻¹ x_q ≈ x̄_mq Exp(δ_q - A δ_m)`` with
    ``A = Ad(x̄_mq⁻¹)``, so the covariance is ``[-A I] Σ_{mq} [-A I]ᵀ`` of the joint marginal of
    ``(x_m, x_q)``. This is the covariance of a loop's prediction under the graph: add the loop's
    own measurement covariance for its innovation covariance.

    Args:
        graph: a ``gtsam.NonlinearFactorGraph`` over Pose2 ``keys``.
        poses: ``(K, 3)`` linearisation point of ``keys`` (e.g. the graph's solution).
        keys: ``(K,)`` the graph's keys, increasing.
        match, query: ``(L,)`` keys (each in ``keys``), ``match < query``.

    Returns:
        ``(L, 3, 3)`` covariances in the tangent space at ``x̄_q`` of the relative pose.

    Raises:
        OptimisationFailed: GTSAM cannot factor the graph (e.g. an under-constrained key).
    """
    import gtsam

    match = np.asarray(match, dtype=np.int64)
    query = np.asarray(query, dtype=np.int64)
    out = np.empty((len(match), 3, 3))
    if len(match) == 0:
        return out
    keys = np.asarray(keys, dtype=np.int64)
    joints = np.empty((len(match), 6, 6))
    try:
        marginals = gtsam.Marginals(graph, initial_values(poses, keys))
        # One joint marginal per chunk of pairs: several times faster than one query per pair.
        for start in range(0, len(match), _MARGINAL_CHUNK):
            chunk = range(start, min(start + _MARGINAL_CHUNK, len(match)))
            wanted = sorted({int(match[k]) for k in chunk} | {int(query[k]) for k in chunk})
            joint = marginals.jointMarginalCovariance(gtsam.KeyVector(wanted))
            for k in chunk:
                m, q = int(match[k]), int(query[k])
                joints[k, :3, :3], joints[k, :3, 3:] = joint.at(m, m), joint.at(m, q)
                joints[k, 3:, :3], joints[k, 3:, 3:] = joint.at(q, m), joint.at(q, q)
    except RuntimeError as exc:
        raise OptimisationFailed(f"marginal covariances failed: {_first_line(exc)}") from exc
    index = np.searchsorted(keys, np.concatenate([match, query]))
    x_m, x_q = np.split(np.asarray(poses, dtype=np.float64)[index], 2)
    jac = np.zeros((len(match), 3, 6))
    jac[:, :, :3] = -se2.adjoint_inverse(se2.between(x_m, x_q))
    jac[:, :, 3:] = np.eye(3)
    out[:] = jac @ joints @ np.swapaxes(jac, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


#: Pairs per joint-marginal query in :func:`relative_covariances` (measured fastest on KITTI and
#: Manhattan graphs: one query per pair costs about 1 ms each, one per 32 pairs about 0.3 ms a pair).
_MARGINAL_CHUNK = 32


#: Serial numbers of :class:`IncrementalGraph` linearisation histories (:attr:`IncrementalGraph.epoch`).
_EPOCHS = itertools.count()


def pair_frames(match: np.ndarray, query: np.ndarray) -> list[int]:
    """The distinct frames of the pairs ``(match, query)``, increasing."""
    return sorted(set(np.asarray(match, dtype=np.int64).reshape(-1).tolist()) | set(np.asarray(query, dtype=np.int64).reshape(-1).tolist()))


class IncrementalGraph:
    """The odometry chain plus a changing set of loop factors, kept solved by iSAM2
    (``gtsam.ISAM2``): ``ilv+``'s working hypothesis.

    Frame ``k`` is key ``k``; frame 0 has the usual prior. Frames are appended with
    :meth:`extend` (initialised by odometry from the last estimate) and loops are added or removed
    by their constraint id with :meth:`update`. Each update re-eliminates only the part of the
    Bayes tree the change touches, then relinearises until no frame moves by more than
    ``relinearize_heading_rad`` in heading or ``relinearize_position_m`` along either axis (at
    most ``max_relinearizations`` extra steps), so the estimate is converged to those
    thresholds. Cost of an update: the cliques between the changed keys and the root, not the
    whole history.

    Both thresholds are 0.05 by default, iSAM2's usual single threshold. A looser one on the
    position (given the headings, a planar pose graph is linear in the positions) relinearises
    far fewer frames: 0.2 m took a 10k-pose world with heavy-tailed odometry from 154 s to 105 s,
    but on one heavy-tailed ring (s9404) a trial that moved the map far then settled in a wrong
    minimum, and 20 false loops were accepted (``docs/verification-bench.md``, twentieth stop).

    Args:
        odom_information: ``(3, 3)`` information of one odometry step.
        relinearize_heading_rad: iSAM2's relinearisation threshold on a frame's heading.
        relinearize_position_m: the same on each axis of its position (in its own frame).
        max_relinearizations: extra relinearisation steps after each update.

    Attributes:
        epoch: the serial number of this graph's linearisation history: new at construction and
            at each :meth:`restart` (a :meth:`rollback` returns to a state of the same history
            and keeps it). Within one epoch, a graph that holds every loop it held at
            an earlier :attr:`version` (:meth:`holds_loops_of`), and maybe more, gives covariances
            of relative poses no larger than it gave then, up to the relinearisation of the
            poses that moved (the frames' own marginals, in the tangent space at each pose, can
            turn with them).
        version: bumped by each update, restart and rollback.
    """

    def __init__(
        self,
        odom_information: np.ndarray,
        *,
        relinearize_heading_rad: float = 0.05,
        relinearize_position_m: float = 0.05,
        max_relinearizations: int = 2,
    ):
        import gtsam

        params = gtsam.ISAM2Params()
        if relinearize_position_m == relinearize_heading_rad:
            params.setRelinearizeThreshold(float(relinearize_heading_rad))
        else:
            thresholds = gtsam.ISAM2ThresholdMap()  # per dimension of Pose2's tangent (x, y, heading)
            # keyed by the key's Symbol character: plain frame indices have none ('\0')
            thresholds.insert(("\0", np.array([relinearize_position_m, relinearize_position_m, relinearize_heading_rad], dtype=np.float64)))
            params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = 2**30  # relinearise only when asked (force_relinearize)
        self._isam = gtsam.ISAM2(params)
        self._odom_noise = information_to_noise(odom_information, what="odometry")
        self._odom = np.zeros((0, 3))
        self._pending_from = 0  # first frame not yet in iSAM2
        self._slots: dict[int, int] = {}  # loop id -> iSAM2 factor index
        self._loop_id_array: np.ndarray | None = None  # loop_ids as an array (cached until the loops change)
        self._loops: dict[int, LoopFactor] = {}
        self._params = params
        self.factorization = "CHOLESKY"  # iSAM2's; QR after a Cholesky failure (see update)
        self._estimate: np.ndarray | None = None
        self._linearization: np.ndarray | None = None  # iSAM2's linearisation point (cached until it moves)
        self._last_estimate = np.zeros((0, 3))  # the latest estimate computed (kept across updates)
        self.max_relinearizations = int(max_relinearizations)
        self.updates = 0  # iSAM2 update calls so far (for timings)
        self.relinearized = 0  # frames relinearised by those calls, in all
        self.epoch = next(_EPOCHS)  # changes at each restart, unique across graphs (see :attr:`epoch`)
        self.version = 0  # bumped by each change (see :meth:`holds_loops_of`)
        self._queried: tuple[tuple[int, int], float] = ((-1, -1), 0.0)  # (epoch, version), seconds of iSAM2 covariance queries at it
        self._batch_marginals = None  # gtsam.Marginals of the system at that version, once built
        self._elimination_s = 0.02  # what building those took last time (a guess until then)
        self._added_at: dict[int, int] = {}  # loop id -> the version that added it
        self._lost: list[tuple[int, int]] = []  # (version added, version removed) of each loop removed, in order

    def __len__(self) -> int:
        return len(self._odom)

    @property
    def loop_ids(self) -> frozenset[int]:
        """Ids of the loops in the graph."""
        return frozenset(self._slots)

    def loop_id_array(self) -> np.ndarray:
        """``(L,)`` int64: :attr:`loop_ids` as an array, in the set's iteration order (cached until
        the loops change; callers must not modify it)."""
        if self._loop_id_array is None:
            self._loop_id_array = np.fromiter(frozenset(self._slots), dtype=np.int64)
            self._loop_id_array.flags.writeable = False
        return self._loop_id_array

    def extend(self, odom_poses: np.ndarray) -> None:
        """Set the cumulative odometry to ``odom_poses`` (``(N, 3)``; the first frames must equal
        the ones given before); the new frames join the graph at the next :meth:`update`."""
        odom = check_poses(odom_poses, "odom_poses")
        if len(odom) < len(self._odom):
            raise VerificationError(f"odometry cannot shrink from {len(self._odom)} to {len(odom)} frames")
        self._odom = odom.copy()

    def update(self, add: Sequence[tuple[int, "LoopFactor"]] = (), remove: Sequence[int] = (), *, relinearize: bool = True) -> None:
        """Add loops ``(id, factor)`` and remove loops by id (and append the frames given to
        :meth:`extend`); then relinearise to convergence, or (``relinearize=False``) not.

        Raises:
            VerificationError: a loop id added twice, removed while absent, or referencing a
                frame outside the graph.
            OptimisationFailed: iSAM2 failed.
        """
        import gtsam

        n = len(self._odom)
        factors = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        start = self._pending_from
        if start < n:
            if start == 0:
                factors.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self._odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
                values.insert(0, gtsam.Pose2(*self._odom[0]))
                first, last = 1, self._odom[0]
            else:
                first, last = start, self.estimate()[start - 1]
            steps = se2.between(self._odom[first - 1 : n - 1], self._odom[first:n])
            extended = se2.compose(last, se2.between(self._odom[first - 1], self._odom[first:n]))
            for k, (step, pose) in enumerate(zip(steps.tolist(), extended.tolist()), start=first):
                factors.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*step), self._odom_noise))
                values.insert(k, gtsam.Pose2(*pose))
        added_ids = []
        for loop_id, loop in add:
            if loop_id in self._slots or loop_id in added_ids:
                raise VerificationError(f"loop {loop_id} is already in the graph")
            if not (0 <= loop.match_frame < n and 0 <= loop.query_frame < n):
                raise VerificationError(f"loop {loop_id} references a frame outside 0..{n - 1}")
            added_ids.append(int(loop_id))
        add_loop_factors(factors, [loop for _, loop in add])
        removed = []
        for loop_id in remove:
            if loop_id not in self._slots:
                raise VerificationError(f"loop {loop_id} is not in the graph")
            removed.append(self._slots.pop(loop_id))
            self._loop_id_array = None
        if factors.size() == 0 and not removed and not relinearize:
            return
        try:
            result = self._isam.update(factors, values, removed, force_relinearize=relinearize)
            self.updates += 1
            self.relinearized += result.getVariablesRelinearized()
            new_slots = list(result.getNewFactorsIndices())
            if values.size() or result.getVariablesRelinearized():
                self._linearization = None
            for _ in range(self.max_relinearizations if relinearize and result.getVariablesRelinearized() else 0):
                again = self._isam.update(force_relinearize=True)
                self.updates += 1
                self.relinearized += again.getVariablesRelinearized()
                if again.getVariablesRelinearized() == 0:
                    break
                self._linearization = None
        except RuntimeError as exc:
            if self.factorization == "QR" or "Indeterminate" not in str(exc):
                raise OptimisationFailed(f"iSAM2 update failed: {_first_line(exc)}") from exc
            self._refactor_qr(add, remove, relinearize)
            return
        offset = factors.size() - len(added_ids)  # the odometry factors come first
        self.version += 1
        for k, (loop_id, (_, loop)) in enumerate(zip(added_ids, add)):
            self._slots[loop_id] = int(new_slots[offset + k])
            self._loops[loop_id] = loop
            self._added_at[loop_id] = self.version
        self._loop_id_array = None
        for loop_id in remove:
            self._loops.pop(loop_id, None)
            self._lost.append((self._added_at.pop(int(loop_id)), self.version))
        self._pending_from = n
        self._estimate = None

    def _refactor_qr(self, add: Sequence[tuple[int, "LoopFactor"]], remove: Sequence[int], relinearize: bool) -> None:
        """Redo a change that iSAM2's Cholesky factorisation called indeterminate with QR, from
        scratch. Cholesky squares the condition number: odometry declared far stiffer across than
        along the road (wheel odometry; ringCity re-weighted to 1.6 mm sideways and 0.011 rad of
        yaw per step, 50 mm along it) fails it on a plain chain of 300 frames, which QR solves. QR is
        slower, so it is used from then on only by graphs that need it."""
        log.info("pose graph: iSAM2's Cholesky factorisation failed; refactoring with QR")
        self._params.setFactorization("QR")
        self.factorization = "QR"
        gone = {int(i) for i in remove}
        loops = {k: v for k, v in self._loops.items() if k not in gone}
        loops.update({int(k): v for k, v in add})
        n = len(self._odom)
        known = self._last_estimate[: min(len(self._last_estimate), n)]
        if len(known) == 0:
            initial = self._odom.copy()
        else:  # the frames after the last estimate extended by odometry from it
            tail = se2.compose(known[-1], se2.between(self._odom[len(known) - 1], self._odom[len(known):]))
            initial = np.concatenate([known, tail])
        self.restart(initial, loops=list(loops.items()))
        if relinearize:
            self.update(relinearize=True)

    def restart(self, initial: np.ndarray, loops: Sequence[tuple[int, "LoopFactor"]] | None = None) -> None:
        """Rebuild the iSAM2 state from scratch with the same factors, linearised at ``initial``
        (``(N, 3)``, e.g. an earlier estimate of the same loop set): a way back to a known
        solution after changes that relinearised far away from it.

        ``loops`` ``(id, factor)``, if given, replace the loops first: a graph built at a known
        solution in one batch elimination (adding them by :meth:`update` first would eliminate
        the whole graph once more, at a linearisation point the restart throws away)."""
        import gtsam

        initial = check_poses(initial, "initial")
        n = len(self._odom)
        if len(initial) != n:
            raise VerificationError(f"restart needs {n} poses, got {len(initial)}")
        if loops is not None:
            replaced: dict[int, LoopFactor] = {}
            for loop_id, loop in loops:
                if int(loop_id) in replaced:
                    raise VerificationError(f"loop {loop_id} is given twice")
                if not (0 <= loop.match_frame < n and 0 <= loop.query_frame < n):
                    raise VerificationError(f"loop {loop_id} references a frame outside 0..{n - 1}")
                replaced[int(loop_id)] = loop
            self._loops = replaced
        loops = sorted(self._loops.items())
        self._isam = gtsam.ISAM2(self._params)
        self.epoch = next(_EPOCHS)
        self._slots, self._loops = {}, {}
        self._loop_id_array = None
        self._pending_from, self._estimate, self._linearization = 0, None, None
        factors = gtsam.NonlinearFactorGraph()
        factors.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self._odom[0]), gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
        steps = se2.between(self._odom[:-1], self._odom[1:])
        for k, step in enumerate(steps.tolist(), start=1):
            factors.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*step), self._odom_noise))
        add_loop_factors(factors, [loop for _, loop in loops])
        try:
            result = self._isam.update(factors, initial_values(initial), [], force_relinearize=True)
            self.updates += 1
            self.relinearized += result.getVariablesRelinearized()
        except RuntimeError as exc:
            raise OptimisationFailed(f"iSAM2 restart failed: {_first_line(exc)}") from exc
        new_slots = list(result.getNewFactorsIndices())
        offset = factors.size() - len(loops)
        self.version += 1
        self._added_at, self._lost = {}, []
        for k, (loop_id, loop) in enumerate(loops):
            self._slots[loop_id] = int(new_slots[offset + k])
            self._loops[loop_id] = loop
            self._added_at[loop_id] = self.version
        self._loop_id_array = None
        self._pending_from = n

    def checkpoint(self) -> "GraphCheckpoint":
        """The graph as it is now, for :meth:`rollback`: a copy of iSAM2's state (its Bayes tree
        cloned clique by clique, the conditionals shared; a few milliseconds on 2,000 poses) and
        of the bookkeeping around it."""
        import gtsam

        return GraphCheckpoint(
            isam=gtsam.ISAM2(self._isam),
            epoch=self.epoch,
            version=self.version,
            frames=len(self._odom),
            pending_from=self._pending_from,
            factorization=self.factorization,
            slots=dict(self._slots),
            loops=dict(self._loops),
            added_at=dict(self._added_at),
            lost=list(self._lost),
            estimate=None if self._estimate is None else self._estimate.copy(),
            linearization=self._linearization,
            batch_marginals=self._batch_marginals if self._queried[0] == (self.epoch, self.version) else None,
        )

    def rollback(self, checkpoint: "GraphCheckpoint") -> None:
        """Put the graph back exactly as it was at ``checkpoint`` (:meth:`checkpoint`, taken in the
        current :attr:`epoch` with the same frames): the undo of a change that was solved and
        then refused. Removing its loops instead re-solves the graph from wherever the change
        took it (iSAM2 relinearises only the frames that moved past the threshold), which can
        settle in another minimum and then needs a restart from the solution before
        (:meth:`restart`): on a heavy-tailed ring of 2,000 poses (s9852) those undos (refused
        trials' removals, lost contests put back, and the restarts after them) took 3.3 s of a
        12.5 s run.

        The :attr:`version` moves on: the versions between the checkpoint and now held loops the
        graph no longer holds (:meth:`holds_loops_of` says so), while the checkpoint's and the
        earlier ones compare as before.

        Raises:
            VerificationError: the checkpoint is of another epoch or another number of frames.
        """
        if checkpoint.isam is None:
            raise VerificationError("a checkpoint serves one rollback; this one was used")
        if checkpoint.epoch != self.epoch or checkpoint.frames != len(self._odom):
            raise VerificationError(f"cannot roll back to a checkpoint of epoch {checkpoint.epoch} with {checkpoint.frames} frames (now epoch {self.epoch}, {len(self._odom)} frames)")
        if checkpoint.factorization != self.factorization:  # a QR refactor restarted iSAM2 since: rebuild it as it was
            checkpoint.isam = None
            self.restart(checkpoint.estimate if checkpoint.estimate is not None else self.estimate(), loops=list(checkpoint.loops.items()))
            return
        self._isam, checkpoint.isam = checkpoint.isam, None  # no second copy: the checkpoint is spent
        self._slots, self._loops = dict(checkpoint.slots), dict(checkpoint.loops)
        self._loop_id_array = None
        self._pending_from = checkpoint.pending_from
        self._estimate = None if checkpoint.estimate is None else checkpoint.estimate.copy()
        self._linearization = checkpoint.linearization
        if self._estimate is not None:
            self._last_estimate = self._estimate
        self.version += 1
        self._added_at = dict(checkpoint.added_at)
        # every version after the checkpoint's may have held a loop that is gone now
        self._lost = checkpoint.lost + [(checkpoint.version + 1, self.version)]
        self._queried = ((self.epoch, self.version), 0.0)
        self._batch_marginals = checkpoint.batch_marginals  # the same linear system as then

    def holds_loops_of(self, version: int) -> bool:
        """Whether the graph holds every loop it held at ``version`` (of its current
        :attr:`epoch`): none of them was removed since."""
        for added, removed in reversed(self._lost):
            if removed <= version:
                return True
            if added <= version:
                return False
        return True

    #: iSAM2's covariance queries at one version may take this many times a fresh elimination
    #: before one answers them (:meth:`_covariance_source`).
    FRESH_ELIMINATION_AFTER = 4.0

    def _covariance_source(self):
        """What answers covariance queries now: iSAM2 itself, or GTSAM ``Marginals`` of the same
        linear system (its factors linearised at iSAM2's linearisation point) eliminated afresh,
        once the queries of iSAM2's Bayes tree at this :attr:`version` have taken
        :attr:`FRESH_ELIMINATION_AFTER` times what such an elimination took last time (as one
        rents skis until the rent would have bought them).

        Why: iSAM2 orders new variables last and re-eliminates only the cliques a change
        touches, so a change can leave a tree with far more fill than a fresh ordering gives
        (on a heavy-tailed ring of 2,000 poses, s9852: 282,009 non-zeros after one trial
        against 80,000 before and after), and a joint marginal of two frames in it takes up to
        2.2 s (the shortcuts of their cliques to the root, recomputed after every change);
        ``Marginals`` of the same system take 20 ms to build and a millisecond a query. The
        two agree to 1e-9 (relative), so which one answers changes no verdict; only the time
        taken to reach it. On that ring the covariance queries took 11 s of a 25 s run before,
        1 s now. On grouped city10000 the tree stays lean, a fresh elimination costs 0.1 to
        0.5 s and saves little: four times its cost (rather than once) keeps the queries there
        with iSAM2 but at 4 versions (18 with once)."""
        key = (self.epoch, self.version)
        if self._queried[0] != key:
            self._queried, self._batch_marginals = (key, 0.0), None
        if self._batch_marginals is not None:
            return self._batch_marginals
        if self._queried[1] <= self.FRESH_ELIMINATION_AFTER * self._elimination_s or self.factorization != "CHOLESKY":
            return self._isam
        import gtsam

        start = time.perf_counter()
        try:
            theta = self._isam.getLinearizationPoint()
            marginals = gtsam.Marginals(self._isam.getFactorsUnsafe().linearize(theta), theta)
        except RuntimeError as exc:  # iSAM2 answers (or raises) as before, for the rest of this version
            log.debug("pose graph: a fresh elimination for covariances failed (%s)", _first_line(exc))
            self._queried = (key, -np.inf)  # no time spent at it reaches the threshold again
            return self._isam
        self._elimination_s = time.perf_counter() - start
        self._batch_marginals = marginals
        return marginals

    def _ask_covariances(self, ask: Callable[[object], T]) -> T:
        """``ask(source)`` of :meth:`_covariance_source`, counting the time of what iSAM2 answers."""
        source = self._covariance_source()
        start = time.perf_counter()
        try:
            return ask(source)
        finally:
            if source is self._isam:
                key, spent = self._queried
                self._queried = (key, spent + time.perf_counter() - start)

    def marginal_covariance(self, frame: int) -> np.ndarray:
        """``(3, 3)`` marginal covariance of frame ``frame`` (right perturbation at its estimate),
        from iSAM2's Bayes tree (cheap for recent frames, near the root) or a fresh elimination
        of the same system (:meth:`_covariance_source`)."""
        try:
            return np.asarray(self._ask_covariances(lambda source: source.marginalCovariance(int(frame))), dtype=np.float64)
        except RuntimeError as exc:
            raise OptimisationFailed(f"marginal covariance of frame {frame} failed: {_first_line(exc)}") from exc

    def relative_covariance(self, match: int, query: int) -> np.ndarray:
        """``(3, 3)`` covariance of the relative pose ``x_match⁻¹ x_query`` under the graph
        (:meth:`joint_relative_covariance` of one pair)."""
        return self.joint_relative_covariance(np.array([match]), np.array([query]))

    def joint_relative_covariance(self, match: np.ndarray, query: np.ndarray) -> np.ndarray:
        """``(3L, 3L)`` joint covariance of the relative poses ``x_mₖ⁻¹ x_qₖ`` of ``L`` pairs under
        the graph, stacked in order: :meth:`joint_marginal` of their frames, transported at the
        current estimate (:meth:`transport`)."""
        frames = pair_frames(match, query)
        return self.transport(match, query, frames, self.joint_marginal(frames))

    def joint_marginal(self, frames: Sequence[int]) -> np.ndarray:
        """``(3F, 3F)`` joint marginal covariance of ``frames`` (distinct, in that order), GTSAM's
        from iSAM2's Bayes tree (costly for frames deep in the tree, and grows with the number of
        frames) or a fresh elimination of the same system (:meth:`_covariance_source`)."""
        import gtsam

        frames = [int(f) for f in frames]
        try:
            joint = self._ask_covariances(lambda source: source.jointMarginalCovariance(gtsam.KeyVector(frames)))
            return np.block([[joint.at(a, b) for b in frames] for a in frames])
        except RuntimeError as exc:
            raise OptimisationFailed(f"joint marginal of frames {frames[:4]}{' …' if len(frames) > 4 else ''} failed: {_first_line(exc)}") from exc

    def transport(self, match: np.ndarray, query: np.ndarray, frames: Sequence[int], joint: np.ndarray) -> np.ndarray:
        """``(3L, 3L)`` covariance of the relative poses ``x_mₖ⁻¹ x_qₖ`` from ``joint``, the
        :meth:`joint_marginal` of ``frames`` (which hold every ``mₖ`` and ``qₖ``), transported
        at the current estimate as in :func:`relative_covariances`."""
        match = np.asarray(match, dtype=np.int64).reshape(-1)
        query = np.asarray(query, dtype=np.int64).reshape(-1)
        at = {int(f): 3 * i for i, f in enumerate(frames)}
        x = self.estimate()
        jac = np.zeros((3 * len(match), 3 * len(at)))
        for k, (m, q) in enumerate(zip(match.tolist(), query.tolist())):
            jac[3 * k : 3 * k + 3, at[m] : at[m] + 3] = -se2.adjoint_inverse(se2.between(x[m], x[q]))
            jac[3 * k : 3 * k + 3, at[q] : at[q] + 3] += np.eye(3)
        out = jac @ joint @ jac.T
        return 0.5 * (out + out.T)

    def estimate(self) -> np.ndarray:
        """``(N', 3)`` current estimate of the frames in the graph (cached until the next update).

        iSAM2's ``calculateEstimate``, computed here: its linearisation point (fetched again only
        after a relinearisation) retracted by its delta (``Pose2.retract`` is ``Expmap``), in
        numpy. GTSAM's retracts into a new ``Values`` of every pose, which is read back pose by
        pose: grouped city10000, 312 estimates of 10k poses, 6.1 to 7.0 s -> 4.8 to 6.2 s (most
        of what is left is iSAM2's back-substitution and the copy of its delta). The two agree to
        about 1e-9 m (GTSAM's ``Expmap`` loses digits at small turns; checked in the tests)."""
        if self._estimate is None:
            import gtsam

            if self._pending_from == 0:
                return np.zeros((0, 3))
            if self._linearization is None:
                self._linearization = np.asarray(gtsam.utilities.extractPose2(self._isam.getLinearizationPoint()), dtype=np.float64)
            delta = np.asarray(self._isam.getDelta().vector(), dtype=np.float64)  # in key order: GTSAM's VectorValues is an ordered map
            if delta.shape != (3 * len(self._linearization),):
                raise OptimisationFailed(f"iSAM2 returned a delta of {delta.size} values for {len(self._linearization)} poses")
            poses = se2.compose(self._linearization, se2.expmap(delta.reshape(-1, 3)))
            if not np.isfinite(poses.sum()):
                raise OptimisationFailed("iSAM2 produced a non-finite estimate")
            self._estimate = self._last_estimate = poses
        return self._estimate


@dataclass
class GraphCheckpoint:
    """:meth:`IncrementalGraph.checkpoint`: the graph's state at one :attr:`~IncrementalGraph.version`,
    for one :meth:`~IncrementalGraph.rollback` (which takes its iSAM2 copy: ``isam`` is None after)."""

    isam: "gtsam.ISAM2 | None"
    epoch: int
    version: int
    frames: int
    pending_from: int
    factorization: str
    slots: dict[int, int]
    loops: dict[int, LoopFactor]
    added_at: dict[int, int]
    lost: list[tuple[int, int]]
    estimate: np.ndarray | None
    linearization: np.ndarray | None
    batch_marginals: object | None


def initial_values(poses: np.ndarray, keys: Sequence[int] | None = None):
    """``gtsam.Values`` with ``Pose2`` key ``keys[i]`` (default ``i``) = ``poses[i]`` for ``(N, 3)`` poses."""
    import gtsam

    poses = check_poses(poses, "poses")
    keys = range(len(poses)) if keys is None else [int(k) for k in keys]
    values = gtsam.Values()
    for k, (x, y, yaw) in zip(keys, poses.tolist()):
        values.insert(k, gtsam.Pose2(x, y, yaw))
    return values


def values_to_poses(values, num_frames: int) -> np.ndarray:
    """``(N, 3)`` array of the ``N`` ``Pose2`` values, in increasing key order."""
    import gtsam

    if num_frames == 0:
        return np.zeros((0, 3))
    poses = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64)
    if poses.shape != (num_frames, 3):
        raise OptimisationFailed(f"expected {num_frames} Pose2 values, GTSAM returned {poses.shape[0]}")
    return poses


def optimise_lm(
    graph,
    initial: np.ndarray,
    *,
    keys: Sequence[int] | None = None,
    max_iterations: int = 100,
    relative_error_tol: float = 1e-5,
) -> PoseGraphSolution:
    """Levenberg-Marquardt from ``initial`` (``(N, 3)``, e.g. the parent hypothesis' estimate).

    ``keys`` are the graph keys of the rows of ``initial`` (increasing; default ``0..N-1``); the
    solution's poses are in the same order.

    GTSAM's LM damps an indeterminant system instead of throwing; a GTSAM exception or a
    non-finite solution (overflowing information, NaN start) is reported as a failure.

    Raises:
        OptimisationFailed: GTSAM raised (e.g. an indeterminant linear system) or the solution
            is not finite.
    """
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(float(relative_error_tol))
    values = initial_values(initial, keys)
    try:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = optimizer.optimize()
    except RuntimeError as exc:
        raise OptimisationFailed(f"Levenberg-Marquardt failed: {_first_line(exc)}") from exc
    poses, error = values_to_poses(result, len(initial)), float(graph.error(result))
    _finite_solution(poses, error, "Levenberg-Marquardt")
    return PoseGraphSolution(poses, error, int(optimizer.iterations()))


def optimise_gnc_tls(
    graph,
    initial: np.ndarray,
    known_inliers: Sequence[int],
    *,
    weights_tol: float = 1e-9,
    max_iterations: int = 100,
    inlier_probability: float | None = None,
) -> tuple[PoseGraphSolution, np.ndarray]:
    """Graduated non-convexity with the truncated-least-squares loss (``gtsam.GncLMOptimizer``).

    Args:
        graph: Gaussian factors (no robust kernels); ``known_inliers`` (e.g.
            :func:`odometry_factor_indices`) are never down-weighted.
        initial: ``(N, 3)`` start.
        weights_tol: GNC stops when weights change less than this; GTSAM's default 1e-4 stops
            after 1-2 iterations on KITTI loop candidates with every weight ~1e-5, so 1e-9 runs the
            schedule to binary weights.
        inlier_probability: if given, the TLS barrier is the chi-square quantile of this
            probability (3 dof), else GTSAM's default.

    Returns:
        ``(solution, weights (F,))``: ``weights[f]`` in [0, 1] for factor ``f`` (1 = inlier).

    Raises:
        OptimisationFailed: GTSAM failed.
    """
    import gtsam

    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(list(int(i) for i in known_inliers))
    params.setWeightsTol(float(weights_tol))
    if int(max_iterations) != params.maxIterations:  # GTSAM prints a warning on every call
        params.setMaxIterations(int(max_iterations))
    values = initial_values(initial)
    try:
        optimizer = gtsam.GncLMOptimizer(graph, values, params)
        if inlier_probability is not None:
            optimizer.setInlierCostThresholdsAtProbability(float(inlier_probability))
        result = optimizer.optimize()
    except RuntimeError as exc:
        raise OptimisationFailed(f"GNC-TLS failed: {_first_line(exc)}") from exc
    weights = np.asarray(optimizer.getWeights(), dtype=np.float64)
    poses, error = values_to_poses(result, len(initial)), float(graph.error(result))
    _finite_solution(poses, error, "GNC-TLS")
    return PoseGraphSolution(poses, error, None), weights


# ----------------------------------------------------------------------------------------------



def _first_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return " ".join(lines[:2]) if lines else type(exc).__name__


def _finite_solution(poses: np.ndarray, error: float, what: str) -> None:
    if not (np.all(np.isfinite(poses)) and np.isfinite(error)):
        raise OptimisationFailed(f"{what} produced a non-finite solution (error {error})")
