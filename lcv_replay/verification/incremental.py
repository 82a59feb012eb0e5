"""The incremental schedule of multi-model hypothesize-and-verify (paper sec. II-D).

:class:`IncrementalVerifier` is the thin stateful shell shared by ``ilv`` and ``ilv+``. It owns the
frames (an :class:`~lcv_replay.verification.measurements.OdometryChain`), the constraint history,
the kept hypotheses, the consistency table and the random generator; a :class:`HypothesisModel`
says how a hypothesis is solved, tested against constraints and ranked.

Schedule, at the end of every window of ``W`` frames (and once more in :meth:`result` for the last,
partial window):

0. (``ilv+`` only) the model recalibrates its test to the rank-1 hypothesis
   (:meth:`HypothesisModel.recalibrate`); if the test changed, the kept rows are rewritten;
1. the constraints that arrived during the window add columns to the table (every kept hypothesis
   is tested against them; nothing else is recomputed, see :mod:`~.consistency`);
2. (``ilv+`` only) the top hypotheses absorb the new constraints consistent with them
   (:meth:`HypothesisModel.absorb`; generation edge ``(parent, child, ABSORBED)``);
3. ``iterations_per_window`` iterations; each takes the ``hypotheses_per_iteration`` top-ranked
   hypotheses (ranking refreshed every iteration) and extends each by one constraint drawn by
   sequential selection (:mod:`~.hypotheses`); each child is solved warm-started from its parent
   and adds one row to the table. With the paper's 10 × 10 that is ``N_g = 100`` per window. A
   parent is never extended twice by the same constraint (the child would be the same);
4. after each iteration the lowest-ranked hypotheses are pruned so that at most ``max_hypotheses``
   are kept (the odometry root is always kept and counts towards the bound); (``ilv+`` only) the
   rank-1 hypothesis after the iterations absorbs too, unless it already did in step 2;
5. a :class:`~lcv_replay.verification.base.VerifierStep` reports the ranking, the generation edges,
   the accepted constraints (``ilv``: those consistent with the rank-1 hypothesis; ``ilv+``: the
   rank-1 hypothesis' own constraints that its solution satisfies), the top-k trajectories and
   the table.

Space is bounded by ``max_hypotheses`` rows (plus one iteration's children) of ``C`` entries and
each kept hypothesis' nodes (``ilv``: every frame; ``ilv+``: its loop endpoints): linear in the
log length and the history, never quadratic.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import numpy as np

from lcv_replay.errors import VerificationError
from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification.base import Constraint, HypothesisSummary, VerificationResult, VerifierStep
from lcv_replay.verification.base import ConstraintHistory, checked_frame, default_informations
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.verification.consistency import ConsistencyTable, position_consistent
from lcv_replay.verification.hypotheses import (
    Hypothesis,
    draw_constraint,
    odometry_root,
    prune,
    rank_order,
    selectable_constraints,
)
from lcv_replay.verification.measurements import OdometryChain
from lcv_replay.verification.pose_graph import OptimisationFailed

log = logging.getLogger(__name__)

#: ``constraint_id`` of a generation edge whose child absorbed every constraint consistent with
#: its parent (``ilv+``), rather than one drawn constraint.
ABSORBED = -1


class HypothesisModel(Protocol):
    """How hypotheses are solved, tested and ranked (``ilv`` and ``ilv+`` differ only here)."""

    #: the chi-square gate in force, reported with each step (``None``: the model has none).
    gate_chi2: float | None

    def eligible(self, constraints: Sequence[Constraint]) -> np.ndarray:
        """``(K,)`` bool: which of these (new) constraints may ever be drawn or accepted."""

    def solve(self, parent: Hypothesis, constraint_ids: tuple[int, ...], *, hypothesis_id: int, window: int, added: int) -> Hypothesis:
        """Optimise the odometry plus ``constraint_ids`` warm-started from ``parent``.

        Raises:
            OptimisationFailed: the optimiser failed (the hypothesis is dropped, not the run).
        """

    def evaluate(self, hypothesis: Hypothesis, constraint_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """``((K,) bool, (K,) float or None)``: which constraints are consistent with the
        hypothesis, and each one's support (a float summed for ranking; ``None`` for none)."""

    def rank_key(self, hypothesis: Hypothesis, score: int, support: float) -> float:
        """Larger ranks first (``ilv``: the score; ``ilv+``: the support)."""

    def tie_key(self, hypothesis: Hypothesis) -> float:
        """Smaller ranks first among equal ``rank_key`` (then the older id)."""

    def forget(self, hypothesis_id: int) -> None:
        """Drop any per-hypothesis cache (the hypothesis was pruned)."""

    def absorb(self, parent: Hypothesis, *, hypothesis_id: int, window: int) -> Hypothesis | None:
        """A child of ``parent`` that also optimises the constraints consistent with it (new
        evidence for the same world), or ``None`` (``ilv``: the paper has no such step)."""

    def draw_weights(self, parent: Hypothesis, candidates: np.ndarray) -> np.ndarray | None:
        """Weights (``>= 0``; 0 = never) of the constraints a child of ``parent`` may be drawn
        with, or ``None`` for a uniform draw (``ilv``, the paper)."""

    def recalibrate(self, top: Hypothesis) -> bool:
        """Called at each window end with the current rank-1 hypothesis before anything else;
        returns whether the consistency test changed, in which case every kept row is
        re-evaluated (``ilv``: never)."""

    def accepted(self, top: Hypothesis, consistent: np.ndarray) -> np.ndarray:
        """``(C,)`` bool: the accepted loop closures given the rank-1 hypothesis and its row
        (``ilv``: the row itself, paper sec. II-A)."""

    def final_trajectory(self, top: Hypothesis, accepted_ids: tuple[int, ...]) -> np.ndarray:
        """``(N, 3)``: the trajectory reported in the result."""


