"""Rerun sink configuration."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from lcv_replay.errors import require


@dataclass(frozen=True)
class RerunConfig:
    """What the Rerun sink logs, and how much."""

    image_every: int = 10  # log the left camera image every k-th frame (0: never)
    log_right_image: bool = False
    top_hypotheses: int = 10  # trajectories of the top-k hypotheses drawn on the map
    memory_limit: str = "25%"  # viewer memory limit for --spawn/--serve

    def __post_init__(self) -> None:
        require(self.image_every >= 0, "rerun.image_every", self.image_every, "an integer >= 0")
        require(self.top_hypotheses >= 1, "rerun.top_hypotheses", self.top_hypotheses, "an integer >= 1")


@dataclass(frozen=True)
class RerunOutputs:
    """Where a recording goes (CLI options, not config); several can be combined (tee).

    Attributes:
        save: the .rrd to write (``None``: no file); overwritten if it exists.
        spawn: start a local viewer and stream to it.
        connect: URL of a running viewer (``rerun+http://127.0.0.1:9876/proxy``).
        serve: host a gRPC server and the web viewer, both bound to 127.0.0.1.
        grpc_port, web_port: ports for ``spawn`` (gRPC) and ``serve``.
        memory_limit: viewer / server memory limit (``"25%"``, ``"4GB"``); ``None``: the config's.
    """

    save: Path | None = None
    spawn: bool = False
    connect: str | None = None
    serve: bool = False
    grpc_port: int = 9876
    web_port: int = 9090
    memory_limit: str | None = None

    @property
    def any(self) -> bool:
        return self.save is not None or self.spawn or self.connect is not None or self.serve

    @property
    def live(self) -> bool:
        """Whether a viewer watches while the replay runs."""
        return self.spawn or self.connect is not None or self.serve
