"""A log that grows while a test follows it: a finished MCAP's bytes appended chunk by chunk on a timer.

:func:`rechunk` rewrites a real log with small chunks (cut by size, so chunk boundaries fall inside
frames) and :class:`ChunkAppender` appends a finished file to a new path one chunk (with its message
indexes) at a time, ``period_s`` apart, as a recorder writing that file would; it can stop in the
middle of a chunk record, as a writer that dies leaves a file.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer


def rechunk(source: Path, out: Path, *, chunk_size_bytes: int = 3000) -> Path:
    """``source``'s records (header, metadata, channels, every message in file order) with small chunks."""
    with open(source, "rb") as f, open(out, "wb") as g:
        reader = make_reader(f)
        header = reader.get_header()
        writer = Writer(g, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        # Like a ROS recorder, every channel is registered before the first message (when it subscribes).
        summary = reader.get_summary()
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in sorted(summary.schemas.items())}
        channels = {
            cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id], dict(c.metadata))
            for cid, c in sorted(summary.channels.items())
        }
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            writer.add_message(channels[channel.id], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time, sequence=message.sequence)
        writer.finish()
    return out


def unchunked(source: Path, out: Path) -> Path:
    """``source``'s records written without chunks (every message a top-level record)."""
    with open(source, "rb") as f, open(out, "wb") as g:
        reader = make_reader(f)
        header = reader.get_header()
        writer = Writer(g, use_chunking=False)
        writer.start(profile=header.profile, library=header.library)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        summary = reader.get_summary()
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in sorted(summary.schemas.items())}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id], dict(c.metadata))
                    for cid, c in sorted(summary.channels.items())}
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            writer.add_message(channels[channel.id], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time, sequence=message.sequence)
        writer.finish()
    return out


def chunk_offsets(path: Path) -> tuple[list[int], int]:
    """Start offsets of the chunk records, and where the data section ends (the summary follows)."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    starts = sorted(index.chunk_start_offset for index in summary.chunk_indexes)
    return starts, max(i.chunk_start_offset + i.chunk_length + i.message_index_length for i in summary.chunk_indexes)


class ChunkAppender(threading.Thread):
    """Appends ``source``'s bytes to ``dest`` one chunk at a time (see the module docstring).

    Attributes:
        landed: ``(monotonic time, end offset)`` after each piece is written and flushed.
        done_at: monotonic time when it stopped.
    """

    def __init__(self, source: Path, dest: Path, *, period_s: float, stop_in_chunk: int | None = None,
                 block_bytes: int | None = None):
        super().__init__(daemon=True)
        self.data = Path(source).read_bytes()
        self.dest = Path(dest)
        self.period_s = period_s
        if block_bytes is not None:  # blocks of bytes, cutting records anywhere (an unchunked writer's buffer)
            self.cuts = [*range(block_bytes, len(self.data), block_bytes), len(self.data)]
        else:  # everything before chunk 1, then chunk k with its message indexes, then the summary
            starts, data_end = chunk_offsets(Path(source))
            self.cuts = [*starts[1:], data_end, len(self.data)]
        self.stop_in_chunk = stop_in_chunk
        self.landed: list[tuple[float, int]] = []
        self.done_at: float | None = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with open(self.dest, "wb") as out:
                written = 0
                for k, cut in enumerate(self.cuts):
                    if self.stop_in_chunk is not None and k == self.stop_in_chunk:
                        cut = written + (cut - written) // 2  # the writer dies inside this chunk
                    out.write(self.data[written:cut])
                    out.flush()  # visible to a reader on this machine (no fsync: not a durability test)
                    written = cut
                    self.landed.append((time.monotonic(), cut))
                    if self.stop_in_chunk is not None and k == self.stop_in_chunk:
                        break
                    time.sleep(self.period_s)
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc
        finally:
            self.done_at = time.monotonic()
