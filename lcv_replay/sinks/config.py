"""Rerun sink configuration."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RerunConfig:
    """What the Rerun sink logs, and how much."""

    image_every: int = 10  # log the left camera image every k-th frame (0: never)
    log_right_image: bool = False
    top_hypotheses: int = 10  # trajectories of the top-k hypotheses drawn on the map
    memory_limit: str = "25%"  # viewer memory limit for --spawn/--serve

    def __post_init__(self) -> None:
        from lcv_replay.config import require

        require(self.image_every >= 0, "rerun.image_every", self.image_every, "an integer >= 0")
        require(self.top_hypotheses >= 1, "rerun.top_hypotheses", self.top_hypotheses, "an integer >= 1")
