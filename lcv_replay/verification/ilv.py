"""``ilv`` (the paper's method), and the registration of ``ilv+`` (the improved verifier).

``ilv`` — Tanaka, "Multi-Model Hypothesize-and-Verify Approach for Incremental Loop Closure
Verification", SII 2016, as the paper defines it:

* a hypothesis is the GTSAM Levenberg-Marquardt solution of the **full** pose graph (every frame,
  ``Pose2`` / ``BetweenFactorPose2``) of the odometry plus its constraints, warm-started from its
  parent's estimate; later frames extend it by odometry;
* a constraint ``(t, t')`` is consistent with it when ``||p(t) - p(t')|| < T_p`` (10 m, II-A);
* score = number of consistent constraints in the whole history; ranking by score (ties: older);
* sequential selection, windows of 500 frames, 10 × 10 children per window, at most 200 kept
  (:mod:`~.incremental`); accepted = the constraints consistent with the rank-1 hypothesis.

``ilv+`` (the default method) is :mod:`lcv_replay.verification.consensus`: incremental
verification by cluster consensus against an iSAM2 working hypothesis, with contests between
hypotheses by truncated cost and an ambiguous verdict; it is registered here beside ``ilv``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from lcv_replay.verification import pose_graph
from lcv_replay.verification.base import Constraint, ConstraintHistory
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.verification.consistency import position_consistent
from lcv_replay.verification.hypotheses import Hypothesis
from lcv_replay.verification.incremental import IncrementalVerifier
from lcv_replay.verification.measurements import OdometryChain
from lcv_replay.verification.registry import register



# ----------------------------------------------------------------------------------------------
# ilv: the paper
# ----------------------------------------------------------------------------------------------


class PaperModel:
    """``ilv``: full-graph GTSAM hypotheses, the 10 m position test, score = consistent count."""

    gate_chi2 = None

    def __init__(self, chain: OdometryChain, history: ConstraintHistory, config: VerificationConfig):
        self.chain = chain
        self.history = history
        self.config = config
        self._base_graph = None
        self._base_frames = -1

    def eligible(self, constraints: Sequence[Constraint]) -> np.ndarray:
        return np.ones(len(constraints), dtype=bool)

    def _odometry_graph(self):
        import gtsam

        n = len(self.chain)
        if self._base_frames != n:
            self._base_graph = pose_graph.build_graph(
                self.chain.poses, self.chain.information, (), loop_default_information=self.history.loop_default_information
            )
            self._base_frames = n
        return gtsam.NonlinearFactorGraph(self._base_graph)

    def solve(self, parent: Hypothesis, constraint_ids: tuple[int, ...], *, hypothesis_id: int, window: int, added: int) -> Hypothesis:
        graph = self._odometry_graph()
        loops = [pose_graph.loop_factor(self.history.constraints[c], self.history.loop_default_information) for c in constraint_ids]
        pose_graph.add_loop_factors(graph, loops)
        initial = parent.trajectory(self.chain)
        solution = pose_graph.optimise_lm(graph, initial, max_iterations=self.config.max_iterations)
        n = len(self.chain)
        return Hypothesis(
            hypothesis_id, parent.id, constraint_ids, window, np.arange(n, dtype=np.int64), solution.poses,
            chi2=solution.chi2, added_constraint_id=added,
        )

    def evaluate(self, hypothesis: Hypothesis, constraint_ids: np.ndarray) -> tuple[np.ndarray, None]:
        if len(constraint_ids) == 0:
            return np.zeros(0, dtype=bool), None
        cons = self.history.constraints
        q = np.array([cons[c].query_frame for c in constraint_ids])
        m = np.array([cons[c].match_frame for c in constraint_ids])
        consistent = position_consistent(
            hypothesis.poses_at(self.chain, q), hypothesis.poses_at(self.chain, m), self.config.consistency_radius_m
        )
        return consistent, None

    def rank_key(self, hypothesis: Hypothesis, score: int, support: float) -> float:
        return float(score)

    def tie_key(self, hypothesis: Hypothesis) -> float:
        return 0.0

    def forget(self, hypothesis_id: int) -> None:
        pass

    def absorb(self, parent: Hypothesis, *, hypothesis_id: int, window: int) -> None:
        return None

    def draw_weights(self, parent: Hypothesis, candidates: np.ndarray) -> None:
        return None

    def recalibrate(self, top: Hypothesis) -> bool:
        return False

    def accepted(self, top: Hypothesis, consistent: np.ndarray) -> np.ndarray:
        return consistent

    def final_trajectory(self, top: Hypothesis, accepted_ids: tuple[int, ...]) -> np.ndarray:
        return top.trajectory(self.chain)


# ----------------------------------------------------------------------------------------------
# Registration
# ----------------------------------------------------------------------------------------------


@register("ilv", help="the paper's multi-model hypothesize-and-verify (full GTSAM graphs, 10 m test)")
def _make_ilv(config: VerificationConfig, *, odometry_information=None) -> IncrementalVerifier:
    return IncrementalVerifier("ilv", config, PaperModel, odometry_information=odometry_information)


@register("ilv+", help="improved ilv: clusters of pairwise-consistent loops verified against an iSAM2 working hypothesis, contests by truncated cost, ambiguous verdicts")
def _make_ilv_plus(config: VerificationConfig, *, odometry_information=None):
    from lcv_replay.verification.consensus import ConsensusVerifier

    return ConsensusVerifier(config, odometry_information=odometry_information)
