"""Trajectory hypotheses and their generation by sequential selection (paper sec. II-C).

A hypothesis is the trajectory that pose-graph SLAM estimates from the odometry plus a chosen set of
constraints. It is stored as the poses of the frames its graph solved (``node_frames``):

* ``ilv`` solves the full graph, so its nodes are every frame ``0..M-1`` known at its
  optimisation; frames added later extend it by odometry from frame ``M-1``;
* ``ilv+`` solves a reduced graph whose nodes are frame 0 and its constraints' endpoints; the other
  frames are the Brownian-bridge interpolation of the odometry between nodes
  (:meth:`~lcv_replay.verification.measurements.OdometryChain.interpolate`), extended by odometry
  after the last node.

Either way a hypothesis never changes after it is created, which is what makes the consistency
table append-only (:mod:`lcv_replay.verification.consistency`).

Sequential selection: the root is odometry only; the first constraint of a branch is drawn at
random; each next constraint is drawn among those **inconsistent** with the parent, and the child
optimises the parent's constraints plus the new one, warm-started from the parent's estimate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import AbstractSet, Mapping

import numpy as np

from lcv_replay.verification.measurements import OdometryChain


@dataclass(frozen=True, eq=False)
class Hypothesis:
    """One trajectory hypothesis.

    Attributes:
        id: unique, 0 is the odometry-only root.
        parent_id: the hypothesis it was extended from (``None`` for the root).
        constraint_ids: the constraints its pose graph optimises, in the order they were added.
        window: the window in which it was created.
        node_frames: ``(K,)`` increasing frame indices its graph solved, ``node_frames[0] == 0``.
        node_poses: ``(K, 3)`` their poses ``[x_m, y_m, yaw_rad]``.
        chi2: whitened chi-square of its pose-graph solution (``None`` for the root).
        added_constraint_id: the constraint drawn to create it (``None`` for the root).
    """

    id: int
    parent_id: int | None
    constraint_ids: tuple[int, ...]
    window: int
    node_frames: np.ndarray
    node_poses: np.ndarray
    chi2: float | None = None
    added_constraint_id: int | None = None
    constraint_set: frozenset[int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "constraint_set", frozenset(self.constraint_ids))
        self.node_frames.flags.writeable = False
        self.node_poses.flags.writeable = False

    @property
    def is_root(self) -> bool:
        return self.parent_id is None

    def poses_at(self, chain: OdometryChain, frames: np.ndarray) -> np.ndarray:
        """``(F, 3)`` poses of ``frames`` (any frames of ``chain``) under this hypothesis."""
        return chain.interpolate(self.node_frames, self.node_poses, np.asarray(frames, dtype=np.int64))

    def trajectory(self, chain: OdometryChain) -> np.ndarray:
        """``(N, 3)`` poses of every frame of ``chain``."""
        return self.poses_at(chain, np.arange(len(chain)))


def odometry_root(chain: OdometryChain, *, window: int = 0) -> Hypothesis:
    """The root: odometry only (one node, frame 0; every other frame extended by odometry)."""
    return Hypothesis(0, None, (), window, np.zeros(1, dtype=np.int64), chain.poses[:1].copy())


def selectable_constraints(
    parent: Hypothesis,
    consistent: np.ndarray,
    *,
    eligible: np.ndarray | None = None,
    existing_sets: AbstractSet[frozenset[int]] | Mapping[frozenset[int], int] = frozenset(),
) -> np.ndarray:
    """Constraint ids a child of ``parent`` may be extended with (paper sec. II-C).

    * the root's first constraint may be any constraint ("drawn at random");
    * otherwise only constraints **inconsistent** with the parent;
    * never one the parent already optimises, an ineligible one, or one that would recreate the
      constraint set of a hypothesis already kept.

    Args:
        consistent: ``(C,)`` bool, the parent's row of the consistency table.
        eligible: ``(C,)`` bool, or ``None`` for all.

    Returns:
        ``(K,)`` int64 ids, increasing.
    """
    consistent = np.asarray(consistent, dtype=bool)
    mask = np.ones(len(consistent), dtype=bool) if parent.is_root else ~consistent
    if eligible is not None:
        mask &= np.asarray(eligible, dtype=bool)
    if parent.constraint_ids:
        mask[list(parent.constraint_ids)] = False
    ids = np.flatnonzero(mask)
    if existing_sets and len(ids):
        base = parent.constraint_set
        ids = np.array([c for c in ids.tolist() if base | {c} not in existing_sets], dtype=np.int64)
    return ids.astype(np.int64)


def draw_constraint(rng: np.random.Generator, candidates: np.ndarray, weights: np.ndarray | None = None) -> int | None:
    """One id drawn from ``candidates`` (``None`` if empty): uniformly (the paper), or with
    probabilities proportional to ``weights`` (``(K,)``, positive)."""
    if len(candidates) == 0:
        return None
    if weights is None:
        return int(candidates[rng.integers(len(candidates))])
    weights = np.asarray(weights, dtype=np.float64)
    return int(candidates[rng.choice(len(candidates), p=weights / weights.sum())])


def rank_order(ids: list[int], keys: Mapping[int, float], tie_keys: Mapping[int, float] | None = None) -> list[int]:
    """Hypothesis ids sorted best first: larger ``keys`` first, then smaller ``tie_keys``, then
    smaller id (older first), so the order is deterministic."""
    ties = tie_keys or {}
    return sorted(ids, key=lambda h: (-keys[h], ties.get(h, 0.0), h))


def prune(ranked_ids: list[int], max_hypotheses: int, *, keep: AbstractSet[int] = frozenset()) -> tuple[list[int], list[int]]:
    """Keep the ``max_hypotheses`` best-ranked ids (plus any in ``keep``, e.g. the root, which
    count towards the bound); returns ``(kept, pruned)``, both in rank order."""
    kept: list[int] = [h for h in ranked_ids if h in keep]
    for h in ranked_ids:
        if len(kept) >= max_hypotheses:
            break
        if h not in keep:
            kept.append(h)
    kept_set = set(kept)
    kept = [h for h in ranked_ids if h in kept_set]
    pruned = [h for h in ranked_ids if h not in kept_set]
    return kept, pruned
