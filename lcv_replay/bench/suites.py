"""Benchmark suites: named sets of cases (logs built by the g2o recorder) and methods.

Built-in suites:

``standard``
    ``robustslam_kitti`` sequences 00, 02, 05, 06, 07 × alphas 0.00, 0.25, 0.50, 0.75, 1.00 (with
    ground truth and true-loop labels; 25 cases) plus Vertigo Manhattan (M3500, with its ground
    truth) spoiled with 100 and 1000 false loops in random, local and group modes (6 cases).
``vertigo``
    The other public Vertigo 2-D benchmarks spoiled the same way: ring (100 outliers), ringCity
    (100 and 500), Intel (100 and 200), each in random, local and group modes, and city10000
    (10,000 poses) with 1,000 random and 1,000 grouped outliers (17 cases).
``generated``
    Generated worlds (:mod:`lcv_replay.bench.worlds`): grid and ring cities × Gaussian,
    heavy-tailed and mis-declared noise × random, local and group outliers, at 1,000 poses with
    100 outliers, 2,000 with 500 and 2,500 with 1,000 (54 cases), plus 5,000 and 10,000 poses with
    1,000 outliers (6 cases); 60 cases, each seeded.
``extended``
    ``standard`` + ``vertigo`` + ``generated`` (108 cases).
``regressions``
    The generated worlds on which ``ilv+`` once accepted false loops or missed the bar, or still
    does (71 of 2,000 poses, two of 5,000), run with ``ilv+``, GNC-TLS, DCS and the oracle.
``quick``
    A CI subset: ``robustslam_kitti`` 06 at alpha 0.50 and 07 at alpha 0.00.

Every case that injects outliers or generates a world is seeded; :func:`with_seeds` redraws it
for other seeds (``bench suite --seeds N``), one case per seed.

A suite file (TOML) names its cases and optionally methods and other suites to include::

    name = "hard-cases"                     # default: the file's stem
    description = "where robust back ends fail"
    methods = ["gnc", "ilv", "ilv+"]         # default: every registered method (see DEFAULT_METHODS)
    include = ["quick"]                      # built-in names or TOML files (relative to this file)

    [[robustslam_kitti]]                     # expands to sequences × alphas
    sequences = ["02", "07"]
    alphas = ["0.00", "0.50"]
    loop_measurements = "as-recorded"        # or "same-place": drop the g2o relative poses

    [[vertigo]]                              # expands to outliers × modes
    dataset = "manhattan"
    outliers = [100, 1000]
    modes = ["random", "local", "group"]
    group_size = 10
    seed = 0

    [[world]]                                # generated worlds: layouts x poses x noise x modes x outliers x seeds
    layouts = ["grid", "ring"]
    poses = [2000]
    noise = ["gaussian", "heavy", "misdeclared"]
    modes = ["group"]
    outliers = [500]
    seeds = [0, 1]
    group_size = 10

    [[case]]                                 # any 2-D pose graph
    name = "my-graph"
    graph = "vertigo/intel/originalDataset/intel.g2o"   # relative to the data folder, or absolute
    ground_truth = "..."                     # optional (vertices, edge chain or x y theta rows)
    true_loops = "..."                       # optional ('i j' per line)
    outliers = 100                           # optional outlier injection (Vertigo protocol)
    outlier_mode = "random"
    group_size = 10
    seed = 0
    loop_measurements = "as-recorded"

Unknown keys are refused by name.
"""

from __future__ import annotations

import difflib
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Literal, Sequence

from lcv_replay.bench.worlds import LAYOUTS, NOISE_MODELS, WorldSpec
from lcv_replay.errors import ConfigError, require_seed

LoopMeasurements = Literal["as-recorded", "same-place"]

ROBUSTSLAM_SEQUENCES = ("00", "02", "05", "06", "07")
ROBUSTSLAM_ALPHAS = ("0.00", "0.25", "0.50", "0.75", "1.00")
VERTIGO_OUTLIERS = (100, 1000)
VERTIGO_MODES = ("random", "local", "group")

#: Methods a suite runs when it names none (those registered; ``ir-only`` at its config X).
DEFAULT_METHODS = ("none", "ir-only", "dcs", "gm", "cauchy", "gnc", "oracle", "ilv", "ilv+")

