"""Dataset recorders: one module per source format, each writing an lcv-replay MCAP log.

Every recorder is a function ``record_<name>(source, out_path, options, *, force=False,
progress=None) -> RecordStats`` (see :class:`Recorder`), with a frozen ``<Name>Options``
dataclass; ``synthetic`` has no source (``record_synthetic(out_path, options, ...)``,
``takes_source=False``). :data:`RECORDERS` maps the CLI name to its module and function; modules are imported
only when a recorder is looked up, so that listing them stays cheap.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from lcv_replay.errors import RecorderError


class Recorder(Protocol):
    """A recorder: a source dataset and options in, one log out (written atomically, or chunk by chunk with ``live``)."""

    def __call__(
        self, source: Any, out_path: str | Path, options: Any, *, force: bool = False, progress: Any = None, live: bool = False
    ) -> Any: ...


@dataclass(frozen=True)
class RecorderInfo:
    """Registry entry: CLI ``name``, the ``module`` and ``function`` that record, a one-line ``summary``.

    ``takes_source`` is false for recorders that generate their data (``synthetic``): their
    function has no ``source`` argument.
    """

    name: str
    module: str
    function: str
    options: str
    summary: str
    takes_source: bool = True

    def load(self) -> Recorder:
        """Import the module and return the recorder function."""
        return getattr(importlib.import_module(self.module), self.function)

    def load_options(self) -> type:
        """Import the module and return its options dataclass."""
        return getattr(importlib.import_module(self.module), self.options)


RECORDERS: dict[str, RecorderInfo] = {
    info.name: info
    for info in (
        RecorderInfo("synthetic", "recorders.synthetic", "record_synthetic", "SyntheticOptions", "the built-in procedural street world", takes_source=False),
        RecorderInfo("kitti", "recorders.kitti", "record_kitti", "KittiOptions", "KITTI odometry layout (sequences/SS/image_0, image_1, calib.txt, times.txt)"),
        RecorderInfo("euroc", "recorders.euroc", "record_euroc", "EurocOptions", "EuRoC ASL layout (mav0/cam0, mav0/cam1, state_groundtruth_estimate0)"),
        RecorderInfo("folder", "recorders.folder", "record_folder", "FolderOptions", "left/right image folders plus a planar odometry CSV"),
        RecorderInfo("g2o", "recorders.g2o", "record_g2o", "G2oOptions", "a 2-D pose graph (g2o, TORO, Vertigo ground truth)"),
        RecorderInfo("rosbag", "recorders.rosbag", "record_rosbag", "RosbagOptions", "ROS 1 bags, ROS 2 bags (sqlite3, MCAP) through rosbags: images, odometry from a pose topic or TF, ground truth"),
        RecorderInfo("ros2", "recorders.rosbag", "record_rosbag", "RosbagOptions", "alias of rosbag"),
    )
}


def get_recorder(name: str) -> RecorderInfo:
    """The registry entry for ``name``; raises :class:`RecorderError` listing the known names."""
    try:
        return RECORDERS[name]
    except KeyError:
        raise RecorderError(f"unknown recorder {name!r}", fix=f"use one of {', '.join(sorted(RECORDERS))}") from None
