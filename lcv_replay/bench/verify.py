"""Verification-only runs: feed a log's odometry and ``/loop_candidates`` through a verifier,
frame by frame, and evaluate the result (``lcv-replay bench verify``; the suite uses it too).

No retrieval and no Rerun: the log is read once into :class:`LogInputs` (odometry, candidates per
frame, truth), then :func:`verify_inputs` times only the verifier. Every method, ``ilv``,
``ilv+`` or a baseline, is fed the same way through the
:class:`~lcv_replay.verification.base.Verifier` protocol.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lcv_replay.errors import LogFormatError
from lcv_replay.evaluation.metrics import Metrics, evaluate
from lcv_replay.evaluation.truth import ConstraintTruth, LoopTruth, choose_truth_source, loop_truth, provide_truth
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification.base import VerificationResult, VerifierStep
from lcv_replay.verification.config import VerificationConfig

StepCallback = Callable[[VerifierStep], None]


@dataclass(frozen=True)
class LogInputs:
    """What a verification run needs from a log, read once.

    Attributes:
        path: the log file.
        frames: number of frames N.
        duration_s: time between the first and last frame stamps.
        odometry: ``(N, 3)`` cumulative odometry ``[x_m, y_m, yaw_rad]``.
        candidates: every loop candidate of the log, sorted by query frame.
        odometry_information: ``(3, 3)`` information of one odometry step, if the log carries one.
        true_pairs: labelled true pairs, or ``None`` when the log has no labels.
        ground_truth: ``(N, 3)`` ground truth (NaN rows where a frame has none), or ``None``.
    """

    path: Path
    frames: int
    duration_s: float
    odometry: np.ndarray
    candidates: tuple[LoopCandidate, ...]
    odometry_information: np.ndarray | None = None
    true_pairs: frozenset[tuple[int, int]] | None = None
    ground_truth: np.ndarray | None = None

    def candidates_by_frame(self) -> dict[int, list[LoopCandidate]]:
        """Candidates grouped by the frame at which they arrive (their query frame)."""
        out: dict[int, list[LoopCandidate]] = {}
        for cand in self.candidates:
            out.setdefault(cand.query_frame, []).append(cand)
        return out

    def truth_of(self, pairs: Sequence[tuple[int, int]], radius_m: float) -> LoopTruth:
        """Truth of ``pairs``: labels, else ground truth closer than ``radius_m``, else unknown."""
        return loop_truth(pairs, true_pairs=self.true_pairs, ground_truth=self.ground_truth, radius_m=radius_m)

    def constraint_truth(self, radius_m: float) -> ConstraintTruth:
        """The same rule as :meth:`truth_of`, as the judge a replay of the log's candidates uses."""
        source = choose_truth_source("log", has_labels=self.true_pairs is not None, has_ground_truth=self.ground_truth is not None)
        return ConstraintTruth(source, self.true_pairs, self.ground_truth, radius_m)


def load_inputs(reader_or_path: Any, *, require_candidates: bool = True) -> LogInputs:
    """Read a log (a path or an open :class:`~lcv_replay.log.reader.LogReader`) into :class:`LogInputs`.

    Args:
        require_candidates: refuse a log without ``/loop_candidates`` (the suite turns it off:
            a graph with no loop edge, such as robustslam_kitti 07 at alpha 1.00, is a valid case).

    Raises:
        LogFormatError: the log cannot be read, or carries no ``/loop_candidates``.
    """
    from lcv_replay.log.format import LOOP_CANDIDATES_TOPIC
    from lcv_replay.log.reader import open_log

    reader = open_log(reader_or_path) if isinstance(reader_or_path, (str, Path)) else reader_or_path
    info = reader.info
    if require_candidates and not info.has_candidates:
        raise LogFormatError(
            f"the log has no loop candidates ({LOOP_CANDIDATES_TOPIC})",
            path=reader.path,
            fix="record it from a source with candidates (e.g. 'lcv-replay record g2o'), or run the "
            "replay, which proposes candidates by place recognition",
        )
    return LogInputs(
        path=Path(reader.path),
        frames=info.frames,
        duration_s=float(info.duration_s),
        odometry=reader.odometry(),
        candidates=tuple(reader.loop_candidates()) if info.has_candidates else (),
        odometry_information=info.odometry_information,
        true_pairs=frozenset(reader.true_loops()) if info.has_labels else None,
        ground_truth=reader.ground_truth() if info.has_ground_truth else None,
    )


