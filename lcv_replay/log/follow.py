"""Following a log that is still being written: ``lcv-replay LOG.mcap --follow``, a mode of the reader.

:func:`follow_log` opens an lcv-replay MCAP that a recorder is still writing (``record ... --live``,
or any writer that appends chunks) and offers the interface of :class:`~lcv_replay.log.reader.LogReader`
(``info``, ``frame_stamps_ns``, ``frames()``, ``ground_truth()``, ``true_loops()``, ...): the replay
cannot tell a followed log from a finished one. Underneath:

* :class:`ChunkTail` reads each MCAP record as soon as it is complete on disk (header, metadata,
  schemas, channels, chunks: decompressed and CRC-checked, with the messages indexed), without
  waiting for the summary section; the index is the same :class:`~lcv_replay.log.container.Container`
  the reader builds from a finished file.
* After each growth a :class:`~lcv_replay.log.reader.LogReader` is rebuilt on that index (stereo
  pairing, joins, candidates to frames, all as for a finished file), and ``frames()`` releases the
  frames that are complete: every frame when the log says its chunks end at frame boundaries
  (``chunking = frame``, written by ``record --live``), otherwise the frames older than the newest
  message seen (a later message proves that a frame's messages are all written).
* ``frames()`` ends when the file is finalised (its footer and closing magic appear); after
  ``idle_timeout_s`` seconds without growth (a warning; the complete chunks are used, as with
  ``--recover``: a writer that died leaves a partial last chunk); at the first chunk that fails to
  decompress or its CRC (a warning, as ``--recover``); or when ``stop()`` turns true (Ctrl-C).
  Each ending leaves the replay to finish its outputs as for a finished log.

What ``info`` says is what is known when the replay starts: ``frames``, ``duration_s`` and the
counts are those of the frames written so far, ``growing`` is true; ``has_candidates``,
``has_ground_truth`` and ``has_labels`` follow the channels the writer declared (``record --live``
declares them before the first frame).

Opening refuses (one :class:`LogFormatError`) a file that is not finalised and has not grown for
``idle_timeout_s`` (its modification time is older): its writer is gone, and ``--recover`` is the
way to read it. A finalised file is simply opened as a finished log.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import struct
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from mcap.records import Header, Metadata

from lcv_replay.errors import ConfigError, LogFormatError
from lcv_replay.log import format as fmt
from lcv_replay.log.container import (
    ENTRY_DTYPE,
    MAGIC,
    ChunkInfo,
    Container,
    _message_head,
    _register_definition,
    _scan_chunk,
    decompress_chunk,
    parse_record,
)
from lcv_replay.log.reader import LogReader
from lcv_replay.records import Frame, FrameWindow

log = logging.getLogger(__name__)

_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_OP_METADATA, _OP_DATA_END = 0x0C, 0x0F

#: Seconds between two looks at the file while waiting for it to grow.
DEFAULT_POLL_S = 0.05
#: Default of ``--idle-timeout``: seconds without growth after which a followed log is taken as ended.
DEFAULT_IDLE_TIMEOUT_S = 30.0


class ChunkTail:
    """The MCAP records appended to a file, read as each one becomes complete (no summary needed).

    :meth:`poll` reads every record that is complete on disk since the last call and indexes the
    messages of complete chunks into :attr:`container` (chunk numbers and offsets as
    :func:`~lcv_replay.log.container.load_container` gives them). A partial record at the end of
    the file is left for a later call.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.container = Container(path=self.path, file_size_bytes=0)
        self.size_bytes = 0
        self.finished = False  # the footer was read: the writer finished the file
        self.damaged: str | None = None  # why reading stopped at a complete but damaged chunk
        self.max_log_time_ns = -1  # newest message seen
        self._pos = 0  # offset of the next record (0: the magic is not read yet)
        self._parts: dict[int, list[np.ndarray]] = {}

    @property
    def messages(self) -> int:
        return int(sum(len(t) for t in self.container.entries.values()))

    def poll(self) -> bool:
        """Read what became complete. Returns whether new messages or definitions arrived.

        Raises:
            LogFormatError: the file is gone, shrank (replaced while followed), or is not an MCAP.
        """
        try:
            size = self.path.stat().st_size
        except FileNotFoundError:
            raise LogFormatError("the followed file disappeared", path=self.path, fix="check who removes it") from None
        if size < self.size_bytes:
            raise LogFormatError(
                f"the file shrank from {self.size_bytes} to {size} bytes while being followed (replaced by another recording?)",
                path=self.path,
                fix="follow the new recording from its start",
            )
        self.size_bytes = self.container.file_size_bytes = size
        if self.finished or self.damaged is not None:
            return False
        new = False
        with open(self.path, "rb") as f:
            if self._pos == 0:
                if size < len(MAGIC):
                    return False
                if f.read(len(MAGIC)) != MAGIC:
                    raise LogFormatError("not an MCAP file (no MCAP magic bytes at the start)", path=self.path,
                                         fix="follow a log written by 'lcv-replay record ... --live'")
                self._pos = len(MAGIC)
            while self._pos + 9 <= size:
                f.seek(self._pos)
                opcode, length = struct.unpack("<BQ", f.read(9))
                end = self._pos + 9 + length
                if end > size:
                    break  # the record is still being written
                if opcode == _OP_FOOTER:
                    self.finished = True
                    break
                new |= self._record(opcode, f.read(length) if opcode != _OP_DATA_END else b"")
                if self.damaged is not None:
                    break
                self._pos = end
        if new:
            self.container.entries = {
                cid: parts[0] if len(parts) == 1 else np.concatenate(parts) for cid, parts in self._parts.items()
            }
            for cid, table in self.container.entries.items():
                self._parts[cid] = [table]
        return new

    def _record(self, opcode: int, body: bytes) -> bool:
        """Index one complete record (through the container's parse guards: damage ends the follow
        at this record, as ``--recover`` would)."""
        try:
            return self._index(opcode, body)
        except LogFormatError as exc:
            self.damaged = exc.message
            return False

    def _index(self, opcode: int, body: bytes) -> bool:
        c = self.container
        if opcode == _OP_CHUNK:
            data = decompress_chunk(body, self._pos, self.path)
            found = _scan_chunk(data, len(c.chunks), self._pos, c, self.path)
            start_time, end_time = struct.unpack_from("<QQ", body)  # the chunk parsed: these are there
            chunk_no = len(c.chunks)
            c.chunks.append(ChunkInfo(self._pos, len(body), start_time, end_time))
            c._cache[chunk_no] = data  # the reader decodes from it without reading the file again
            while len(c._cache) > c._cache_size:
                c._cache.popitem(last=False)
            for cid, table in found.items():
                self._parts.setdefault(cid, []).append(table)
                self.max_log_time_ns = max(self.max_log_time_ns, int(table["log_time"].max()))
            return True
        if opcode in (_OP_SCHEMA, _OP_CHANNEL):
            _register_definition(c, opcode, body, self._pos, self.path)
            return True
        if opcode == _OP_METADATA:
            record = parse_record(Metadata, body, offset=self._pos, path=self.path)
            c.metadata[record.name] = dict(record.metadata)
            return True
        if opcode == _OP_HEADER:
            c.library = parse_record(Header, body, offset=self._pos, path=self.path).library
        elif opcode == _OP_MESSAGE:  # a message outside any chunk (an unchunked writer)
            channel_id, log_time = _message_head(body, self._pos, self.path, "")
            self._parts.setdefault(channel_id, []).append(np.array([(log_time, -1, self._pos, channel_id)], dtype=ENTRY_DTYPE))
            self.max_log_time_ns = max(self.max_log_time_ns, int(log_time))
            return True
        return False


