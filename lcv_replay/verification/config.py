"""Verification configuration: the paper's hypothesize-and-verify defaults (Tanaka, SII 2016)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class VerificationConfig:
    """Multi-model hypothesize-and-verify (method ``ilv``) and its improved variant ``ilv+``."""

    method: str = "ilv"  # verifier name (registry in lcv_replay.verification)
    consistency_radius_m: float = 10.0  # T_p: constraint consistent if endpoints closer (sec. II-A)
    window_frames: int = 500  # W: time-window length in frames (sec. II-D)
    iterations_per_window: int = 10  # generation iterations per window (sec. II-D)
    hypotheses_per_iteration: int = 10  # top-ranked hypotheses extended per iteration (sec. II-D)
    max_hypotheses: int = 200  # pruning bound on kept hypotheses
    seed: int = 0

    def __post_init__(self) -> None:
        from lcv_replay.config import require

        require(self.consistency_radius_m > 0, "verification.consistency_radius_m", self.consistency_radius_m, "a number > 0")
        require(self.window_frames >= 1, "verification.window_frames", self.window_frames, "an integer >= 1")
        require(self.iterations_per_window >= 1, "verification.iterations_per_window", self.iterations_per_window, "an integer >= 1")
        require(self.hypotheses_per_iteration >= 1, "verification.hypotheses_per_iteration", self.hypotheses_per_iteration, "an integer >= 1")
        require(self.max_hypotheses >= self.hypotheses_per_iteration, "verification.max_hypotheses", self.max_hypotheses, "an integer >= hypotheses_per_iteration")