ModelFactory = Callable[[OdometryChain, ConstraintHistory, VerificationConfig], HypothesisModel]


@dataclass
class _Generation:
    """What one window end generated (for its :class:`VerifierStep`)."""

    timings: dict[str, float]
    edges: list[tuple[int, int, int]] = field(default_factory=list)
    created: list[int] = field(default_factory=list)
    dropped: list[tuple[int, str]] = field(default_factory=list)


class WindowedVerifier:
    """The frame-by-frame shell of a windowed verifier (``ilv``, ``ilv+``): odometry buffered until
    the window end, candidates admitted into the history, a step at every window of
    ``config.window_frames`` frames. A subclass sets ``name``, ``config``, ``chain``, ``history``,
    ``_pending`` (buffered odometry), ``_stepped_frames`` and ``_result``, and implements
    :meth:`_window_end`."""

    name: str
    config: VerificationConfig
    chain: OdometryChain
    history: ConstraintHistory
    _pending: list[tuple[float, float, float]]
    _stepped_frames: int
    _result: VerificationResult | None

    def add_frame(self, frame_index: int, odom: Pose2D) -> None:
        self._pending.append(checked_frame(self.name, frame_index, self.num_frames, odom, finished=self._result is not None))

    def add_candidates(self, candidates: Sequence[LoopCandidate]) -> list[Constraint]:
        if self._result is not None:
            raise VerificationError(f"{self.name}: add_candidates after result()", fix="build a new verifier")
        return self.history.admit(candidates, self.num_frames)

    @property
    def num_frames(self) -> int:
        """Frames added so far."""
        return len(self.chain) + len(self._pending)

    def step(self) -> VerifierStep | None:
        n = self.num_frames
        if n == 0 or n % self.config.window_frames != 0 or n == self._stepped_frames:
            return None
        return self._window_end()

    def _window_end(self) -> VerifierStep:
        raise NotImplementedError

    def _finish(self, step: VerifierStep, trajectory: np.ndarray) -> VerificationResult:
        """The result of the last ``step`` with the final ``trajectory`` (kept: ``result()`` is
        idempotent); the paper's consistent set is judged on that trajectory."""
        constraints = tuple(self.history.constraints)
        paper: tuple[int, ...] = ()
        if constraints:
            q = np.array([c.query_frame for c in constraints])
            m = np.array([c.match_frame for c in constraints])
            ok = position_consistent(trajectory[q], trajectory[m], self.config.consistency_radius_m)
            paper = tuple(int(i) for i in np.flatnonzero(ok))
        self._result = VerificationResult(
            method=self.name,
            constraints=constraints,
            accepted_constraint_ids=step.accepted_constraint_ids,
            trajectory=trajectory,
            ranking=step.ranking,
            paper_consistent_ids=paper,
            last_step=step,
            ambiguous_constraint_ids=step.ambiguous_constraint_ids,
        )
        return self._result