#: Vertigo 2-D benchmarks: (graph, ground truth or ``None``) relative to the data folder. Their own
#: loops are all true; city10000 and Intel have no ground-truth file (no ATE).
_VERTIGO_DATASETS: dict[str, tuple[str, str | None]] = {
    "manhattan": (
        "vertigo/manhattan/originalDataset/g2o/manhattanOlson3500.g2o",
        "vertigo/manhattan/groundTruth/manhattanOlson3500_nodes_groundTruth.dat",
    ),
    "ring": ("vertigo/ring/originalDataset/ring.g2o", "vertigo/ring/groundTruth/ring.g2o"),
    "ringCity": ("vertigo/ringCity/originalDataset/ringCity.g2o", "vertigo/ringCity/groundTruth/ringCity.g2o"),
    "city10000": ("vertigo/city10000/originalDataset/city10000.g2o", None),
    "intel": ("vertigo/intel/originalDataset/intel.g2o", None),
}


@dataclass(frozen=True)
class SuiteCase:
    """One log of a suite, built by the g2o recorder.

    Paths are relative to the data folder unless absolute. ``outliers = 0`` injects none. A case
    with a ``world`` has no files: the world is generated into the suite's work folder
    (:mod:`lcv_replay.bench.worlds`), then recorded like any graph; ``seed`` seeds the outliers
    (and ``world.seed`` the world).
    """

    name: str
    graph: str = ""
    ground_truth: str | None = None
    true_loops: str | None = None
    outliers: int = 0
    outlier_mode: str = "random"
    group_size: int = 10
    seed: int = 0
    loop_measurements: LoopMeasurements = "as-recorded"
    world: WorldSpec | None = None

    def __post_init__(self) -> None:
        if bool(self.graph) == (self.world is not None):
            raise ConfigError(f"suite case '{self.name}' needs a graph file or a generated world (exactly one)")

    @property
    def seeded(self) -> bool:
        """Whether the case depends on a seed (it injects outliers or generates a world)."""
        return self.outliers > 0 or self.world is not None

    def with_seed(self, seed: int) -> "SuiteCase":
        """The same case drawn with another seed (world and outliers); the name ends in ``-s<seed>``."""
        base = self.name[: -len(f"-s{self.seed}")] if self.name.endswith(f"-s{self.seed}") else self.name
        world = replace(self.world, seed=seed) if self.world is not None else None
        return replace(self, name=f"{base}-s{seed}", seed=seed, world=world)

    def resolve(self, data_dir: Path, relative: str | None) -> Path | None:
        """A case path resolved against ``data_dir``."""
        if relative is None:
            return None
        path = Path(relative)
        return path if path.is_absolute() else data_dir / path


@dataclass(frozen=True)
class Suite:
    """A named list of cases and the methods to run on each (``()`` = :data:`DEFAULT_METHODS`)."""

    name: str
    cases: tuple[SuiteCase, ...]
    methods: tuple[str, ...] = ()
    description: str = ""


# ---------------------------------------------------------------------------------------------
# Case generators
# ---------------------------------------------------------------------------------------------


def robustslam_cases(
    sequences: Iterable[str] = ROBUSTSLAM_SEQUENCES,
    alphas: Iterable[str] = ROBUSTSLAM_ALPHAS,
    *,
    loop_measurements: LoopMeasurements = "as-recorded",
) -> tuple[SuiteCase, ...]:
    """``robustslam_kitti`` sequence × alpha cases, with ground truth and true-loop labels."""
    cases = []
    for seq in sequences:
        for alpha in alphas:
            base = f"robustslam_kitti/{seq}/kitti_{seq}"
            suffix = "" if loop_measurements == "as-recorded" else "-same-place"
            cases.append(
                SuiteCase(
                    name=f"kitti{seq}-a{alpha}{suffix}",
                    graph=f"{base}_alpha_{alpha}.g2o",
                    ground_truth=f"{base}_GT.g2o",
                    true_loops=f"{base}_alpha_{alpha}_GT_LC.txt",
                    loop_measurements=loop_measurements,
                )
            )
    return tuple(cases)


