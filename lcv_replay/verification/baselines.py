"""Baseline verifiers in the same :class:`~lcv_replay.verification.base.Verifier` interface as ``ilv``.

Registered methods (``--method``):

``none``
    Odometry only: nothing is accepted.
``ir-only`` (and ``ir-only-10`` .. ``ir-only-50``)
    The paper's baseline (Tanaka, SII 2016, sec. III): X constraints drawn at random from the
    history, all accepted; the trajectory is the Levenberg-Marquardt solution with them.
    ``ir-only`` uses ``verification.baselines.ir_only_count``; ``ir-only-N`` fixes X = N.
``dcs``, ``gm``, ``cauchy``
    A GTSAM robust noise model (``mEstimator.DCS`` Φ, ``GemanMcClure`` c, ``Cauchy`` c) around
    every loop factor, one batch Levenberg-Marquardt solve from the odometry; a loop is accepted
    when its whitened (Gaussian) chi-square at the solution is below ``accept_chi2`` (7.81, the
    95 % quantile of chi-square with 3 degrees of freedom).
``gnc``
    ``gtsam.GncLMOptimizer`` with the truncated-least-squares loss, the prior and odometry as
    known inliers, ``weightsTol`` 1e-9 (GTSAM's 1e-4 stops after 1-2 iterations with every
    weight ~1e-5 on KITTI candidates); a loop is accepted when its final weight exceeds 0.5.
``oracle``
    Only the true loops, solved with Levenberg-Marquardt: the reference for ATE. It has the
    :class:`~lcv_replay.verification.base.NeedsTruth` capability: the replay and the bench call
    :meth:`OracleVerifier.set_truth` with the truth that judges the run (the log's labels, else its
    ground truth) before feeding frames.

All of them are fed frame by frame and never read the future. With ``baselines.solve_every =
"end"`` (the default) a batch method solves once in :meth:`result`, from the odometry: the classic
batch set-up, and its window steps carry the odometry with nothing accepted (so its latency is the
frames to the end of the log). With ``"window"`` it re-solves the whole history at every window
end, warm-started from its previous solution extended by odometry, so a replay shows it evolving;
that costs about 3x the time of one batch solve on KITTI 00 (10 windows), and much more where one
solve is slow (GNC on Manhattan with 1000 outliers: minutes per solve).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from lcv_replay import se2
from lcv_replay.errors import VerificationError
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification import measurements, pose_graph
from lcv_replay.verification.base import (
    Constraint,
    ConstraintHistory,
    HypothesisSummary,
    PairTruth,
    VerificationResult,
    VerifierStep,
    checked_frame,
    default_informations,
)
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.verification.registry import register

log = logging.getLogger(__name__)

IR_ONLY_COUNTS = (10, 20, 30, 40, 50)  # the paper's X values for the ir-only baseline


# ----------------------------------------------------------------------------------------------
# The shared incremental shell of a batch method
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BatchSolution:
    """What a batch method returns for the history so far.

    Attributes:
        poses: ``(N, 3)`` estimate of frames 0..N-1.
        accepted_ids: accepted constraint ids, ascending.
        chi2: total whitened chi-square at the solution (Gaussian factors), if computed.
    """

    poses: np.ndarray
    accepted_ids: tuple[int, ...]
    chi2: float | None = None


class BatchVerifier:
    """A batch method run incrementally: solve the whole history at each window end (or once).

    Subclasses implement :meth:`solve`. This shell owns the frames, the constraint history and the
    window schedule, and turns each solution into a :class:`VerifierStep`.
    """

    name = "batch"

    def __init__(self, config: VerificationConfig, *, odometry_information: np.ndarray | None = None):
        self.config = config
        self.baseline = config.baselines
        self.odom_information, loop_information = default_informations(config, odometry_information)
        self.history = ConstraintHistory(loop_information)
        self._odom: list[tuple[float, float, float]] = []
        self._window_index = 0
        self._stepped_frames = 0  # frames covered by the last step
        self._stepped_constraints = 0
        self._estimate: np.ndarray | None = None  # last solution, (M, 3)
        self._accepted: tuple[int, ...] = ()
        self._chi2: float | None = None
        self._last_step: VerifierStep | None = None
        self._result: VerificationResult | None = None

    # --------------------------------------------------------------------- Verifier protocol
    def add_frame(self, frame_index: int, odom: Pose2D) -> None:
        self._odom.append(checked_frame(self.name, frame_index, len(self._odom), odom, finished=self._result is not None))

    def add_candidates(self, candidates: Sequence[LoopCandidate]) -> list[Constraint]:
        return self.history.admit(candidates, len(self._odom))

    def step(self) -> VerifierStep | None:
        n = len(self._odom)
        if n == 0 or n % self.config.window_frames != 0 or n == self._stepped_frames:
            return None
        return self._run_step(solve=self.baseline.solve_every == "window")

    def result(self) -> VerificationResult:
        if self._result is not None:
            return self._result
        if not self._odom:
            raise VerificationError(f"{self.name}: no frames were added", fix="feed at least one frame")
        needs_final = (
            len(self._odom) != self._stepped_frames
            or len(self.history) != self._stepped_constraints
            or self.baseline.solve_every == "end"
        )
        step = self._run_step(solve=True) if needs_final else self._last_step
        assert step is not None
        poses = self._current_poses()
        self._result = VerificationResult(
            method=self.name,
            constraints=tuple(self.history.constraints),
            accepted_constraint_ids=self._accepted,
            trajectory=poses,
            ranking=(),
            paper_consistent_ids=tuple(int(i) for i in np.flatnonzero(self._consistent(poses))),
            last_step=step,
        )
        return self._result

    # --------------------------------------------------------------------- subclass hook
    def solve(self, odom: np.ndarray, constraints: Sequence[Constraint], initial: np.ndarray) -> BatchSolution:
        """Solve frames ``0..N-1`` with the whole history. ``initial`` is ``(N, 3)``."""
        raise NotImplementedError

    # --------------------------------------------------------------------- internals
    @property
    def odometry(self) -> np.ndarray:
        """``(N, 3)`` cumulative odometry of the frames added so far."""
        return np.asarray(self._odom, dtype=np.float64).reshape(-1, 3)

    def _current_poses(self) -> np.ndarray:
        odom = self.odometry
        if self._estimate is None:
            return odom.copy()
        return measurements.extend_by_odometry(self._estimate, odom)

    def _consistent(self, poses: np.ndarray) -> np.ndarray:
        """``(C,)`` bool: the paper's T_p test (sec. II-A) of every constraint against ``poses``."""
        if not self.history.constraints:
            return np.zeros(0, dtype=bool)
        pairs = np.array([(c.query_frame, c.match_frame) for c in self.history.constraints])
        d = np.linalg.norm(poses[pairs[:, 0], :2] - poses[pairs[:, 1], :2], axis=1)
        return d < self.config.consistency_radius_m

    def _run_step(self, *, solve: bool) -> VerifierStep:
        n = len(self._odom)
        timings: dict[str, float] = {}
        dropped: tuple[tuple[int, str], ...] = ()
        if solve:
            odom = self.odometry
            initial = odom.copy() if self.baseline.solve_every == "end" else self._current_poses()
            start = time.perf_counter()
            try:
                solution = self.solve(odom, tuple(self.history.constraints), initial)
            except pose_graph.OptimisationFailed as exc:
                log.warning("%s: solve at frame %d failed, keeping the previous estimate: %s", self.name, n - 1, exc.message)
                dropped = ((0, exc.message),)
            else:
                self._estimate, self._accepted, self._chi2 = solution.poses, solution.accepted_ids, solution.chi2
            timings["optimise"] = time.perf_counter() - start
        poses = self._current_poses()
        consistent = self._consistent(poses)
        new_ids = tuple(range(self._stepped_constraints, len(self.history)))
        summary = HypothesisSummary(
            id=0, parent_id=None, constraint_ids=self._accepted, score=int(consistent.sum()), rank=1,
            window=self._window_index, chi2=self._chi2, rank_key=float(consistent.sum()),
        )
        step = VerifierStep(
            frame_index=n - 1,
            window_index=self._window_index,
            new_constraint_ids=new_ids,
            new_hypotheses=(),
            generation_edges=(),
            ranking=(summary,),
            accepted_constraint_ids=self._accepted,
            trajectories={0: poses},
            consistency=consistent[None, :],
            timings_s=timings,
            dropped=dropped,
        )
        self._window_index += 1
        self._stepped_frames = n
        self._stepped_constraints = len(self.history)
        self._last_step = step
        return step