@contextlib.contextmanager
def _quiet(logger_name: str) -> Iterator[None]:
    """Silence a logger while a partial log is indexed (its warnings would repeat at every growth)."""
    logger = logging.getLogger(logger_name)
    was = logger.disabled
    logger.disabled = True
    try:
        yield
    finally:
        logger.disabled = was


@dataclasses.dataclass(frozen=True)
class GrowingWindow(FrameWindow):
    """A :class:`~lcv_replay.records.FrameWindow` of a log still being written.

    ``first`` and ``last`` index the frames known when it was made (the replay's start); the
    follower goes on past ``last`` up to ``end_ns`` (``None``: to the end of the recording).
    ``t0_ns`` is the window's start time.
    """

    t0_ns: int = 0
    end_ns: int | None = None


class FollowReader:
    """A log being written, read as it grows (see the module docstring). Made by :func:`follow_log`."""

    def __init__(
        self,
        tail: ChunkTail,
        *,
        idle_timeout_s: float,
        poll_s: float,
        stop: Callable[[], bool],
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        stereo_tolerance_ns: int | None,
    ):
        self.path = tail.path
        self._tail = tail
        self._idle_timeout_s = idle_timeout_s
        self._poll_s = poll_s
        self._stop = stop
        self._clock = clock
        self._sleep = sleep
        self._tolerance_ns = stereo_tolerance_ns
        self._last_growth = clock()
        self._last_size = tail.size_bytes
        self._ended = False
        self.end_reason: str | None = None  # finalised, idle, damaged, stopped
        self._snapshot: LogReader | None = None
        self._ready = 0
        while not self._update():
            if not self._wait_once():
                raise LogFormatError(
                    f"--follow: no complete frame arrived in {self._idle_timeout_s:g} s and the file is not finalised",
                    path=self.path,
                    fix="start the recorder first (record ... --live), raise --idle-timeout, or replay it with --recover",
                )
        info = self._snapshot.info
        channels = {ch.topic for ch in tail.container.channels.values()}
        self.info = dataclasses.replace(
            info,
            growing=not tail.finished,
            has_candidates=info.has_candidates or fmt.LOOP_CANDIDATES_TOPIC in channels,
            has_ground_truth=info.has_ground_truth or fmt.GROUND_TRUTH_TOPIC in channels,
        )

    # -- LogReader's interface ---------------------------------------------------------------------
    def __enter__(self) -> "FollowReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._tail.container._cache.clear()

    @property
    def frame_stamps_ns(self) -> np.ndarray:
        """Stamps of the frames known so far."""
        return self._snapshot.frame_stamps_ns[: self._ready]

    @property
    def calibration(self):
        return self._snapshot.calibration

    def ground_truth(self) -> np.ndarray | None:
        gt = self._snapshot.ground_truth()
        return None if gt is None else gt[: self._ready]

    def odometry(self) -> np.ndarray:
        return self._snapshot.odometry()[: self._ready]

    def true_loops(self) -> set[tuple[int, int]]:
        return {p for p in self._snapshot.true_loops() if p[0] < self._ready}

    def loop_candidates(self) -> list:
        return [c for c in self._snapshot.loop_candidates() if c.query_frame < self._ready]

    @property
    def chunks_decoded(self) -> int:
        return self._tail.container.chunks_decoded

    def window(self, start_offset_s: float = 0.0, duration_s: float | None = None) -> "GrowingWindow":
        """The frames of ``[stamp_0 + start_offset_s, + duration_s)``: ``first``/``last`` among the frames
        known now (``last`` grows as :meth:`frames` follows the file), and the window's times."""
        if not (math.isfinite(start_offset_s) and start_offset_s >= 0):
            raise ConfigError(f"start offset {start_offset_s} s must be >= 0", fix="pass a non-negative --start-offset")
        if duration_s is not None and not (duration_s > 0):
            raise ConfigError(f"duration {duration_s} s must be > 0", fix="pass a positive --duration")
        stamps = self.frame_stamps_ns
        t0 = int(stamps[0]) + round(start_offset_s * 1e9)
        t_end = None if duration_s is None or not math.isfinite(duration_s) else t0 + round(duration_s * 1e9)
        first = int(np.searchsorted(stamps, t0, "left"))
        last = len(stamps) if t_end is None else int(np.searchsorted(stamps, t_end, "left"))
        return GrowingWindow(first, last, t0_ns=t0, end_ns=t_end)

    def frames(
        self, *, start_offset_s: float = 0.0, duration_s: float | None = None, window: FrameWindow | None = None
    ) -> Iterator[Frame]:
        """Frames in time order as they are written, within ``[start + start_offset_s, + duration_s)``
        (or a :meth:`window`). Frames keep their log indices.

        Blocks while waiting for the file to grow; ends as the module docstring says.
        """
        if window is None:
            window = self.window(start_offset_s, duration_s)
        if isinstance(window, GrowingWindow):
            return self._follow(window.first, window.end_ns)
        return self._follow(window.first, int(self._snapshot.frame_stamps_ns[window.last - 1]) + 1 if window.last else None)

    # -- following ---------------------------------------------------------------------------------
    def _follow(self, first: int, t_end: int | None) -> Iterator[Frame]:
        i = first
        while True:
            snapshot, ready = self._snapshot, self._ready
            stamps = snapshot._tables.stamps_ns
            while i < ready:
                if t_end is not None and int(stamps[i]) >= t_end:
                    return
                yield next(snapshot._iter_frames(i, i + 1))
                i += 1
            if self._ended:
                return
            while not self._update():
                if not self._wait_once():
                    break

    def _update(self) -> bool:
        """Read what the file gained; returns whether more frames are ready (or the log ended)."""
        tail = self._tail
        new = tail.poll()
        if tail.size_bytes != self._last_size:
            self._last_size, self._last_growth = tail.size_bytes, self._clock()
        if tail.finished:
            self._finish("finalised")
            return True
        if tail.damaged is not None:
            log.warning("%s: %s; ending the follow with the complete chunks before it (as --recover)", self.path, tail.damaged)
            self._finish("damaged", recovered=True)
            return True
        if not new and self._snapshot is not None:
            return False
        before = self._ready
        self._rebuild()
        return self._snapshot is not None and self._ready > before

    def _wait_once(self) -> bool:
        """Sleep one poll period; ``False`` when waiting should end (idle timeout or stop)."""
        if self._stop():
            if self._snapshot is None:  # stopped before the first frame: nothing to follow
                from lcv_replay.shutdown import Interrupted, current_signal

                raise Interrupted(current_signal())
            self._end_now("stopped")
            return False
        idle_s = self._clock() - self._last_growth
        if idle_s >= self._idle_timeout_s:
            if self._snapshot is None:
                return False
            log.warning(
                "%s: no growth for %.1f s (--idle-timeout) and not finalised: the writer stopped; "
                "ending with the %d complete chunks (as --recover)", self.path, idle_s, len(self._tail.container.chunks),
            )
            self._finish("idle", recovered=True)
            return False
        self._sleep(self._poll_s)
        return True

    def _end_now(self, reason: str) -> None:
        self._ended, self.end_reason = True, reason

    def _finish(self, reason: str, *, recovered: bool = False) -> None:
        """The last snapshot: all frames of a finalised file, or the complete frames of an abandoned one."""
        container = self._tail.container
        if recovered:
            container.recovered_messages = self._tail.messages
            container.skipped_chunks = 1 if reason == "damaged" else 0
        if self._snapshot is None and not any(len(t) for t in container.entries.values()):
            raise LogFormatError("the log ended without a frame", path=self.path, fix="check the recorder")
        self._snapshot = LogReader(container, stereo_tolerance_ns=self._tolerance_ns)
        self._ready = len(self._snapshot._tables.stamps_ns)
        self._end_now(reason)

    def _rebuild(self) -> None:
        container = self._tail.container
        try:
            with _quiet("lcv_replay.log.reader"):
                snapshot = LogReader(container, stereo_tolerance_ns=self._tolerance_ns)
        except LogFormatError:
            defining = [cid for cid, ch in container.channels.items() if ch.topic in (fmt.LEFT_IMAGE_TOPIC, fmt.ODOM_TOPIC)]
            if any(len(container.entries.get(cid, ())) for cid in defining):
                raise  # the log has frames and still fails: a real format error
            return  # nothing to make frames of yet
        stamps = snapshot._tables.stamps_ns
        if container.metadata.get(fmt.METADATA_NAME, {}).get("chunking") == "frame":
            ready = len(stamps)  # every chunk ends at a frame boundary
        else:
            ready = int(np.searchsorted(stamps, self._tail.max_log_time_ns, side="left"))
        self._snapshot = snapshot
        self._ready = max(self._ready, ready)