def vertigo_cases(
    dataset: str = "manhattan",
    outliers: Iterable[int] = VERTIGO_OUTLIERS,
    modes: Iterable[str] = VERTIGO_MODES,
    *,
    group_size: int = 10,
    seed: int = 0,
) -> tuple[SuiteCase, ...]:
    """A Vertigo dataset spoiled with ``outliers`` false loops in each mode (its loops labelled true)."""
    if dataset not in _VERTIGO_DATASETS:
        raise ConfigError(f"unknown vertigo dataset '{dataset}'", fix=f"use one of {', '.join(_VERTIGO_DATASETS)}")
    outliers, modes = tuple(outliers), tuple(modes)
    for mode in modes:
        _check_mode(mode)
    graph, ground_truth = _VERTIGO_DATASETS[dataset]
    return tuple(
        SuiteCase(
            name=f"{dataset}-{mode}-{count}",
            graph=graph,
            ground_truth=ground_truth,
            outliers=int(count),
            outlier_mode=mode,
            group_size=group_size,
            seed=seed,
        )
        for count in outliers
        for mode in modes
    )


def world_cases(
    layouts: Iterable[str] = LAYOUTS,
    poses: Iterable[int] = (2000,),
    noise: Iterable[str] = NOISE_MODELS,
    modes: Iterable[str] = VERTIGO_MODES,
    outliers: Iterable[int] = (500,),
    seeds: Iterable[int] = (0,),
    *,
    group_size: int = 10,
) -> tuple[SuiteCase, ...]:
    """Generated worlds (layouts × poses × noise) spoiled by ``outliers`` in each mode, per seed;
    named ``<layout>-<poses>-<noise>-<mode>-<outliers>-s<seed>``, the mode ``group<n>`` where
    groups are not of 10 (``ring-2k-heavy-group20-400-s9804``)."""
    layouts, poses, noise, modes, outliers, seeds = (tuple(v) for v in (layouts, poses, noise, modes, outliers, seeds))
    cases = []
    for layout in layouts:
        for n in poses:
            for model in noise:
                for mode in modes:
                    _check_mode(mode)
                    for count in outliers:
                        for seed in seeds:
                            world = WorldSpec(layout=layout, poses=int(n), noise=model, seed=int(seed))  # type: ignore[arg-type]
                            size = world.name.split("-")[1]
                            label = f"{mode}{group_size}" if mode == "group" and group_size != 10 else mode
                            cases.append(
                                SuiteCase(
                                    name=f"{layout}-{size}-{model}-{label}-{count}-s{seed}",
                                    outliers=int(count),
                                    outlier_mode=mode,
                                    group_size=group_size,
                                    seed=int(seed),
                                    world=world,
                                )
                            )
    return tuple(cases)


def _check_mode(mode: str) -> None:
    if mode not in VERTIGO_MODES:
        raise ConfigError(f"unknown outlier mode '{mode}'", fix=f"use one of {', '.join(VERTIGO_MODES)}")


def _generated_cases() -> tuple[SuiteCase, ...]:
    """The built-in ``generated`` suite: every layout × noise × mode at three sizes (54 cases), and
    6 larger worlds. The seeds are fixed (1 to 5; the development set used seeds 100 and up);
    ``--seeds N`` redraws them."""
    cases: list[SuiteCase] = []
    for poses, count, seed in ((1000, 100, 1), (2000, 500, 2), (2500, 1000, 3)):
        cases.extend(world_cases(poses=[poses], outliers=[count], seeds=[seed]))
    cases.extend(world_cases(poses=[5000], noise=["gaussian", "misdeclared"], modes=["random", "group"], outliers=[1000], seeds=[4], layouts=["grid"]))
    cases.extend(world_cases(poses=[10000], noise=["gaussian"], modes=["random"], outliers=[1000], seeds=[5], layouts=["ring"]))
    cases.extend(world_cases(poses=[10000], noise=["heavy"], modes=["group"], outliers=[1000], seeds=[5], layouts=["ring"]))
    return tuple(cases)