# ----------------------------------------------------------------------------------------------
# The methods
# ----------------------------------------------------------------------------------------------


def _chi2_below(poses: np.ndarray, constraints: Sequence[Constraint], loop_information: np.ndarray, limit: float) -> np.ndarray:
    """``(C,)`` bool: whitened chi-square of each loop at ``poses`` below ``limit``."""
    if not constraints:
        return np.zeros(0, dtype=bool)
    match_idx, query_idx, measured, info = measurements.loop_arrays(constraints, loop_information)
    return se2.between_chi2(poses, match_idx, query_idx, measured, info) < limit


class OdometryOnlyVerifier(BatchVerifier):
    """``none``: the odometry, nothing accepted."""

    name = "none"

    def solve(self, odom, constraints, initial):
        return BatchSolution(odom.copy(), ())


class LeastSquaresVerifier(BatchVerifier):
    """Plain Levenberg-Marquardt with a chosen subset of the constraints, all accepted."""

    def select(self, constraints: Sequence[Constraint]) -> tuple[int, ...]:
        raise NotImplementedError

    def solve(self, odom, constraints, initial):
        chosen = self.select(constraints)
        graph = pose_graph.build_graph(
            odom, self.odom_information, [constraints[i] for i in chosen],
            loop_default_information=self.history.loop_default_information,
        )
        solution = pose_graph.optimise_lm(graph, initial, max_iterations=self.baseline.max_iterations)
        return BatchSolution(solution.poses, tuple(sorted(chosen)), solution.chi2)


