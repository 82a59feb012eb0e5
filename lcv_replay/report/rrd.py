"""Read a replay's :class:`~lcv_replay.sinks.run_record.RunRecord` back from its ``.rrd``.

The Rerun sink stores the record's columns as static ``/postmortem/<table>`` entities
(:data:`~lcv_replay.sinks.blueprint.POSTMORTEM`); this reads them with ``rerun.chunk.RrdReader``
(only those static chunks) and rebuilds the record.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from lcv_replay.errors import LcvError
from lcv_replay.sinks import blueprint as bp
from lcv_replay.sinks.run_record import RunRecord


class RecordingError(LcvError):
    """A recording cannot be read, or is not a finished lcv-replay recording."""


def read_run_record(path: str | Path) -> RunRecord:
    """The run record stored in the recording ``path``.

    Raises:
        RecordingError: the file is missing, not an .rrd, truncated, or not an lcv-replay
            recording (no ``/postmortem`` data: another tool's recording, or one whose replay
            failed before it ended).
    """
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.is_file():
        raise RecordingError("recording not found", path=path, fix="pass the .rrd a replay wrote (--save)")
    tables: dict[str, dict[str, list]] = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "no footer/manifest" on a truncated file: the read below fails clearly
            stream = RrdReader(path).stream().filter(content=f"{bp.POSTMORTEM}/**", is_static=True)
            for chunk in stream:
                table = chunk.entity_path.rsplit("/", 1)[-1]
                batch = chunk.to_record_batch()
                columns = tables.setdefault(table, {})
                for name in batch.schema.names:
                    if name.startswith("rerun."):
                        continue
                    values = batch.column(name).to_pylist()
                    if values and values[-1] is not None:
                        columns[name] = values[-1]  # the last row of a static entity wins
    except (RuntimeError, ValueError, OSError) as exc:
        raise RecordingError(f"not a readable Rerun recording ({_first_line(exc)})", path=path,
                             fix="pass a complete .rrd written by 'lcv-replay LOG.mcap --save'") from None
    if "meta" not in tables:
        raise RecordingError("not an lcv-replay post-mortem recording (it has no /postmortem data)", path=path,
                             fix="pass a recording written by 'lcv-replay LOG.mcap' with this version, to its end")
    try:
        return RunRecord.from_columns(tables)
    except (KeyError, ValueError, TypeError, IndexError) as exc:
        raise RecordingError(f"the recording's post-mortem data is incomplete ({_first_line(exc)})", path=path,
                             fix="re-run the replay with this version of lcv-replay") from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
