"""The ATE reference of a replay: the ``oracle`` verifier on the same constraints, as a sink.

A fleet table ranks logs by ATE over the oracle's ATE (the error left when exactly the true loops
are accepted), as ``bench suite`` does. :class:`OracleReference` feeds the oracle alongside the
replay, frame by frame: the odometry and the constraints the replay admitted, judged by the same
truth (the flags in :class:`~lcv_replay.sinks.base.FrameUpdate`). It solves once, at the end (one
Levenberg-Marquardt solve), and only when the run has ground truth to measure ATE against.
"""

from __future__ import annotations

import logging

from lcv_replay.errors import LcvError
from lcv_replay.sinks.base import BaseSink, FrameUpdate, RunStart, RunSummary

logger = logging.getLogger(__name__)


class OracleReference(BaseSink):
    """After the replay, :attr:`ate_rmse_m` is the oracle's ATE on the replay's constraints, or
    ``None`` (no ground truth, no truth for the constraints, an interrupted run, a failed solve)."""

    def __init__(self) -> None:
        self.ate_rmse_m: float | None = None
        self._oracle = None
        self._ground_truth = None
        self._flags: dict[tuple[int, int], bool | None] = {}

    def on_start(self, start: RunStart) -> None:
        if start.ground_truth is None or start.truth_source == "none":
            return
        from lcv_replay.config import from_dict
        from lcv_replay.log.messages import information_from_json
        from lcv_replay.verification.config import VerificationConfig
        from lcv_replay.verification.registry import make_verifier

        verification = from_dict(VerificationConfig, dict(start.config.get("verification", {})), where="verification")
        information = information_from_json(start.log_metadata.get("odometry_information"))
        self._oracle = make_verifier("oracle", verification, odometry_information=information)
        self._oracle.set_truth(lambda query, match: self._flags.get((query, match)) is True)
        self._ground_truth = start.ground_truth

    def on_frame(self, update: FrameUpdate) -> None:
        if self._oracle is None:
            return
        self._oracle.add_frame(update.frame.index, update.frame.odom)
        if update.new_constraints:
            for constraint, truth in zip(update.new_constraints, update.new_constraint_truth):
                self._flags[(constraint.query_frame, constraint.match_frame)] = truth
            self._oracle.add_candidates([c.candidate for c in update.new_constraints])

    def on_finish(self, summary: RunSummary) -> None:
        if self._oracle is None or summary.interrupted or summary.frames == 0:
            return
        from lcv_replay.evaluation.metrics import ate_rmse_m

        try:
            result = self._oracle.result()
        except LcvError as exc:  # a reference that cannot be computed is missing, not an error of the run
            logger.warning("oracle reference not computed: %s", exc.format())
            return
        self.ate_rmse_m = ate_rmse_m(result.trajectory, self._ground_truth)