def _regression_cases() -> tuple[SuiteCase, ...]:
    """The built-in ``regressions`` suite: the generated worlds on which ``ilv+`` once went wrong
    (drawn fresh at a development stop, fixed at that or a later one) or still misses the bar
    (docs/verification-bench.md, each stop's "Where issue 16 stands"). The unit tests keep one
    world per fix (tests/verification/test_consensus.py); this suite holds every one of them."""
    heavy_rings = {
        10: (9102, 9104, 9207, 9300, 9302, 9308, 9404, 9420, 9421, 9900, 9903, 10301, 10612, 10712, 11008, 11023, 11803,
             11804, 12008, 12219, 12805, 13503, 13511, 13514, 13556, 13587, 13663, 13687, 13746, 14034, 14355, 14390),
        20: (9804, 9805, 9852, 11604, 12708, 13201, 13518, 13529, 13597, 13609, 13633, 13653, 13704, 13728, 14204, 14416),
        5: (9755, 10407),
    }
    heavy_grids = {10: (11911, 13520, 13559, 13565, 13611, 13731), 20: (12905, 13585, 13588, 13712, 14043)}
    cases: list[SuiteCase] = []
    for layout, by_size in (("ring", heavy_rings), ("grid", heavy_grids)):
        for size, seeds in by_size.items():
            cases.extend(world_cases([layout], [2000], ["heavy"], ["group"], [400], seeds, group_size=size))
    cases.extend(world_cases(["ring"], [2000], ["misdeclared"], ["group"], [400], [12400, 13718]))
    cases.extend(world_cases(["ring"], [2000], ["anisotropic"], ["group"], [400], [13695]))
    cases.extend(world_cases(["ring"], [2000], ["anisotropic"], ["group"], [500], [305]))
    cases.extend(world_cases(["grid"], [2000], ["anisotropic"], ["group"], [400], [12464, 12465, 13634, 13635]))
    cases.extend(world_cases(["ring"], [5000], ["heavy"], ["group"], [1000], [9007]))
    cases.extend(world_cases(["ring"], [5000], ["heavy"], ["local"], [1000], [13338]))  # a slip placed by refused loops
    cases.extend(world_cases(["ring"], [2000], ["heavy"], ["local"], [400], [13923]))  # a revisit beside a slip, once flagged on the count
    cases.extend(world_cases(["grid"], [2000], ["heavy"], ["local"], [400], [14099]))  # a revisit with slips inside its stretches, once flagged
    return tuple(cases)


_VERTIGO_SUITE = (
    vertigo_cases("ring", [100])
    + vertigo_cases("ringCity", [100, 500])
    + vertigo_cases("intel", [100, 200])
    + vertigo_cases("city10000", [1000], ["random", "group"])
)

BUILTIN_SUITES: dict[str, Suite] = {
    "standard": Suite(
        "standard",
        robustslam_cases() + vertigo_cases(),
        description="robustslam_kitti 00/02/05/06/07 x 5 alphas + Manhattan with 100/1000 random/local/group outliers",
    ),
    "vertigo": Suite(
        "vertigo",
        _VERTIGO_SUITE,
        description="Vertigo ring, ringCity, Intel and city10000 with random/local/group outliers",
    ),
    "generated": Suite(
        "generated",
        _generated_cases(),
        description="generated grid and ring cities, 1k-10k poses, Gaussian/heavy-tailed/mis-declared noise, random/local/group outliers",
    ),
    "extended": Suite(
        "extended",
        robustslam_cases() + vertigo_cases() + _VERTIGO_SUITE + _generated_cases(),
        description="standard + vertigo + generated",
    ),
    "regressions": Suite(
        "regressions",
        _regression_cases(),
        methods=("ilv+", "gnc", "dcs", "oracle"),
        description="generated worlds where ilv+ once went wrong (fixed) or still misses the bar",
    ),
    "quick": Suite(
        "quick",
        robustslam_cases(["06"], ["0.50"]) + robustslam_cases(["07"], ["0.00"]),
        description="CI subset: robustslam_kitti 06 alpha 0.50 and 07 alpha 0.00",
    ),
}


# ---------------------------------------------------------------------------------------------
# TOML
# ---------------------------------------------------------------------------------------------

_TOP_KEYS = {"name", "description", "methods", "include", "robustslam_kitti", "vertigo", "world", "case"}
_KITTI_KEYS = {"sequences", "alphas", "loop_measurements"}
_VERTIGO_KEYS = {"dataset", "outliers", "modes", "group_size", "seed"}
_WORLD_KEYS = {"layouts", "poses", "noise", "modes", "outliers", "seeds", "group_size"}
_CASE_KEYS = {"name", "graph", "ground_truth", "true_loops", "outliers", "outlier_mode", "group_size", "seed", "loop_measurements"}


