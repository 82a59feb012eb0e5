"""Verification configuration: the paper's hypothesize-and-verify defaults (Tanaka, SII 2016)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal

from lcv_replay.errors import require, require_seed

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np


@dataclass(frozen=True)
class BaselineConfig:
    """Parameters of the baseline verifiers (``none``, ``ir-only``, ``dcs``, ``gm``, ``cauchy``,
    ``gnc``, ``oracle``; lcv_replay.verification.baselines)."""

    solve_every: Literal["window", "end"] = "end"  # "end": one batch solve in result() (the classic set-up); "window": re-solve at every window end so a replay shows it evolving (about 3x the time on KITTI 00; GNC on Manhattan-1000 takes minutes per solve)
    accept_chi2: float = 7.81  # accept a loop whose whitened chi2 at the solution is below chi2(3 dof, 0.95)
    dcs_phi: float = 100.0  # DCS Φ; Φ = 1 accepts nothing on robustslam_kitti (docs/verification-bench.md)
    gm_c: float = 10.0  # Geman-McClure c (c² = 100); c = 1 accepts nothing on robustslam_kitti
    cauchy_c: float = 1.0  # Cauchy c
    gnc_weights_tol: float = 1e-9  # GTSAM's default 1e-4 stops GNC-TLS with every weight ~1e-5
    gnc_accept_weight: float = 0.5  # accept a loop whose final GNC weight exceeds this
    ir_only_count: int = 10  # X: constraints drawn at random and all accepted (paper baseline, X in 10..50)
    max_iterations: int = 100  # Levenberg-Marquardt / GNC iteration cap

    def __post_init__(self) -> None:
        require(self.accept_chi2 > 0, "verification.baselines.accept_chi2", self.accept_chi2, "a number > 0")
        require(self.dcs_phi > 0, "verification.baselines.dcs_phi", self.dcs_phi, "a number > 0")
        require(self.gm_c > 0, "verification.baselines.gm_c", self.gm_c, "a number > 0")
        require(self.cauchy_c > 0, "verification.baselines.cauchy_c", self.cauchy_c, "a number > 0")
        require(0 < self.gnc_weights_tol < 1, "verification.baselines.gnc_weights_tol", self.gnc_weights_tol, "a number in (0, 1)")
        require(0 < self.gnc_accept_weight < 1, "verification.baselines.gnc_accept_weight", self.gnc_accept_weight, "a number in (0, 1)")
        require(self.ir_only_count >= 1, "verification.baselines.ir_only_count", self.ir_only_count, "an integer >= 1")
        require(self.max_iterations >= 1, "verification.baselines.max_iterations", self.max_iterations, "an integer >= 1")


@dataclass(frozen=True)
class IlvPlusConfig:
    """Parameters of ``ilv+``, the improved verifier; not in the paper. It is two verifiers, one
    per kind of loop (``loops``):

    * **measured** loops, each with a relative pose (g2o graphs, geometric verification): the
      cluster-consensus verifier (lcv_replay.verification.consensus) verifies clusters of
      pairwise-consistent loops against an iSAM2 working hypothesis (the innovation of each
      cluster), contests conflicting clusters by the truncated-least-squares cost and flags the
      undecided ones as ambiguous;
    * **same-place** loops, without a relative pose (our image retrieval): the hypothesis-table
      verifier (lcv_replay.verification.ilv, ``PlusModel``) keeps the paper's incremental
      multi-hypothesis structure with a Mahalanobis test under each hypothesis' uncertainty, ranking
      by truncated-least-squares cost and consensus refinement.

    Both calibrate their gate to the noise the data show (``calibrate_gate``;
    verification.noise_scale).
    """

    loops: Literal["auto", "measured", "same-place"] = "auto"  # auto: the replay decides by where the loops come from (retrieval: same-place; the log's candidates: measured), the bench by whether any carries a relative pose
    gate_chi2: float = 11.34  # chi-square gate on one loop's innovation until calibrated (3 dof, 0.99; GTSAM GNC-TLS default inlier threshold)
    min_loop_gap_frames: int = 0  # drop candidates closer in time (retrieval already excludes Δt, sec. II-B)
    calibrate_gate: bool = True  # calibrate the gate (and, for measured loops, the loops' weight) to the noise the data show (verification.noise_scale); gate_chi2 holds until then
    calibration_min_loops: int = 30  # statistics needed before a fit (same-place: loops of the best hypothesis; measured: innovations, or clusters contributing pairwise cycles, which may widen the gate from fewer)
    calibration_sample_loops: int = 2000  # at most this many statistics are fitted per window
    calibrated_max_chi2: float = 16.27  # a heavy-tailed fit may widen the gate up to this (3 dof, 0.999); measured loops: or to the fit's Gaussian quantile if larger
    calibration_confidence: float = 0.9999  # the calibrated gate is this quantile of the fitted statistic (of 2,000 true loops, 0.2 expected beyond it)
    # same-place loops (the hypothesis-table verifier)
    explore_chi2: float = 113.4  # sequential selection never draws a constraint with innovation beyond 10 x gate (a cheap bound screens those out)
    closure_rounds: int = 2  # consensus refinement rounds per drawn hypothesis (0 = the paper's child)
    iterations_per_window: int = 3  # sec. II-D uses 10 x 10; consensus refinement needs far fewer children
    hypotheses_per_iteration: int = 5
    max_hypotheses: int = 50  # kept hypotheses (the paper's bound is 200); each costs a column test per window
    # measured loops (the cluster-consensus verifier)
    cluster_span_frames: int = 10  # loops whose query and match frames both lie within this many frames are tested pairwise and clustered
    ambiguity_margin: float = 1.0  # a contest within this many gates of truncated cost is undecided: both sides are flagged ambiguous
    count_ambiguity_margin: float = 10.0  # at the end of the log, a revisit the final map holds only on the truncated cost, and by fewer gates than this, is flagged ambiguous
    max_contests_per_window: int = 20  # alternative hypotheses solved per window (bounds the cost of a window)
    frontier_min_loops: int = 3  # a smaller cluster beyond every accepted loop waits one window for support (decided at the end of the log)

    def __post_init__(self) -> None:
        require(self.loops in ("auto", "measured", "same-place"), "verification.ilv_plus.loops", self.loops, "'auto', 'measured' or 'same-place'")
        require(self.gate_chi2 > 0, "verification.ilv_plus.gate_chi2", self.gate_chi2, "a number > 0")
        require(self.explore_chi2 >= self.gate_chi2, "verification.ilv_plus.explore_chi2", self.explore_chi2, "a number >= gate_chi2")
        require(self.min_loop_gap_frames >= 0, "verification.ilv_plus.min_loop_gap_frames", self.min_loop_gap_frames, "an integer >= 0")
        require(self.closure_rounds >= 0, "verification.ilv_plus.closure_rounds", self.closure_rounds, "an integer >= 0")
        require(self.iterations_per_window >= 1, "verification.ilv_plus.iterations_per_window", self.iterations_per_window, "an integer >= 1")
        require(self.hypotheses_per_iteration >= 1, "verification.ilv_plus.hypotheses_per_iteration", self.hypotheses_per_iteration, "an integer >= 1")
        require(self.max_hypotheses >= self.hypotheses_per_iteration, "verification.ilv_plus.max_hypotheses", self.max_hypotheses, "an integer >= hypotheses_per_iteration")
        require(self.calibration_min_loops >= 10, "verification.ilv_plus.calibration_min_loops", self.calibration_min_loops, "an integer >= 10")
        require(self.calibration_sample_loops >= self.calibration_min_loops, "verification.ilv_plus.calibration_sample_loops", self.calibration_sample_loops, "an integer >= calibration_min_loops")
        require(self.calibrated_max_chi2 >= self.gate_chi2, "verification.ilv_plus.calibrated_max_chi2", self.calibrated_max_chi2, "a number >= gate_chi2")
        require(0.5 < self.calibration_confidence < 1.0, "verification.ilv_plus.calibration_confidence", self.calibration_confidence, "a number in (0.5, 1)")
        require(self.cluster_span_frames >= 1, "verification.ilv_plus.cluster_span_frames", self.cluster_span_frames, "an integer >= 1")
        require(self.ambiguity_margin >= 0, "verification.ilv_plus.ambiguity_margin", self.ambiguity_margin, "a number >= 0")
        require(self.count_ambiguity_margin >= self.ambiguity_margin, "verification.ilv_plus.count_ambiguity_margin", self.count_ambiguity_margin, "a number >= ambiguity_margin")
        require(self.frontier_min_loops >= 1, "verification.ilv_plus.frontier_min_loops", self.frontier_min_loops, "an integer >= 1")
        require(self.max_contests_per_window >= 0, "verification.ilv_plus.max_contests_per_window", self.max_contests_per_window, "an integer >= 0")


@dataclass(frozen=True)
class VerificationConfig:
    """Multi-model hypothesize-and-verify (method ``ilv``) and its improved variant ``ilv+``."""

    method: str = "ilv+"  # verifier name (registry); ilv+ measures better than the paper's ilv (docs/verification-bench.md)
    consistency_radius_m: float = 10.0  # T_p: constraint consistent if endpoints closer (sec. II-A)
    window_frames: int = 500  # W: time-window length in frames (sec. II-D)
    iterations_per_window: int = 10  # generation iterations per window (sec. II-D)
    hypotheses_per_iteration: int = 10  # top-ranked hypotheses extended per iteration (sec. II-D)
    max_hypotheses: int = 200  # pruning bound on kept hypotheses
    seed: int = 0
    # Pose-graph noise where the input carries none (not in the paper; g2o logs carry both):
    odometry_sigmas: tuple[float, float, float] = (0.05, 0.05, 0.002)  # per-frame odometry sigma [m, m, rad], ~libviso2 at 10 Hz
    loop_sigmas: tuple[float, float, float] = (2.0, 2.0, 0.2)  # identity "same place" loop [m, m, rad]: same place, not same pose (sec. II-A)
    top_k_trajectories: int = 10  # trajectories of the top-ranked hypotheses carried by each step (for sinks: the map and the paper's Fig. V)
    max_iterations: int = 100  # Levenberg-Marquardt iteration cap per hypothesis
    ilv_plus: IlvPlusConfig = field(default_factory=IlvPlusConfig)  # the improved verifier
    baselines: BaselineConfig = field(default_factory=BaselineConfig)  # baseline verifiers

    def __post_init__(self) -> None:
        require(self.consistency_radius_m > 0, "verification.consistency_radius_m", self.consistency_radius_m, "a number > 0")
        require(self.window_frames >= 1, "verification.window_frames", self.window_frames, "an integer >= 1")
        require(self.iterations_per_window >= 1, "verification.iterations_per_window", self.iterations_per_window, "an integer >= 1")
        require(self.hypotheses_per_iteration >= 1, "verification.hypotheses_per_iteration", self.hypotheses_per_iteration, "an integer >= 1")
        require(self.max_hypotheses >= self.hypotheses_per_iteration, "verification.max_hypotheses", self.max_hypotheses, "an integer >= hypotheses_per_iteration")
        require_seed(self.seed, "config key 'verification.seed'")
        require(self.top_k_trajectories >= 1, "verification.top_k_trajectories", self.top_k_trajectories, "an integer >= 1")
        require(self.max_iterations >= 1, "verification.max_iterations", self.max_iterations, "an integer >= 1")
        require(all(s > 0 for s in self.odometry_sigmas), "verification.odometry_sigmas", self.odometry_sigmas, "three numbers > 0 [m, m, rad]")
        require(all(s > 0 for s in self.loop_sigmas), "verification.loop_sigmas", self.loop_sigmas, "three numbers > 0 [m, m, rad]")

    def odometry_information_matrix(self) -> "np.ndarray":
        """``(3, 3)`` information of one odometry step from :attr:`odometry_sigmas`."""
        import numpy as np

        return np.diag(1.0 / np.square(np.asarray(self.odometry_sigmas, dtype=np.float64)))

    def loop_information_matrix(self) -> "np.ndarray":
        """``(3, 3)`` information of a loop candidate that carries none, from :attr:`loop_sigmas`."""
        import numpy as np

        return np.diag(1.0 / np.square(np.asarray(self.loop_sigmas, dtype=np.float64)))


def with_loop_kind(config: VerificationConfig, *, same_place: bool) -> VerificationConfig:
    """``config`` with ``ilv_plus.loops`` decided where it is ``auto``: ``same-place`` when the
    loops carry no relative pose (``same_place``), else ``measured``."""
    if config.ilv_plus.loops != "auto":
        return config
    return replace(config, ilv_plus=replace(config.ilv_plus, loops="same-place" if same_place else "measured"))