class IrOnlyVerifier(LeastSquaresVerifier):
    """``ir-only``: X constraints drawn at random from the history and all accepted (the paper's
    baseline). Each solve draws afresh from the whole history with a generator seeded by
    ``(seed, window)``, so runs are deterministic for a seed."""

    def __init__(self, config: VerificationConfig, *, odometry_information=None, count: int | None = None):
        super().__init__(config, odometry_information=odometry_information)
        self.count = config.baselines.ir_only_count if count is None else count
        self.name = "ir-only" if count is None else f"ir-only-{count}"

    def select(self, constraints):
        rng = np.random.default_rng([self.config.seed, self._window_index])
        k = min(self.count, len(constraints))
        return tuple(int(i) for i in rng.choice(len(constraints), size=k, replace=False)) if k else ()


class OracleVerifier(LeastSquaresVerifier):
    """``oracle``: only the true loops (:class:`~lcv_replay.verification.base.NeedsTruth`: call
    :meth:`set_truth` before the first solve)."""

    name = "oracle"

    def __init__(self, config: VerificationConfig, *, odometry_information=None):
        super().__init__(config, odometry_information=odometry_information)
        self._is_true: PairTruth | None = None

    def set_truth(self, is_true: PairTruth) -> None:
        """``is_true(query_frame, match_frame)``: whether a loop is true."""
        self._is_true = is_true

    def select(self, constraints):
        if self._is_true is None:
            raise VerificationError(
                "the oracle needs the log's true loops",
                fix="use a log with /ground_truth/loops labels or ground truth, or another method",
            )
        return tuple(i for i, c in enumerate(constraints) if self._is_true(c.query_frame, c.match_frame))


