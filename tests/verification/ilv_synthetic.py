"""Tiny synthetic pose-graph worlds for the ilv / pose-graph tests (no data files needed).

A robot drives ``laps`` laps of a circle; its odometry has a yaw bias, so the odometry-only
trajectory drifts. True loop candidates join frames one lap apart (same place); false candidates
join frames on opposite sides of the circle (far apart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lcv_replay.records import LoopCandidate
from lcv_replay.verification.base import Constraint
from lcv_replay import se2

ODOM_INFORMATION = np.diag([400.0, 400.0, 40000.0])  # sigma 5 cm, 5 cm, 0.005 rad per step


@dataclass(frozen=True)
class World:
    """``truth (N, 3)``, ``odom (N, 3)`` cumulative odometry, candidates (query > match)."""

    truth: np.ndarray
    odom: np.ndarray
    true_candidates: tuple[LoopCandidate, ...]
    false_candidates: tuple[LoopCandidate, ...]
    frames_per_lap: int

    @property
    def candidates(self) -> tuple[LoopCandidate, ...]:
        """True and false candidates, sorted by query frame (arrival order)."""
        return tuple(sorted(self.true_candidates + self.false_candidates, key=lambda c: (c.query_frame, c.match_frame)))

    def is_true(self, candidate: LoopCandidate) -> bool:
        return candidate.pair in {c.pair for c in self.true_candidates}


def circle_world(
    *,
    frames_per_lap: int = 200,
    laps: float = 2.0,
    radius_m: float = 60.0,
    yaw_bias_rad: float = 0.0015,
    true_every: int = 10,
    num_false: int = 6,
    seed: int = 0,
) -> World:
    """A circle driven ``laps`` times with drifting odometry, true and false loop candidates."""
    rng = np.random.default_rng(seed)
    n = int(frames_per_lap * laps)
    angle = 2.0 * np.pi * np.arange(n) / frames_per_lap
    truth = np.stack([radius_m * np.sin(angle), radius_m * (1.0 - np.cos(angle)), angle], axis=1)
    truth[:, 2] = (truth[:, 2] + np.pi) % (2 * np.pi) - np.pi
    steps = se2.between(truth[:-1], truth[1:])
    steps[:, 2] += yaw_bias_rad
    steps[:, :2] += rng.normal(0.0, 0.02, size=(n - 1, 2))
    odom = np.zeros((n, 3))
    for k, step in enumerate(steps):
        odom[k + 1] = se2.compose(odom[k], step)
    true_c = tuple(
        LoopCandidate(q, q - frames_per_lap, similarity=0.9, source="synthetic")
        for q in range(frames_per_lap + 5, n, true_every)
    )
    false_c = []
    for _ in range(num_false if n > frames_per_lap else 0):
        q = int(rng.integers(frames_per_lap, n))
        m = (q - frames_per_lap // 2) % frames_per_lap  # the opposite side: 2 * radius apart
        false_c.append(LoopCandidate(q, m, similarity=0.5, source="synthetic"))
    return World(truth, odom, true_c, tuple(false_c), frames_per_lap)


def as_constraints(candidates) -> list[Constraint]:
    """Candidates as a constraint history with ids 0.. in the given order."""
    return [Constraint(k, c, c.query_frame) for k, c in enumerate(candidates)]
