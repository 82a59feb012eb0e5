"""Feeding verifiers frame by frame, shared by the verification tests (synthetic worlds are in
:mod:`tests.verification.ilv_synthetic`)."""

from __future__ import annotations

import dataclasses

from lcv_replay.records import LoopCandidate, Pose2D
from lcv_replay.verification.config import VerificationConfig

#: A small ilv/ilv+ configuration for fast tests: windows of 100 frames, few hypotheses; ``ilv+``
#: is its hypothesis-table verifier (same-place loops: the synthetic worlds' candidates carry no
#: relative pose). The cluster-consensus verifier (measured loops) has its own tests.
SMALL = VerificationConfig(window_frames=100, iterations_per_window=3, hypotheses_per_iteration=3, max_hypotheses=8)
SMALL = dataclasses.replace(
    SMALL, ilv_plus=dataclasses.replace(SMALL.ilv_plus, loops="same-place", iterations_per_window=3, hypotheses_per_iteration=3, max_hypotheses=8)
)
#: The default configuration with ``ilv+``'s hypothesis-table verifier (for its tests on real,
#: measured loops, which the default would give to the cluster-consensus verifier).
TABLE = VerificationConfig()
TABLE = dataclasses.replace(TABLE, ilv_plus=dataclasses.replace(TABLE.ilv_plus, loops="same-place"))


def candidates_by_query(candidates) -> dict[int, list[LoopCandidate]]:
    """Candidates keyed by their query frame (the frame at which they arrive)."""
    by_query: dict[int, list[LoopCandidate]] = {}
    for c in candidates:
        by_query.setdefault(c.query_frame, []).append(c)
    return by_query


def feed_frames(verifier, odom, by_frame: dict[int, list[LoopCandidate]]):
    """Feed odometry poses frame by frame, with ``by_frame[k]`` added at frame ``k``; returns the steps."""
    steps = []
    for k, pose in enumerate(odom):
        verifier.add_frame(k, Pose2D(*pose))
        verifier.add_candidates(by_frame.get(k, []))
        step = verifier.step()
        if step is not None:
            steps.append(step)
    return steps


def feed(verifier, world, *, extra: dict[int, list[LoopCandidate]] | None = None):
    """Feed ``world`` frame by frame; returns the steps."""
    by_query = candidates_by_query(world.candidates)
    for k, extra_list in (extra or {}).items():
        by_query.setdefault(k, []).extend(extra_list)
    return feed_frames(verifier, world.odom, by_query)