class RobustKernelVerifier(BatchVerifier):
    """``dcs``/``gm``/``cauchy``: robust kernel on every loop factor, LM, accept chi2 < limit."""

    def __init__(self, config: VerificationConfig, *, odometry_information=None, kernel: pose_graph.RobustKernel):
        super().__init__(config, odometry_information=odometry_information)
        self.kernel = kernel
        self.name = kernel.kind

    def solve(self, odom, constraints, initial):
        graph = pose_graph.build_graph(
            odom, self.odom_information, constraints,
            loop_default_information=self.history.loop_default_information, robust=self.kernel,
        )
        solution = pose_graph.optimise_lm(graph, initial, max_iterations=self.baseline.max_iterations)
        ok = _chi2_below(solution.poses, constraints, self.history.loop_default_information, self.baseline.accept_chi2)
        return BatchSolution(solution.poses, tuple(int(i) for i in np.flatnonzero(ok)), None)


class GncVerifier(BatchVerifier):
    """``gnc``: GNC-TLS with the prior and odometry as known inliers; accept weight > 0.5."""

    name = "gnc"

    def solve(self, odom, constraints, initial):
        graph = pose_graph.build_graph(
            odom, self.odom_information, constraints,
            loop_default_information=self.history.loop_default_information,
        )
        n = len(odom)
        if not constraints:  # nothing to weigh: GNC would only repeat the odometry
            return BatchSolution(odom.copy(), ())
        solution, weights = pose_graph.optimise_gnc_tls(
            graph, initial, pose_graph.odometry_factor_indices(n),
            weights_tol=self.baseline.gnc_weights_tol, max_iterations=self.baseline.max_iterations,
        )
        loop_weights = weights[pose_graph.loop_factor_index(n, 0):]
        accepted = tuple(int(i) for i in np.flatnonzero(loop_weights > self.baseline.gnc_accept_weight))
        return BatchSolution(solution.poses, accepted, solution.chi2)


# ----------------------------------------------------------------------------------------------
# Registration
# ----------------------------------------------------------------------------------------------


@register("none", help="odometry only: no loop closure accepted")
def _make_none(config: VerificationConfig, *, odometry_information=None) -> OdometryOnlyVerifier:
    return OdometryOnlyVerifier(config, odometry_information=odometry_information)


@register("ir-only", help="paper baseline: X random constraints all accepted (X = baselines.ir_only_count)")
def _make_ir_only(config: VerificationConfig, *, odometry_information=None) -> IrOnlyVerifier:
    return IrOnlyVerifier(config, odometry_information=odometry_information)


def _register_ir_only_variant(count: int) -> None:
    @register(f"ir-only-{count}", help=f"paper baseline with X = {count} random constraints all accepted")
    def _make(config: VerificationConfig, *, odometry_information=None) -> IrOnlyVerifier:
        return IrOnlyVerifier(config, odometry_information=odometry_information, count=count)


for _count in IR_ONLY_COUNTS:
    _register_ir_only_variant(_count)


def _register_kernel(kind: str, scale_key: str, help: str) -> None:
    @register(kind, help=f"{help} (scale = baselines.{scale_key}), accept chi2 < baselines.accept_chi2")
    def _make(config: VerificationConfig, *, odometry_information=None) -> RobustKernelVerifier:
        kernel = pose_graph.RobustKernel(kind, getattr(config.baselines, scale_key))  # type: ignore[arg-type]
        return RobustKernelVerifier(config, odometry_information=odometry_information, kernel=kernel)


_register_kernel("dcs", "dcs_phi", "dynamic covariance scaling on every loop factor")
_register_kernel("gm", "gm_c", "Geman-McClure on every loop factor")
_register_kernel("cauchy", "cauchy_c", "Cauchy kernel on every loop factor")


@register("gnc", help="GNC-TLS (GncLMOptimizer, weightsTol 1e-9), odometry known inliers, accept weight > 0.5")
def _make_gnc(config: VerificationConfig, *, odometry_information=None) -> GncVerifier:
    return GncVerifier(config, odometry_information=odometry_information)


@register("oracle", help="only the labelled true loops (needs labels or ground truth): the ATE reference")
def _make_oracle(config: VerificationConfig, *, odometry_information=None) -> OracleVerifier:
    return OracleVerifier(config, odometry_information=odometry_information)
