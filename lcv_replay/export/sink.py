"""``--export DIR``: the run's results as files other tools read, written when the replay ends.

=====================  ==========================================================================
``trajectory.tum``     the final estimate (evo ``tum``: ``stamp x y z qx qy qz qw``, z = 0)
``trajectory.kitti``   the same poses as ``3 × 4`` matrices (evo ``kitti``)
``odometry.tum``       the log's odometry
``ground_truth.tum``   the ground truth, where the log has it (frames without it left out)
``loops.csv``          every constraint with its fate (``lcv_replay.export.formats.LOOP_COLUMNS``)
``accepted.g2o``       odometry plus the accepted loops, with their information (``record g2o``
                       reads it back)
``config.toml``        the resolved config (``--config`` loads it back)
``summary.json``       the ``--summary-json`` document
=====================  ==========================================================================

Each file is written to a temp file and renamed (an interrupted export never leaves a half-written
file); after Ctrl-C the files hold the run as of its last completed window.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TextIO

from lcv_replay.errors import OutputError
from lcv_replay.export import formats
from lcv_replay.fileio import write_text_atomic
from lcv_replay.sinks.base import BaseSink, RunSummary
from lcv_replay.sinks.run_record import RunRecord, RunRecorder

EXPORT_FILES = (
    "trajectory.tum", "trajectory.kitti", "odometry.tum", "ground_truth.tum",
    "loops.csv", "accepted.g2o", "config.toml", "summary.json",
)


def check_export_folder(folder: str | Path) -> Path:
    """Validate ``--export DIR`` before any work: an existing writable folder, or a new one whose
    parent exists (it is created). Raises :class:`OutputError` otherwise."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError("--export needs a folder, but this is a file", path=folder, fix="name a folder (it is created if missing)")
    if not folder.exists():
        parent = folder.parent if str(folder.parent) else Path(".")
        if not parent.is_dir():
            raise OutputError("the export folder's parent does not exist", path=folder, fix=f"create {parent} first")
        if not os.access(parent, os.W_OK):
            raise OutputError("cannot create the export folder here (not writable)", path=folder, fix="choose another folder")
    elif not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError("the export folder is not writable", path=folder, fix="choose another folder")
    _probe(folder if folder.exists() else (folder.parent if str(folder.parent) else Path(".")), folder)
    return folder


def _probe(where: Path, folder: Path) -> None:
    """Create and remove a file in ``where``: permissions say little to root, a read-only or
    virtual file system (``/proc``) only answers a real write."""
    import tempfile

    try:
        with tempfile.TemporaryFile(dir=where):
            pass
    except OSError as exc:
        raise OutputError(f"cannot write into {'the export folder' if where == folder else 'its parent'} "
                          f"({exc.strerror or exc})", path=folder, fix="choose another folder") from None


def export_files(record: RunRecord, summary_json_text: str) -> dict[str, str]:
    """``{file name: text}`` of an export (``ground_truth.tum`` only where the run has truth)."""
    estimate = record.estimate if record.estimate is not None else record.odometry
    files = {
        "trajectory.tum": formats.tum_text(record.stamps_ns, estimate),
        "trajectory.kitti": formats.kitti_text(estimate),
        "odometry.tum": formats.tum_text(record.stamps_ns, record.odometry),
    }
    if record.ground_truth is not None:
        files["ground_truth.tum"] = formats.tum_text(record.stamps_ns, record.ground_truth)
    files["loops.csv"] = formats.loops_csv_text(record.loops)
    accepted = [loop for loop in record.loops if loop.state == "accepted"]
    files["accepted.g2o"] = formats.g2o_text(estimate, record.odometry, record.odometry_information, accepted)
    files["config.toml"] = formats.toml_text(record.config)
    files["summary.json"] = summary_json_text
    return files


def write_export(folder: str | Path, record: RunRecord, summary_json_text: str) -> list[Path]:
    """Write :func:`export_files` into ``folder`` (created if missing), each file atomically."""
    folder = check_export_folder(folder)
    folder.mkdir(exist_ok=True)
    written = []
    for name, text in export_files(record, summary_json_text).items():
        written.append(write_text_atomic(folder / name, text))
    return written


class ExportSink(BaseSink):
    """Writes the export into ``folder`` at ``on_finish`` from ``recorder``'s record.

    ``recorder`` must come before this sink in the replay's sink list (it builds the record in its
    own ``on_finish``). The folder is checked when the sink is built, before any work starts. A
    line naming the folder and the files is printed to ``stream``.
    """

    def __init__(self, recorder: RunRecorder, folder: str | Path, *, stream: TextIO | None = None):
        self.recorder = recorder
        self.folder = check_export_folder(folder)
        self.stream = stream
        self.written: list[Path] = []

    def on_finish(self, summary: RunSummary) -> None:
        from lcv_replay.sinks.summary import summary_json

        if self.recorder.record is None:
            raise RuntimeError("ExportSink: the RunRecorder must come before it in the sink list")
        self.written = write_export(self.folder, self.recorder.record, summary_json(summary))
        if self.stream is not None:
            names = ", ".join(p.name for p in self.written)
            print(f"  export            {self.folder}{os.sep}  ({names})", file=self.stream, flush=True)