@dataclass(frozen=True)
class VerifyRow:
    """One row of ``bench verify`` / ``bench suite``: one log × one method. ``None`` = undefined.

    Counts and precision/recall/F1 are over the accepted loops; ``paper_*`` over the constraints
    consistent with the top hypothesis (paper sec. II-A); ``ate_rmse_m`` after SE(2) alignment.
    ``window_time_*`` are the verifier's wall time per window step (``ilv``'s incremental work);
    ``cpu_time_s`` is the process CPU time of the run (steadier than wall time on a shared machine,
    but it also counts GTSAM's worker threads, if any). ``gate_chi2`` is the chi-square gate in
    force at the end (``ilv+`` calibrates it to the data; ``None`` for methods without one).
    ``ambiguous`` counts the constraints flagged ambiguous at the end (neither accepted nor
    rejected, ``ilv+``), ``ambiguous_true`` how many of them are true (``None`` without truth).
    """

    log: str
    method: str
    frames: int
    log_duration_s: float
    wall_time_s: float
    cpu_time_s: float
    candidates: int
    constraints: int
    accepted: int
    true_candidates: int | None
    true_positives: int | None
    false_positives: int | None
    false_negatives: int | None
    precision: float | None
    recall: float | None
    f1: float | None
    ate_rmse_m: float | None
    ate_unaligned_m: float | None
    paper_precision: float | None
    paper_recall: float | None
    paper_f1: float | None
    latency_mean_frames: float | None
    latency_max_frames: int | None
    truth_source: str
    realtime_factor: float | None
    windows: int
    window_time_mean_s: float | None
    window_time_max_s: float | None
    gate_chi2: float | None
    seed: int
    ambiguous: int = 0
    ambiguous_true: int | None = None
    case: str | None = None
    config: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN/inf become ``None``)."""
        out = dataclasses.asdict(self)
        for key, value in out.items():
            if isinstance(value, float) and not math.isfinite(value):
                out[key] = None
        return out


@dataclass(frozen=True)
class VerifyRun:
    """Everything one run produced: the row, the verifier's result and steps, the metrics."""

    row: VerifyRow
    result: VerificationResult
    steps: tuple[VerifierStep, ...]
    metrics: Metrics
    window_times_s: tuple[float, ...]


def feed(verifier, inputs: LogInputs, *, on_step: StepCallback | None = None) -> tuple[VerificationResult, list[VerifierStep], list[float]]:
    """Feed ``inputs`` frame by frame through ``verifier``; returns ``(result, steps, window_times_s)``.

    ``window_times_s[k]`` is the wall time from the end of step ``k-1`` (or the start) to the end
    of step ``k``, the last entry covering :meth:`result`.
    """
    by_frame = inputs.candidates_by_frame()
    steps: list[VerifierStep] = []
    window_times: list[float] = []
    last = time.perf_counter()
    for k, (x, y, yaw) in enumerate(inputs.odometry.tolist()):
        verifier.add_frame(k, Pose2D(x, y, yaw))
        arriving = by_frame.get(k)
        if arriving:
            verifier.add_candidates(arriving)
        step = verifier.step()
        if step is not None:
            now = time.perf_counter()
            window_times.append(now - last)
            last = now
            steps.append(step)
            if on_step is not None:
                on_step(step)
    result = verifier.result()
    window_times.append(time.perf_counter() - last)
    return result, steps, window_times


