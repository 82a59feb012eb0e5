"""``ilv`` (the paper's method) and ``ilv+`` (the improved verifier), registered as methods.

``ilv`` — Tanaka, "Multi-Model Hypothesize-and-Verify Approach for Incremental Loop Closure
Verification", SII 2016, as the paper defines it:

* a hypothesis is the GTSAM Levenberg-Marquardt solution of the **full** pose graph (every frame,
  ``Pose2`` / ``BetweenFactorPose2``) of the odometry plus its constraints, warm-started from its
  parent's estimate; later frames extend it by odometry;
* a constraint ``(t, t')`` is consistent with it when ``||p(t) - p(t')|| < T_p`` (10 m, II-A);
* score = number of consistent constraints in the whole history; ranking by score (ties: older);
* sequential selection, windows of 500 frames, 10 × 10 children per window, at most 200 kept
  (:mod:`~.incremental`); accepted = the constraints consistent with the rank-1 hypothesis.

``ilv+`` keeps that structure (constraint history, hypotheses as pose-graph solutions warm-started
from their parents, the append-only table, sequential selection of inconsistent constraints,
windows, pruning) and changes what the paper leaves weak:

1. **Mahalanobis consistency under the hypothesis' own uncertainty** instead of a fixed 10 m radius,
   so loops between places that really are near each other are judged by their measurement, not
   by a radius. The covariance of a loop's predicted relative pose is the Laplace covariance of
   the hypothesis' own pose graph at its solution (GTSAM's marginals), so the test is tight where
   the hypothesis has closed loops and loose after a long open traverse. A constraint outside the
   hypothesis is plausible when its innovation passes the chi-square gate,
   ``rᵀ (R + Σ_pred)⁻¹ r < gate`` (3 dof, 0.99, in the declared units; see 7). The consistency
   table itself holds the cheaper question "does the hypothesis' solution satisfy it",
   ``rᵀ R⁻¹ r < gate``.
2. **Ranking by the truncated-least-squares cost** ``J = χ²_odometry + Σ_c min(χ²_c, gate)`` of the
   hypothesis' solution over the whole history (the objective GNC-TLS minimises), instead of the
   count of consistent constraints. Bending the odometry to satisfy a false loop, or a group of
   mutually consistent false loops, costs its odometry chi-square and the true loops it breaks; a
   hypothesis that merely fails to exclude constraints earns nothing for them.
3. **Consensus refinement**: every child is solved, then the constraints outside it that its
   solution satisfies join, and members leave whose residual fails the gate or whose
   **leave-one-out** statistic does (removing the loop would lower the graph's chi-square by more
   than the truncated cost of leaving it out: a false loop that bends a weakly held part of the
   graph, such as the open end of the trajectory, fits its own solution well and only this test
   sees it); it is solved again (``closure_rounds``); the drawn constraint stays, since the child
   tests it. At every window end the top hypotheses also **absorb** the constraints whose
   innovation passes the gate under them (a child edge with constraint id ``ABSORBED``), which is
   how a hypothesis follows new evidence for its world.
4. **A reduced pose graph**: nodes are frame 0 and the hypothesis' loop endpoints only, the odometry
   between them composed exactly with its covariance (first order); the other frames are the
   Brownian-bridge interpolation. The cost of a hypothesis depends on its loops, not on the log
   length, so a smaller schedule (3 × 5 children, 50 kept) runs far faster than the paper's.
5. **Sequential selection weighted by plausibility**: the drawn constraint is still one
   inconsistent with the parent, but nearly consistent ones are preferred (:meth:`PlusModel.draw_weights`).
6. Accepted = the rank-1 hypothesis' own constraints that its solution satisfies.
   ``min_loop_gap_frames`` (default 0) can drop candidates too close in time.
7. **The gate is calibrated to the data** (:meth:`PlusModel.recalibrate`): declared covariances
   are often far from the real noise (Vertigo Manhattan's are about 40 times too loose, which lets a
   false loop at the loosely held end of the trajectory pass a gate of 11.34). At each window end
   the leave-one-out statistics of the best hypothesis' loops are fitted as a scaled, possibly
   heavy-tailed F variable (:mod:`~lcv_replay.verification.noise_scale`) and the gate becomes
   ``min(its 0.9999 quantile, calibrated_max_chi2)``; every test above uses the gate in force.
   Gaussian data far tighter than declared (Manhattan) get a gate of 0.5; heavy-tailed data (KITTI)
   get the ceiling, 16.27 (3 dof, 0.999), which admits a true loop of KITTI 05 at 12.6.

The reported trajectory of ``ilv+`` is the reduced-graph solution of its accepted set, interpolated.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Sequence

import numpy as np

from lcv_replay import se2
from lcv_replay.verification import pose_graph
from lcv_replay.verification.base import Constraint
from lcv_replay.verification.base import ConstraintHistory
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.verification.consistency import mahalanobis_d2, position_consistent
from lcv_replay.verification.hypotheses import Hypothesis
from lcv_replay.verification.incremental import IncrementalVerifier
from lcv_replay.verification.measurements import OdometryChain
from lcv_replay.verification.noise_scale import NoiseFit, calibrated_gate
from lcv_replay.verification.registry import register

log = logging.getLogger(__name__)


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
# ilv+: Mahalanobis consistency, consensus refinement, reduced graphs
# ----------------------------------------------------------------------------------------------


class PlusModel:
    """``ilv+`` (see the module docstring)."""

    def __init__(self, chain: OdometryChain, history: ConstraintHistory, config: VerificationConfig):
        self.chain = chain
        self.history = history
        self.config = config
        self.plus = config.ilv_plus
        self._m = np.zeros(0, dtype=np.int64)
        self._q = np.zeros(0, dtype=np.int64)
        self._z = np.zeros((0, 3))
        self._r = np.zeros((0, 3, 3))  # measurement covariances
        self._d2: dict[int, dict[int, float]] = {}  # per hypothesis: innovation d² of the constraints tested
        self._chain_chi2: dict[int, float] = {0: 0.0}  # odometry chi-square of each hypothesis' solution
        self._evaluated: dict[int, tuple[Hypothesis, np.ndarray, np.ndarray]] = {}  # last whole-history evaluation
        self.gate_chi2 = self.plus.gate_chi2  # the gate in force (declared units), see recalibrate()
        self.noise_fit: NoiseFit | None = None  # the fit behind it, if calibrated
        self._calibrated_on: int | None = None  # the hypothesis it was fitted on

    @property
    def explore_chi2(self) -> float:
        """``explore_chi2``, scaled with the gate in force."""
        return self.plus.explore_chi2 * self.gate_chi2 / self.plus.gate_chi2

    # ------------------------------------------------------------------ noise calibration
    def recalibrate(self, top: Hypothesis) -> bool:
        """Fit the noise the best hypothesis' loops show and calibrate the gate to it.

        The leave-one-out statistics (:meth:`leave_one_out`) of at most ``calibration_sample_loops``
        of its loops (evenly spaced in arrival order) are fitted as ``d² / (3 s) ~ F(3, ν)``
        (:func:`~lcv_replay.verification.noise_scale.fit_noise`), and the gate becomes
        ``min(calibration_confidence quantile, calibrated_max_chi2)``: where the declared
        covariances are far looser than the data (Vertigo Manhattan), a false loop at a loosely held
        part of the graph no longer fits; where the errors are heavy-tailed (KITTI), the quantile
        lies far out and the ceiling applies. The ceiling is what bounds a fit on a consensus that
        already holds false loops (the fit cannot tell them from heavy-tailed noise). With fewer
        than ``calibration_min_loops`` loops the configured ``gate_chi2`` applies. Returns whether the gate changed (the caller re-evaluates its table)."""
        if not self.plus.calibrate_gate or top.id == self._calibrated_on:
            return False
        self._calibrated_on = top.id
        gate, fit = self.plus.gate_chi2, None
        members = np.sort(np.asarray(top.constraint_ids, dtype=np.int64))
        if len(members) >= self.plus.calibration_min_loops:
            take = np.unique(np.linspace(0, len(members) - 1, min(len(members), self.plus.calibration_sample_loops)).round().astype(np.int64))
            try:
                d2 = self.leave_one_out(top, members[take])
            except pose_graph.OptimisationFailed as exc:
                log.warning("ilv+: hypothesis %d: gate not recalibrated (%s)", top.id, exc.message)
                return False
            if np.count_nonzero(d2 > 0) >= self.plus.calibration_min_loops:
                quantile, fit = calibrated_gate(d2, self.plus.calibration_confidence)
                gate = min(quantile, self.plus.calibrated_max_chi2)
        self.noise_fit = fit
        if gate == self.gate_chi2:
            return False
        if gate > self.gate_chi2:
            self._d2.clear()  # cached screening bounds were only valid below the old explore_chi2
        self._evaluated.clear()
        log.debug("ilv+: gate %.4g -> %.4g (hypothesis %d, %s)", self.gate_chi2, gate, top.id, fit)
        self.gate_chi2 = gate
        return True

    # ------------------------------------------------------------------ constraints
    def _sync(self) -> None:
        """The arrays of every constraint so far (:meth:`ConstraintHistory.arrays`)."""
        a = self.history.arrays()
        self._m, self._q, self._z, self._r = a.match, a.query, a.measured, a.covariance

    def eligible(self, constraints: Sequence[Constraint]) -> np.ndarray:
        self._sync()
        return np.array([c.query_frame - c.match_frame >= self.plus.min_loop_gap_frames for c in constraints], dtype=bool)

    def _factors(self, ids: Sequence[int]) -> list[pose_graph.LoopFactor]:
        return [
            pose_graph.LoopFactor(int(self._m[c]), int(self._q[c]), self._z[c], np.linalg.inv(self._r[c])) for c in ids
        ]

    # ------------------------------------------------------------------ solving
    def _solve_set(self, ids: tuple[int, ...], warm: Hypothesis) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Solve the reduced graph of ``ids`` from ``warm``: ``(nodes, poses, chi2, odometry chi2)``."""
        nodes = np.unique(np.concatenate([[0], self._m[list(ids)], self._q[list(ids)]])).astype(np.int64)
        graph = pose_graph.build_reduced_graph(self.chain, nodes, self._factors(ids))
        initial = warm.poses_at(self.chain, nodes)
        solution = pose_graph.optimise_lm(graph, initial, keys=nodes, max_iterations=self.config.max_iterations)
        a, b = nodes[:-1], nodes[1:]
        steps = se2.between(self.chain.poses[a], self.chain.poses[b])
        info = np.linalg.inv(self.chain.segment_covariance(a, b)) if len(a) else np.zeros((0, 3, 3))
        idx = np.arange(len(nodes))
        odometry = float(se2.between_chi2(solution.poses, idx[:-1], idx[1:], steps, info).sum()) if len(a) else 0.0
        return nodes, solution.poses, solution.chi2, odometry

    def absorb(self, parent: Hypothesis, *, hypothesis_id: int, window: int) -> Hypothesis | None:
        """The parent plus every eligible constraint whose innovation passes the gate under the
        parent's covariance (:meth:`mahalanobis`), refined (new evidence for the same world).

        If that child ranks below its parent (individually plausible constraints that are not
        jointly so, after a long open traverse), the child absorbs only the constraints the
        parent's solution already satisfies."""
        self._sync()
        outside = self._eligible_mask().copy()
        outside[list(parent.constraint_ids)] = False
        candidates = np.flatnonzero(outside)
        if len(candidates) == 0:
            return None
        d2, chi2 = self.mahalanobis(parent, candidates)
        passing = d2 < self.gate_chi2
        extra = candidates[passing]
        if len(extra) == 0:
            return None
        child = self.solve(parent, tuple(parent.constraint_ids) + tuple(int(c) for c in extra), hypothesis_id=hypothesis_id, window=window, added=None)
        if self._key(child) >= self._key(parent):
            return child
        satisfied = chi2[passing] < self.gate_chi2
        if not satisfied.any() or satisfied.all():
            return child
        self.forget(hypothesis_id)
        ids = tuple(parent.constraint_ids) + tuple(int(c) for c in extra[satisfied])
        return self.solve(parent, ids, hypothesis_id=hypothesis_id, window=window, added=None)

    def _key(self, hypothesis: Hypothesis) -> float:
        """:meth:`rank_key` of a hypothesis from a full evaluation (not from the table)."""
        support = self.evaluate(hypothesis, np.arange(len(self._m), dtype=np.int64))[1]
        return self.rank_key(hypothesis, 0, float(support.sum()))

    def _make(self, ids: tuple[int, ...], warm: Hypothesis, hypothesis_id: int, parent_id: int | None, window: int, added: int | None) -> Hypothesis:
        self.forget(hypothesis_id)
        nodes, poses, chi2, odometry = self._solve_set(ids, warm)
        self._chain_chi2[hypothesis_id] = odometry
        return Hypothesis(hypothesis_id, parent_id, ids, window, nodes, poses, chi2=chi2, added_constraint_id=added)

    def solve(self, parent: Hypothesis, constraint_ids: tuple[int, ...], *, hypothesis_id: int, window: int, added: int | None) -> Hypothesis:
        """Solve ``constraint_ids`` from the parent, then refine it to its consensus set, for at
        most ``closure_rounds`` rounds, each kept only if it improves :meth:`rank_key` (a descent
        step on the truncated-least-squares cost):

        * constraints outside it that its solution satisfies (``rᵀR⁻¹r < gate``) join;
        * members leave whose residual fails the gate, or whose leave-one-out test fails it
          (:meth:`leave_one_out`: removing the loop would lower the graph's chi-square by more than
          the gate, the truncated cost of leaving it out). The test is run on the members new
          since the parent and on those with a residual above a third of the gate (a loop that
          bends a weakly held part of the graph, such as the open end of the trajectory, fits its
          own solution well and only this test sees it). The drawn ``added`` stays: this child
          tests it."""
        self._sync()
        ids = tuple(constraint_ids)
        hypothesis = self._make(ids, parent, hypothesis_id, parent.id, window, added)
        all_ids = np.arange(len(self._m), dtype=np.int64)
        ok, support = self.evaluate(hypothesis, all_ids)
        key = self.rank_key(hypothesis, 0, float(support.sum()))
        previous_odometry = self._chain_chi2[hypothesis_id]
        gate = self.gate_chi2
        for _ in range(self.plus.closure_rounds):
            members = np.zeros(len(all_ids), dtype=bool)
            members[list(ids)] = True
            keep = members & ok
            suspect = np.flatnonzero(keep & ((support < 2.0 * gate / 3.0) | ~np.isin(all_ids, parent.constraint_ids)))
            if added is not None:
                suspect = suspect[suspect != added]
            if len(suspect):
                keep[suspect[self.leave_one_out(hypothesis, suspect) > gate]] = False
            if added is not None:
                keep[added] = True
            refined = tuple(int(c) for c in ids if keep[c]) + tuple(int(c) for c in np.flatnonzero(ok & ~members))
            if set(refined) == set(ids):
                break
            candidate = self._make(refined, hypothesis, hypothesis_id, parent.id, window, added)
            ok_c, support_c = self.evaluate(candidate, all_ids)
            key_c = self.rank_key(candidate, 0, float(support_c.sum()))
            if key_c <= key:  # no descent: keep the previous solution
                self.forget(hypothesis_id)
                self._chain_chi2[hypothesis_id] = previous_odometry
                break
            previous_odometry = self._chain_chi2[hypothesis_id]
            hypothesis, ids, ok, support, key = candidate, refined, ok_c, support_c, key_c
        return hypothesis

    def _eligible_mask(self) -> np.ndarray:
        return (self._q - self._m) >= self.plus.min_loop_gap_frames

    # ------------------------------------------------------------------ uncertainty
    def _predicted(self, hypothesis: Hypothesis, ids: np.ndarray) -> np.ndarray:
        """``(K, 3, 3)`` Laplace covariance of each constraint's relative pose ``x_m⁻¹ x_q`` under
        the hypothesis' own pose graph: GTSAM's marginals at its solution, with ``m`` and ``q``
        added as nodes (:func:`~.pose_graph.relative_covariances`)."""
        members = list(hypothesis.constraint_ids)
        ends = [[0], self._m[members], self._q[members], self._m[ids], self._q[ids]]
        nodes = np.unique(np.concatenate(ends)).astype(np.int64)
        graph = pose_graph.build_reduced_graph(self.chain, nodes, self._factors(members))
        poses = hypothesis.poses_at(self.chain, nodes)
        return pose_graph.relative_covariances(graph, poses, nodes, self._m[ids], self._q[ids])

    def mahalanobis(self, hypothesis: Hypothesis, constraint_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Innovation test of each constraint under the hypothesis.

        The innovation ``r = Log(z⁻¹ x_m⁻¹ x_q)`` at the hypothesis' solution has covariance
        ``C = R + Σ_pred`` (:meth:`_predicted`): tight where the hypothesis has closed loops,
        loose after a long open traverse. A hypothesis never changes, so each value is computed
        once (cached until the hypothesis is forgotten). The test is meaningful for constraints
        outside the hypothesis; members have :meth:`leave_one_out`.

        Returns:
            ``(d2 (K,), chi2 (K,))``: ``rᵀ C⁻¹ r`` (exact below ``explore_chi2``; above it, the lower
            bound that screened it out), and the plain whitened residual ``rᵀ R⁻¹ r``.
        """
        self._sync()
        ids = np.asarray(constraint_ids, dtype=np.int64)
        if len(ids) == 0:
            return np.zeros(0), np.zeros(0)
        r = self._residuals(hypothesis, ids)
        chi2 = mahalanobis_d2(r, self._r[ids])
        cache = self._d2.setdefault(hypothesis.id, {})
        todo = np.array([k for k, c in enumerate(ids.tolist()) if c not in cache], dtype=np.int64)
        if len(todo):
            missing = ids[todo]
            # Screen: loops only shrink Σ_pred below the odometry's own segment covariance, so
            # ``d²`` under that is a lower bound; beyond explore_chi2 it is kept as the value.
            bound = mahalanobis_d2(r[todo], self._r[missing] + self.chain.segment_covariance(self._m[missing], self._q[missing]))
            d2 = bound.copy()
            near = bound < self.explore_chi2
            if near.any():
                d2[near] = mahalanobis_d2(r[todo[near]], self._r[missing[near]] + self._predicted(hypothesis, missing[near]))
            cache.update(zip(missing.tolist(), d2.tolist()))
        return np.array([cache[c] for c in ids.tolist()]), chi2

    def leave_one_out(self, hypothesis: Hypothesis, member_ids: np.ndarray) -> np.ndarray:
        """``(K,)`` leave-one-out statistic of members: ``rᵀ (R - Σ_pred)⁻¹ r`` at the solution,
        where ``Σ_pred`` is the covariance of the member's relative pose under the graph that
        includes it. For a linear-Gaussian graph this equals the member's innovation under the
        graph without it, and the drop in the graph's chi-square if it were removed (for
        ``R - Σ_pred = R C⁻¹ R`` and ``r = R C⁻¹ e``). A member that is the only evidence for its
        relative pose has ``R - Σ_pred`` near zero; where that is not positive definite the
        statistic is ``0`` (keep)."""
        ids = np.asarray(member_ids, dtype=np.int64)
        if len(ids) == 0:
            return np.zeros(0)
        r = self._residuals(hypothesis, ids)
        remaining = self._r[ids] - self._predicted(hypothesis, ids)
        remaining = 0.5 * (remaining + np.swapaxes(remaining, -1, -2))
        good = np.all(np.linalg.eigvalsh(remaining) > 1e-9 * np.trace(self._r[ids], axis1=1, axis2=2)[:, None], axis=1)
        out = np.zeros(len(ids))
        if good.any():
            out[good] = mahalanobis_d2(r[good], remaining[good])
        return out

    def _residuals(self, hypothesis: Hypothesis, ids: np.ndarray) -> np.ndarray:
        """``(K, 3)`` loop residuals ``Log(z⁻¹ x_m⁻¹ x_q)`` at the hypothesis' solution."""
        x_m, x_q = np.split(hypothesis.poses_at(self.chain, np.concatenate([self._m[ids], self._q[ids]])), 2)
        return se2.logmap(se2.between(self._z[ids], se2.between(x_m, x_q)))

    def evaluate(self, hypothesis: Hypothesis, constraint_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ids = np.asarray(constraint_ids, dtype=np.int64)
        whole = len(ids) == len(self._m) and (len(ids) == 0 or (ids[0] == 0 and ids[-1] == len(ids) - 1))
        cached = self._evaluated.get(hypothesis.id)
        if whole and cached is not None and cached[0] is hypothesis and len(cached[1]) == len(ids):
            return cached[1], cached[2]
        ok, support = self._evaluate(hypothesis, ids)
        if whole:
            self._evaluated[hypothesis.id] = (hypothesis, ok, support)
        return ok, support

    def _evaluate(self, hypothesis: Hypothesis, constraint_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Consistent: the hypothesis' solution satisfies the constraint, ``rᵀR⁻¹r < gate_chi2``
        (members and others alike; a cheap vectorised test, so every kept hypothesis is checked
        against every constraint). The innovation test under the hypothesis' covariance
        (:meth:`mahalanobis`) decides what a hypothesis absorbs and which draws are plausible.

        Support: ``gate - min(rᵀR⁻¹r, gate)``, the truncated-least-squares cost the hypothesis'
        solution saves on the constraint; :meth:`rank_key` subtracts the odometry chi-square.
        """
        ids = np.asarray(constraint_ids, dtype=np.int64)
        if len(ids) == 0:
            return np.zeros(0, dtype=bool), np.zeros(0)
        self._sync()
        chi2 = mahalanobis_d2(self._residuals(hypothesis, ids), self._r[ids])
        eligible = self._eligible_mask()[ids]
        gate = self.gate_chi2
        return (chi2 < gate) & eligible, np.where(eligible, gate - np.minimum(chi2, gate), 0.0)

    def draw_weights(self, parent: Hypothesis, candidates: np.ndarray) -> np.ndarray | None:
        """Sequential selection draws among the constraints inconsistent with the parent; ``ilv+``
        prefers the nearly consistent ones, ``w = exp(-(d² - gate) / (2 gate))``, floored at
        ``1e-3``, and never tries one beyond ``explore_chi2`` (a child built on it would have to
        bend the parent far beyond its uncertainty). A true loop that only a joint correction can
        satisfy (its innovation just above the gate) is then tried long before the hundreds of
        far-off false candidates, and a window with nothing plausible to try costs nothing. If
        GTSAM cannot compute the parent's marginals, the draw is the paper's uniform one."""
        try:
            d2 = self.mahalanobis(parent, candidates)[0]
        except pose_graph.OptimisationFailed as exc:
            log.warning("ilv+: hypothesis %d: uniform draw (%s)", parent.id, exc.message)
            return None
        gate = self.gate_chi2
        weights = np.maximum(np.exp(-np.maximum(d2 - gate, 0.0) / (2.0 * gate)), 1e-3)
        return np.where(d2 < self.explore_chi2, weights, 0.0)

    def accepted(self, top: Hypothesis, consistent: np.ndarray) -> np.ndarray:
        """The rank-1 hypothesis' own constraints whose residual at its solution passes the gate
        (a constraint outside it that merely lies inside a loose covariance is not accepted; the
        absorb step brings consistent ones inside at every window)."""
        members = np.zeros(len(consistent), dtype=bool)
        members[list(top.constraint_ids)] = True
        return consistent & members

    def rank_key(self, hypothesis: Hypothesis, score: int, support: float) -> float:
        """``-J`` up to a constant: ``J = χ²_odometry + Σ_c min(χ²_c, gate)`` is the truncated-least-
        squares cost of the hypothesis' solution over the whole history (the objective GNC-TLS
        minimises); bending the odometry to satisfy false loops costs ``χ²_odometry``."""
        return float(support - self._chain_chi2.get(hypothesis.id, 0.0))

    def tie_key(self, hypothesis: Hypothesis) -> float:
        return 0.0 if hypothesis.chi2 is None else hypothesis.chi2

    def forget(self, hypothesis_id: int) -> None:
        self._d2.pop(hypothesis_id, None)
        self._evaluated.pop(hypothesis_id, None)
        if hypothesis_id != 0:
            self._chain_chi2.pop(hypothesis_id, None)

    def final_trajectory(self, top: Hypothesis, accepted_ids: tuple[int, ...]) -> np.ndarray:
        if set(accepted_ids) == set(top.constraint_ids):
            return top.trajectory(self.chain)
        try:
            nodes, poses, _, _ = self._solve_set(tuple(accepted_ids), top)
        except pose_graph.OptimisationFailed:
            return top.trajectory(self.chain)
        return self.chain.interpolate(nodes, poses, np.arange(len(self.chain)))


# ----------------------------------------------------------------------------------------------
# Registration
# ----------------------------------------------------------------------------------------------


@register("ilv", help="the paper's multi-model hypothesize-and-verify (full GTSAM graphs, 10 m test)")
def _make_ilv(config: VerificationConfig, *, odometry_information=None) -> IncrementalVerifier:
    return IncrementalVerifier("ilv", config, PaperModel, odometry_information=odometry_information)


@register("ilv+", help="improved ilv (the default): measured loops by cluster consensus against an iSAM2 working hypothesis, same-place loops by a hypothesis table with Mahalanobis tests")
def _make_ilv_plus(config: VerificationConfig, *, odometry_information=None):
    """``ilv+`` for the kind of loop ``config.ilv_plus.loops`` names (``auto``: measured; the replay
    and the bench decide it first, see :func:`~lcv_replay.verification.config.with_loop_kind`)."""
    if config.ilv_plus.loops == "same-place":
        schedule = dataclasses.replace(
            config,
            iterations_per_window=config.ilv_plus.iterations_per_window,
            hypotheses_per_iteration=config.ilv_plus.hypotheses_per_iteration,
            max_hypotheses=config.ilv_plus.max_hypotheses,
        )
        return IncrementalVerifier("ilv+", schedule, PlusModel, odometry_information=odometry_information)
    from lcv_replay.verification.consensus import ConsensusVerifier

    return ConsensusVerifier(config, odometry_information=odometry_information)