def follow_log(
    path: str | Path,
    *,
    recover: bool = False,
    idle_timeout_s: float = DEFAULT_IDLE_TIMEOUT_S,
    poll_s: float = DEFAULT_POLL_S,
    stop: Callable[[], bool] | None = None,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    stereo_tolerance_ns: int | None = None,
) -> "FollowReader | LogReader":
    """Open ``path`` to follow it as it is written (see the module docstring).

    Args:
        path: an lcv-replay MCAP log being written.
        recover: accepted for the ``open_reader`` interface; a followed log always ends like
            ``--recover`` when its writer stops.
        idle_timeout_s: seconds without growth after which the log is taken as ended.
        poll_s: seconds between two looks at the file.
        stop: returns true when following should end (Ctrl-C).
        clock, sleep: injectable time (tests).

    Returns:
        A :class:`FollowReader`, or a plain :class:`LogReader` when the file is already finalised.

    Raises:
        LogFormatError: the file is missing, not an MCAP, not finalised and not growing, or
            malformed.
        ConfigError: ``idle_timeout_s`` or ``poll_s`` is not positive.
    """
    if not (idle_timeout_s > 0 and math.isfinite(idle_timeout_s)):
        raise ConfigError(f"--idle-timeout {idle_timeout_s} must be a positive number of seconds", fix="pass e.g. --idle-timeout 30")
    if not poll_s > 0:
        raise ConfigError(f"poll period {poll_s} must be positive")
    path = Path(path)
    if not path.exists():
        raise LogFormatError("file not found", path=path, fix="check the path (start the recorder with --live first)")
    if not path.is_file():
        raise LogFormatError("not a file", path=path, fix="pass an .mcap file")
    tail = ChunkTail(path)
    tail.poll()
    if tail.finished:
        from lcv_replay.log.reader import open_log

        return open_log(path, recover=recover, stereo_tolerance_ns=stereo_tolerance_ns)
    stale_s = time.time() - os.stat(path).st_mtime
    if stale_s > idle_timeout_s:
        raise LogFormatError(
            f"--follow: the file is not finalised and not growing (last written {stale_s:.0f} s ago, "
            f"--idle-timeout {idle_timeout_s:g} s): its writer is gone",
            path=path,
            fix="replay it with --recover to use its complete chunks",
        )
    return FollowReader(
        tail, idle_timeout_s=idle_timeout_s, poll_s=poll_s, stop=stop or (lambda: False), clock=clock, sleep=sleep,
        stereo_tolerance_ns=stereo_tolerance_ns,
    )