class IncrementalVerifier(WindowedVerifier):
    """Multi-model hypothesize-and-verify, fed frame by frame (the ``Verifier`` protocol).

    Args:
        name: the method name (``"ilv"``, ``"ilv+"``).
        config: window length, iterations, bound and seed.
        model_factory: builds the :class:`HypothesisModel` over this verifier's chain and history.
        odometry_information: ``(3, 3)`` information of one odometry step from the log, or
            ``None`` for ``config.odometry_sigmas``.
    """

    def __init__(
        self,
        name: str,
        config: VerificationConfig,
        model_factory: ModelFactory,
        *,
        odometry_information: np.ndarray | None = None,
    ):
        self.name = name
        self.config = config
        odom_info, loop_info = default_informations(config, odometry_information)
        self.chain = OdometryChain(odom_info)
        self.history = ConstraintHistory(loop_info)
        self.model = model_factory(self.chain, self.history, config)
        self.rng = np.random.default_rng(config.seed)
        self.table = ConsistencyTable()
        self.hypotheses: dict[int, Hypothesis] = {}
        self._sets: dict[frozenset[int], int] = {}
        self._tried: dict[int, set[int]] = {}  # per hypothesis: constraints its children were drawn with
        self._eligible = np.zeros(0, dtype=bool)
        self._next_id = 0
        self._window = 0
        self._stepped_frames = 0
        self._pending: list[tuple[float, float, float]] = []  # odometry not yet appended to the chain
        self._last_step: VerifierStep | None = None
        self._result: VerificationResult | None = None

    # ------------------------------------------------------------------ Verifier protocol

    def _flush(self) -> None:
        """Append the buffered odometry to the chain (done once per window, not per frame)."""
        if self._pending:
            self.chain.extend(np.asarray(self._pending, dtype=np.float64))
            self._pending.clear()

    def result(self) -> VerificationResult:
        if self._result is not None:
            return self._result
        if self.num_frames == 0:
            raise VerificationError(f"{self.name}: no frames were added", fix="feed at least one frame")
        self._flush()
        if len(self.chain) != self._stepped_frames or len(self.history) != self.table.num_constraints:
            self._window_end()
        step = self._last_step
        assert step is not None  # a window end ran above or earlier
        top = self.hypotheses[step.ranking[0].id]
        return self._finish(step, self.model.final_trajectory(top, step.accepted_constraint_ids))

    # ------------------------------------------------------------------ the schedule
    def ranked_ids(self) -> list[int]:
        """Kept hypothesis ids, best first."""
        ids = self.table.hypothesis_ids
        keys = {h: self.model.rank_key(self.hypotheses[h], self.table.score(h), self.table.support(h)) for h in ids}
        ties = {h: self.model.tie_key(self.hypotheses[h]) for h in ids}
        return rank_order(ids, keys, ties)

    def _window_end(self) -> VerifierStep:
        start = time.perf_counter()
        timings = {"columns": 0.0, "optimise": 0.0, "rows": 0.0, "prune": 0.0}
        self._flush()
        n = len(self.chain)
        constraints = self.history.constraints
        first_new = self.table.num_constraints
        new_ids = np.arange(first_new, len(constraints), dtype=np.int64)
        if new_ids.size:
            self._eligible = np.concatenate([self._eligible, self.model.eligible(constraints[first_new:])])
        if 0 not in self.hypotheses:
            root = odometry_root(self.chain, window=self._window)
            self._keep(root, *self.model.evaluate(root, np.arange(first_new, dtype=np.int64)))
        # 0. the model may recalibrate its test to the best hypothesis (ilv+): rows are rewritten
        t = time.perf_counter()
        if first_new and self.model.recalibrate(self.hypotheses[self.ranked_ids()[0]]):
            old_ids = np.arange(first_new, dtype=np.int64)
            for h in self.table.hypothesis_ids:
                self.table.rewrite(h, *self.model.evaluate(self.hypotheses[h], old_ids))
        timings["calibrate"] = time.perf_counter() - t
        # 1. new constraints -> new columns
        t = time.perf_counter()
        if new_ids.size:
            ids = self.table.hypothesis_ids
            evaluations = [self.model.evaluate(self.hypotheses[h], new_ids) for h in ids]
            block = np.stack([e[0] for e in evaluations])
            support = None if evaluations[0][1] is None else np.stack([e[1] for e in evaluations])
            self.table.add_constraints(ids, block, support)
        timings["columns"] += time.perf_counter() - t
        # 2-3. generation and pruning
        gen = _Generation(timings)
        all_ids = np.arange(len(constraints), dtype=np.int64)
        absorbed: set[int] = set()
        if new_ids.size:
            for parent_id in self.ranked_ids()[: self.config.hypotheses_per_iteration]:
                self._absorb(gen, parent_id, all_ids, absorbed)
        for _ in range(self.config.iterations_per_window):
            grew = False
            for parent_id in self.ranked_ids()[: self.config.hypotheses_per_iteration]:
                parent = self.hypotheses[parent_id]
                tried = self._tried.setdefault(parent_id, set())
                eligible = self._eligible.copy()
                eligible[list(tried)] = False  # the same draw from the same parent gives the same child
                choices = selectable_constraints(parent, self.table.row(parent_id), eligible=eligible, existing_sets=self._sets)
                weights = self.model.draw_weights(parent, choices) if len(choices) else None
                if weights is not None:
                    choices, weights = choices[weights > 0], weights[weights > 0]
                added = draw_constraint(self.rng, choices, weights)
                if added is None:
                    continue
                tried.add(added)
                grew |= self._try_child(
                    gen, parent_id, added, all_ids,
                    lambda child_id: self.model.solve(
                        parent, parent.constraint_ids + (added,), hypothesis_id=child_id, window=self._window, added=added
                    ),
                )
            self._prune(gen)
            if not grew:
                break  # nothing left to draw for the top hypotheses
        # 3b. the best hypothesis found in this window absorbs what it now explains as well
        if new_ids.size and self._absorb(gen, self.ranked_ids()[0], all_ids, absorbed):
            self._prune(gen)
        # 4. report
        ranking_ids = self.ranked_ids()
        summaries = tuple(self._summary(h, rank) for rank, h in enumerate(ranking_ids, start=1))
        by_id = {s.id: s for s in summaries}
        top = ranking_ids[0]
        accepted_mask = self.model.accepted(self.hypotheses[top], self.table.row(top)) & self._eligible
        accepted = tuple(int(i) for i in np.flatnonzero(accepted_mask))
        top_k = ranking_ids[: self.config.top_k_trajectories]
        trajectories = {h: self.hypotheses[h].trajectory(self.chain) for h in top_k}
        timings["total"] = time.perf_counter() - start
        step = VerifierStep(
            frame_index=n - 1,
            window_index=self._window,
            new_constraint_ids=tuple(int(i) for i in new_ids),
            new_hypotheses=tuple(by_id[h] for h in gen.created if h in by_id),
            generation_edges=tuple(gen.edges),
            ranking=summaries,
            accepted_constraint_ids=accepted,
            trajectories=trajectories,
            consistency=self.table.matrix(ranking_ids),
            timings_s=timings,
            dropped=tuple(gen.dropped),
            gate_chi2=self.model.gate_chi2,
        )
        self._window += 1
        self._stepped_frames = n
        self._last_step = step
        return step

    # ------------------------------------------------------------------ internals
    def _prune(self, gen: "_Generation") -> None:
        """Keep the ``max_hypotheses`` best-ranked (and the root)."""
        t = time.perf_counter()
        kept, pruned = prune(self.ranked_ids(), self.config.max_hypotheses, keep={0})
        for rank, h in enumerate(pruned, start=len(kept) + 1):
            self._forget(h)
            gen.dropped.append((h, f"pruned at rank {rank}"))
        gen.timings["prune"] += time.perf_counter() - t

    def _absorb(self, gen: "_Generation", parent_id: int, all_ids: np.ndarray, absorbed: set[int]) -> bool:
        """The :meth:`HypothesisModel.absorb` child of ``parent_id``, once per parent per window."""
        if parent_id in absorbed:
            return False
        absorbed.add(parent_id)
        parent = self.hypotheses[parent_id]
        return self._try_child(
            gen, parent_id, ABSORBED, all_ids,
            lambda child_id: self.model.absorb(parent, hypothesis_id=child_id, window=self._window),
        )

    def _try_child(self, gen: "_Generation", parent_id: int, added: int, all_ids: np.ndarray, make: Callable[[int], Hypothesis | None]) -> bool:
        """Create one child with ``make(child_id)``; keep it unless it fails, is ``None`` or repeats
        a kept constraint set. Returns whether a hypothesis was kept."""
        child_id = self._next_id
        t = time.perf_counter()
        try:
            child = make(child_id)
        except OptimisationFailed as exc:
            what = "its consistent constraints" if added == ABSORBED else f"constraint {added}"
            log.warning("%s: dropped hypothesis %d (parent %d + %s): %s", self.name, child_id, parent_id, what, exc.message)
            self._next_id += 1
            gen.dropped.append((child_id, f"optimiser failure: {exc.message}"))
            return False
        finally:
            gen.timings["optimise"] += time.perf_counter() - t
        if child is None:
            return False
        self._next_id += 1
        gen.edges.append((parent_id, child_id, added))
        if child.constraint_set in self._sets:
            gen.dropped.append((child_id, f"same constraint set as hypothesis {self._sets[child.constraint_set]}"))
            self.model.forget(child_id)
            return False
        t = time.perf_counter()
        self._keep(child, *self.model.evaluate(child, all_ids))
        gen.timings["rows"] += time.perf_counter() - t
        gen.created.append(child_id)
        return True

    def _keep(self, hypothesis: Hypothesis, row: np.ndarray, support: np.ndarray | None = None) -> None:
        self.table.add_hypothesis(hypothesis.id, row, support)
        self.hypotheses[hypothesis.id] = hypothesis
        self._sets[hypothesis.constraint_set] = hypothesis.id
        self._next_id = max(self._next_id, hypothesis.id + 1)

    def _forget(self, hypothesis_id: int) -> None:
        hypothesis = self.hypotheses.pop(hypothesis_id)
        self.table.remove([hypothesis_id])
        if self._sets.get(hypothesis.constraint_set) == hypothesis_id:
            del self._sets[hypothesis.constraint_set]
        self._tried.pop(hypothesis_id, None)
        self.model.forget(hypothesis_id)

    def _summary(self, hypothesis_id: int, rank: int) -> HypothesisSummary:
        h = self.hypotheses[hypothesis_id]
        score = self.table.score(hypothesis_id)
        return HypothesisSummary(
            id=h.id,
            parent_id=h.parent_id,
            constraint_ids=h.constraint_ids,
            score=score,
            rank=rank,
            window=h.window,
            chi2=h.chi2,
            rank_key=float(self.model.rank_key(h, score, self.table.support(hypothesis_id))),
        )