def _refuse_unknown(table: dict[str, Any], known: set[str], where: str, path: Path) -> None:
    for key in table:
        if key not in known:
            close = difflib.get_close_matches(key, sorted(known), n=1)
            hint = f"did you mean '{close[0]}'?" if close else f"known keys: {', '.join(sorted(known))}"
            raise ConfigError(f"unknown suite key '{where}{key}'", path=path, fix=hint)


def _typed(value: Any, kind: type | tuple[type, ...], key: str, path: Path) -> Any:
    if isinstance(value, bool) and kind is not bool or not isinstance(value, kind):
        name = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
        raise ConfigError(f"suite key '{key}' = {value!r} must be a {name}", path=path)
    return value


def _group_size(table: dict, section: str, path: Path) -> int:
    """``group_size`` of a suite table (default 10): loops per run of grouped outliers, >= 1."""
    value = _typed(table.get("group_size", 10), int, f"{section}.group_size", path)
    if value < 1:
        raise ConfigError(f"suite key '{section}.group_size' = {value} must be >= 1", path=path, fix="set it to e.g. 10 (Vertigo's)")
    return value


def _seed(value: Any, key: str, path: Path) -> int:
    try:
        return require_seed(value, f"suite key '{key}'")
    except ConfigError as exc:
        raise ConfigError(exc.message, path=path, fix=exc.fix) from None


def _list_of(table: dict, key: str, kind: type, path: Path, default: Iterable) -> tuple:
    if key not in table:
        return tuple(default)
    values = _typed(table[key], list, key, path)
    return tuple(_typed(v, kind, key, path) for v in values)


def _measurements(value: Any, path: Path) -> LoopMeasurements:
    if value not in ("as-recorded", "same-place"):
        raise ConfigError(f"suite key 'loop_measurements' = {value!r} is not allowed", path=path, fix="use 'as-recorded' or 'same-place'")
    return value