def verify_inputs(
    inputs: LogInputs,
    method: str,
    config: VerificationConfig | None = None,
    *,
    seed: int | None = None,
    case: str | None = None,
    on_step: StepCallback | None = None,
) -> VerifyRun:
    """Run verifier ``method`` over ``inputs`` and evaluate it.

    Args:
        inputs: the log, read by :func:`load_inputs`.
        method: a registered method (``ilv``, ``ilv+``, ``gnc``, ...).
        config: verification config (paper defaults if ``None``); ``seed`` overrides its seed.
        case: a suite case name written into the row.
        on_step: called with each :class:`VerifierStep` (e.g. a progress bar).

    Raises:
        ConfigError: unknown method. VerificationError: the oracle on a log without truth, a
            singular information matrix, ...
    """
    from lcv_replay.config import to_dict
    from lcv_replay.verification.config import with_loop_kind
    from lcv_replay.verification.registry import make_verifier

    config = config or VerificationConfig()
    if seed is not None:
        config = dataclasses.replace(config, seed=seed)
    # ilv+ verifies measured loops and same-place loops with different verifiers
    config = with_loop_kind(config, same_place=not any(c.T_match_query is not None for c in inputs.candidates))
    verifier = make_verifier(method, config, odometry_information=inputs.odometry_information)
    provide_truth(verifier, inputs.constraint_truth(config.consistency_radius_m), method=method, path=inputs.path)

    started, started_cpu = time.perf_counter(), time.process_time()
    result, steps, window_times = feed(verifier, inputs, on_step=on_step)
    wall = time.perf_counter() - started
    cpu = time.process_time() - started_cpu

    truth = inputs.truth_of([c.candidate.pair for c in result.constraints], config.consistency_radius_m)
    metrics = evaluate(result, truth, ground_truth=inputs.ground_truth, steps=steps)
    acc, paper = metrics.accepted, metrics.paper
    row = VerifyRow(
        log=str(inputs.path),
        method=method,
        frames=inputs.frames,
        log_duration_s=inputs.duration_s,
        wall_time_s=wall,
        cpu_time_s=cpu,
        candidates=len(inputs.candidates),
        constraints=len(result.constraints),
        accepted=acc.accepted,
        true_candidates=acc.true_candidates,
        true_positives=acc.true_positives,
        false_positives=acc.false_positives,
        false_negatives=acc.false_negatives,
        precision=acc.precision,
        recall=acc.recall,
        f1=acc.f1,
        ate_rmse_m=metrics.ate.rmse_m if metrics.ate else None,
        ate_unaligned_m=metrics.ate.unaligned_rmse_m if metrics.ate else None,
        paper_precision=paper.precision,
        paper_recall=paper.recall,
        paper_f1=paper.f1,
        latency_mean_frames=metrics.latency.mean_frames if metrics.latency else None,
        latency_max_frames=metrics.latency.max_frames if metrics.latency else None,
        truth_source=metrics.truth_source.value,
        realtime_factor=inputs.duration_s / wall if wall > 0 and inputs.duration_s > 0 else None,
        windows=len(steps),
        window_time_mean_s=float(np.mean(window_times)) if window_times else None,
        window_time_max_s=float(np.max(window_times)) if window_times else None,
        gate_chi2=result.last_step.gate_chi2 if result.last_step else None,
        seed=config.seed,
        ambiguous=len(result.ambiguous_constraint_ids),
        ambiguous_true=len(truth.true_ids & set(result.ambiguous_constraint_ids)) if truth.known else None,
        case=case,
        config=to_dict(config),
    )
    return VerifyRun(row, result, tuple(steps), metrics, tuple(window_times))


def run_verification(reader_or_path: Any, method: str, config: VerificationConfig | None = None, seed: int | None = None) -> VerifyRow:
    """Verify one log (path or open reader) with one method; the bench row (see :class:`VerifyRow`)."""
    return verify_inputs(load_inputs(reader_or_path), method, config, seed=seed).row