def load_suite_file(path: str | Path, *, _seen: tuple[Path, ...] = ()) -> Suite:
    """Load a suite TOML file (format in the module docstring).

    Raises:
        ConfigError: missing file, bad TOML, unknown key, wrong type, unknown suite in ``include``,
            include cycle, or a suite without cases.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError("suite file not found", path=path, fix="pass a built-in suite name or an existing TOML file")
    resolved = path.resolve()
    if resolved in _seen:
        raise ConfigError("suite files include each other in a cycle", path=path, fix="remove one of the includes")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"not valid TOML: {exc}", path=path, fix="fix the syntax") from None
    _refuse_unknown(data, _TOP_KEYS, "", path)
    try:
        return _suite_from_tables(data, path, (*_seen, resolved))
    except ConfigError as exc:  # a world, mode or included suite refused without naming this file
        if exc.path is not None:
            raise
        raise ConfigError(exc.message, path=path, fix=exc.fix) from None


def _suite_from_tables(data: dict, path: Path, seen: tuple[Path, ...]) -> Suite:
    """The :class:`Suite` of a parsed suite file ``path`` (:func:`load_suite_file`)."""
    cases: list[SuiteCase] = []
    methods: tuple[str, ...] = _list_of(data, "methods", str, path, ())
    for name in _list_of(data, "include", str, path, ()):
        included = get_suite(name, base_dir=path.parent, _seen=seen)
        cases.extend(included.cases)
        methods = methods or included.methods
    for table in _typed(data.get("robustslam_kitti", []), list, "robustslam_kitti", path):
        _refuse_unknown(_typed(table, dict, "robustslam_kitti", path), _KITTI_KEYS, "robustslam_kitti.", path)
        cases.extend(
            robustslam_cases(
                _list_of(table, "sequences", str, path, ROBUSTSLAM_SEQUENCES),
                _list_of(table, "alphas", str, path, ROBUSTSLAM_ALPHAS),
                loop_measurements=_measurements(table.get("loop_measurements", "as-recorded"), path),
            )
        )
    for table in _typed(data.get("vertigo", []), list, "vertigo", path):
        _refuse_unknown(_typed(table, dict, "vertigo", path), _VERTIGO_KEYS, "vertigo.", path)
        cases.extend(
            vertigo_cases(
                _typed(table.get("dataset", "manhattan"), str, "vertigo.dataset", path),
                _list_of(table, "outliers", int, path, VERTIGO_OUTLIERS),
                _list_of(table, "modes", str, path, VERTIGO_MODES),
                group_size=_group_size(table, "vertigo", path),
                seed=_seed(table.get("seed", 0), "vertigo.seed", path),
            )
        )
    for table in _typed(data.get("world", []), list, "world", path):
        _refuse_unknown(_typed(table, dict, "world", path), _WORLD_KEYS, "world.", path)
        cases.extend(
            world_cases(
                _list_of(table, "layouts", str, path, LAYOUTS),
                _list_of(table, "poses", int, path, (2000,)),
                _list_of(table, "noise", str, path, NOISE_MODELS),
                _list_of(table, "modes", str, path, VERTIGO_MODES),
                _list_of(table, "outliers", int, path, (500,)),
                tuple(_seed(v, "world.seeds", path) for v in _list_of(table, "seeds", int, path, (0,))),
                group_size=_group_size(table, "world", path),
            )
        )
    for table in _typed(data.get("case", []), list, "case", path):
        _refuse_unknown(_typed(table, dict, "case", path), _CASE_KEYS, "case.", path)
        for required in ("name", "graph"):
            if required not in table:
                raise ConfigError(f"a [[case]] lacks '{required}'", path=path, fix="give every case a name and a graph")
        cases.append(
            SuiteCase(
                name=_typed(table["name"], str, "case.name", path),
                graph=_typed(table["graph"], str, "case.graph", path),
                ground_truth=_typed(table.get("ground_truth"), (str, type(None)), "case.ground_truth", path),
                true_loops=_typed(table.get("true_loops"), (str, type(None)), "case.true_loops", path),
                outliers=_typed(table.get("outliers", 0), int, "case.outliers", path),
                outlier_mode=_typed(table.get("outlier_mode", "random"), str, "case.outlier_mode", path),
                group_size=_group_size(table, "case", path),
                seed=_seed(table.get("seed", 0), "case.seed", path),
                loop_measurements=_measurements(table.get("loop_measurements", "as-recorded"), path),
            )
        )
    if not cases:
        raise ConfigError("the suite has no cases", path=path, fix="add [[robustslam_kitti]], [[vertigo]] or [[case]] tables, or include a suite")
    names = [c.name for c in cases]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ConfigError(f"case name '{duplicates[0]}' is used twice", path=path, fix="give every case a distinct name")
    name = _typed(data.get("name", path.stem), str, "name", path)
    description = _typed(data.get("description", ""), str, "description", path)
    return Suite(name, tuple(cases), methods, description)


def get_suite(name_or_path: str | Path, *, base_dir: Path | None = None, _seen: tuple[Path, ...] = ()) -> Suite:
    """A built-in suite by name, or a suite TOML file (relative paths against ``base_dir``)."""
    text = str(name_or_path)
    if text in BUILTIN_SUITES:
        return BUILTIN_SUITES[text]
    path = Path(text)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    if path.suffix != ".toml" and not path.exists():
        raise ConfigError(
            f"unknown suite '{text}'",
            fix=f"use one of {', '.join(BUILTIN_SUITES)} or a suite .toml file",
        )
    return load_suite_file(path, _seen=_seen)


def with_seeds(suite: Suite, seeds: Sequence[int]) -> Suite:
    """``suite`` with every seeded case (:attr:`SuiteCase.seeded`) replaced by one case per seed
    of ``seeds`` (``bench suite --seeds N``); unseeded cases (robustslam_kitti) are kept once."""
    cases: list[SuiteCase] = []
    seen: set[str] = set()
    for case in suite.cases:
        for drawn in ([case.with_seed(int(s)) for s in seeds] if case.seeded else [case]):
            if drawn.name not in seen:
                seen.add(drawn.name)
                cases.append(drawn)
    return replace(suite, cases=tuple(cases))


def with_methods(suite: Suite, methods: Iterable[str]) -> Suite:
    """``suite`` with its methods replaced (``--method`` on the command line)."""
    methods = tuple(methods)
    return replace(suite, methods=methods) if methods else suite
