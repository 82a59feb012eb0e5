"""Low-level MCAP container access for the reader: index, chunk cache, recovery.

This module knows MCAP records but nothing about lcv-replay topics. :func:`load_container` builds a
:class:`Container`: schemas, channels, metadata, the list of chunks and, per channel, a table of
every message's ``log_time`` and location, in file order. It is built from the summary section and
the message-index records that follow each chunk, so opening a log decodes no chunk. Without a
summary (or with ``recover=True``) it falls back to one linear scan over the records.

Chunks are decompressed (and their CRC checked) only when a message in them is read;
:attr:`Container.chunks_decoded` counts that, so tests can prove that time-window reads skip
chunks.

**Every byte is parsed behind one guard.** Record framing goes through :func:`iter_records` and
:func:`read_record_head`, record bodies through :func:`parse_record`, chunks through
:func:`decompress_chunk`. Damage never escapes as ``struct.error``, ``UnicodeDecodeError`` or
``mcap.exceptions.EndOfFile``: it is a :class:`~lcv_replay.errors.LogFormatError` that names the
record kind and its byte offset, e.g. ``the metadata record at byte 1234 is damaged (a string in it
is not valid UTF-8)``. A reader that follows a growing file can reuse the same guards.

**What the official ``mcap`` library does here, and what stays hand-written (and why):**

* Record bodies (Header, Footer, Schema, Channel, Chunk, ChunkIndex, Metadata, MetadataIndex,
  Message) are parsed by :mod:`mcap.records`, through a strict stream: mcap's ``ReadDataStream``
  returns a short string silently when a length field is damaged.
* Hand-written: finding the footer and checking the summary CRC (``SeekingReader.get_summary``
  checks no CRC and cannot tell a truncated file from one with bytes appended); the message-index
  tables (numpy over the record bytes: ``MessageIndex.read`` is a Python loop per entry, and mcap's
  readers give no random access to one message, they decompress and walk whole chunks);
  decompression with a size check (mcap's ``get_chunk_data_stream`` returns a stream, not the
  bytes that message offsets point into, and checks no size for lz4 or uncompressed chunks); and
  recover mode (mcap's stream reader stops at the first damage without saying what it kept).
"""

from __future__ import annotations

import io
import logging
import mmap
import re
import struct
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Footer, Header, Message, Metadata, MetadataIndex, Schema

from lcv_replay.errors import LogFormatError

log = logging.getLogger(__name__)

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_FOOTER_SIZE = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc
_DATA_END_SIZE = 1 + 8 + 4  # opcode, length, data_section_crc
_MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time
#: The largest chunk this reader decompresses (mcap's own default record size limit).
MAX_CHUNK_BYTES = 4 << 30
_MAX_LOG_TIME_NS = (1 << 63) - 1  # stamps are int64 nanoseconds downstream
_RECOVER_FIX = "re-run with --recover to salvage the complete chunks"
_DAMAGED_FIX = "the file is corrupted; re-copy it, or " + _RECOVER_FIX
_INDEX_FIX = "the index is damaged; re-run with --recover, which rebuilds it by scanning the chunks"

# Entries of the per-channel message tables: log_time, chunk number (-1: a message record outside
# any chunk, located in the file itself), byte offset (in the decompressed chunk, or the file) and
# the channel the index says the message is on (checked when the message is read).
ENTRY_DTYPE = np.dtype([("log_time", "<i8"), ("chunk", "<i4"), ("offset", "<i8"), ("channel", "<u2")])


@dataclass(frozen=True)
class ChunkInfo:
    """Where a chunk record lies in the file and how to decompress it."""

    file_offset: int  # offset of the chunk record's opcode
    record_length: int  # bytes of the record body (after opcode + length)
    start_time_ns: int
    end_time_ns: int


@dataclass(frozen=True)
class RawMessage:
    """One message record: channel, sequence, times and undecoded payload."""

    channel_id: int
    sequence: int
    log_time_ns: int
    publish_time_ns: int
    data: bytes


@dataclass
class Container:
    """What the reader needs from an MCAP file (see module docstring)."""

    path: Path
    file_size_bytes: int
    library: str = ""
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    chunks: list[ChunkInfo] = field(default_factory=list)
    entries: dict[int, np.ndarray] = field(default_factory=dict)  # channel id -> ENTRY_DTYPE, file order
    recovered_messages: int | None = None  # set by recover mode
    skipped_chunks: int = 0  # complete chunks dropped by recover mode (the first damaged one and all after it)
    damage: str | None = None  # recover mode: the first damage found, where reading stopped (None: none)
    data_end_offset: int | None = None  # offset of the DataEnd record (None: not located, e.g. recover mode)
    chunks_decoded: int = 0  # chunk decompressions done for message reads (not index building)
    _cache: OrderedDict = field(default_factory=OrderedDict, repr=False)
    _cache_size: int = 4

    # -- message access ---------------------------------------------------------------------------
    def chunk_data(self, chunk_no: int) -> bytes:
        """Decompressed records of chunk ``chunk_no`` (LRU-cached; CRC checked)."""
        data = self._cache.get(chunk_no)
        if data is not None:
            self._cache.move_to_end(chunk_no)
            return data
        with open(self.path, "rb") as f:
            data = _read_chunk(f, self.chunks[chunk_no], self.path)
        self.chunks_decoded += 1
        self._cache[chunk_no] = data
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return data

    def read_message(self, chunk_no: int, offset: int) -> RawMessage:
        """The message record at ``offset`` of chunk ``chunk_no`` (or of the file when ``chunk_no == -1``)."""
        if chunk_no < 0:
            with open(self.path, "rb") as f:
                f.seek(offset)
                head = f.read(9)
                opcode, length = read_record_head(head, 0, offset=offset, path=self.path, section="the file")
                body = f.read(length)
            where = ""
            if len(body) != length:
                raise damaged(record_kind(opcode), offset, f"it declares {length} bytes, past the end of the file", path=self.path)
        else:
            data = self.chunk_data(chunk_no)
            where = f" of the chunk at byte {self.chunks[chunk_no].file_offset}"
            if offset + 9 > len(data):
                raise LogFormatError(
                    f"the message index points to byte {offset}{where}, past its end ({len(data)} bytes)",
                    path=self.path,
                    fix=_INDEX_FIX,
                )
            opcode, length = _RECORD_HEAD.unpack_from(data, offset)
            if offset + 9 + length > len(data):
                raise damaged(
                    record_kind(opcode), offset, f"it declares {length} bytes, past the end of the chunk",
                    path=self.path, where=where, fix=_INDEX_FIX,
                )
            body = data[offset + 9 : offset + 9 + length]
        if opcode != Opcode.MESSAGE:
            raise LogFormatError(
                f"expected a message record at byte {offset}{where}, found a {record_kind(opcode)} record",
                path=self.path,
                fix=_INDEX_FIX,
            )
        record = parse_record(Message, body, offset=offset, path=self.path, where=where, fix=_INDEX_FIX)
        return RawMessage(record.channel_id, record.sequence, record.log_time, record.publish_time, record.data)

    def read_entry(self, entry: np.void) -> RawMessage:
        """The message of a table row, checked against the index: the channel and ``log_time`` must match.

        Message indexes carry no CRC, so a damaged entry is caught here, where it is used.
        """
        chunk_no, offset = int(entry["chunk"]), int(entry["offset"])
        raw = self.read_message(chunk_no, offset)
        if raw.channel_id != int(entry["channel"]) or raw.log_time_ns != int(entry["log_time"]):
            where = "the file" if chunk_no < 0 else f"the chunk at byte {self.chunks[chunk_no].file_offset}"
            raise LogFormatError(
                f"the message index of {where} is damaged: its entry for byte {offset} says channel "
                f"{int(entry['channel'])} at {int(entry['log_time'])} ns, but the message there is on channel "
                f"{raw.channel_id} at {raw.log_time_ns} ns",
                path=self.path,
                fix=_INDEX_FIX,
            )
        return raw

    def verify_chunks(self) -> None:
        """Decompress every chunk once and check its CRC (raises :class:`LogFormatError`)."""
        with open(self.path, "rb") as f:
            for chunk in self.chunks:
                _read_chunk(f, chunk, self.path)

    def verify_data_section(self) -> None:
        """Check the data-section CRC of the DataEnd record, when the file has one (not 0).

        It covers what no other CRC does: metadata, message indexes and the schema and channel
        records outside chunks.
        """
        if self.data_end_offset is None:
            return
        with open(self.path, "rb") as f:
            f.seek(self.data_end_offset)
            head = f.read(_DATA_END_SIZE)
            if len(head) != _DATA_END_SIZE or head[0] != Opcode.DATA_END:
                return
            (stored,) = struct.unpack_from("<I", head, 9)
            if stored == 0:
                return
            f.seek(0)
            crc, left = 0, self.data_end_offset
            while left > 0:
                block = f.read(min(left, 1 << 20))
                if not block:
                    break
                crc = zlib.crc32(block, crc)
                left -= len(block)
        if crc != stored:
            raise LogFormatError(
                f"the data section (bytes 0..{self.data_end_offset}) fails its CRC check "
                f"(stored 0x{stored:08x}, computed 0x{crc:08x}); every chunk passes its own, so a record "
                "outside the chunks is damaged (metadata, a message index, a schema or a channel)",
                path=self.path,
                fix="re-copy the file, or re-run with --recover to read what is intact",
            )

    def topic_channels(self, topic: str) -> list[int]:
        """Channel ids on ``topic`` (usually zero or one)."""
        return [cid for cid, ch in self.channels.items() if ch.topic == topic]


# -- the parse guards -----------------------------------------------------------------------------
class _StrictStream(ReadDataStream):
    """mcap's ``ReadDataStream`` that refuses short reads (the original returns a short string)."""

    def read(self, length: int) -> bytes:
        data = super().read(length)
        if len(data) != length:
            raise EndOfFile()
        return data


def record_kind(opcode: int) -> str:
    """``0x0c -> 'metadata'``, ``0x07 -> 'message index'``; unknown opcodes by number."""
    try:
        return Opcode(opcode).name.lower().replace("_", " ")
    except ValueError:
        return f"unknown (opcode 0x{opcode:02x})"


def _class_kind(cls: type) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", " ", cls.__name__).lower()


def _reason(exc: BaseException) -> str:
    if isinstance(exc, EndOfFile):
        return "its fields run past its end"
    if isinstance(exc, UnicodeDecodeError):
        return "a string in it is not valid UTF-8"
    if isinstance(exc, struct.error):
        return "a field is cut off"
    return str(exc) or type(exc).__name__


def damaged(kind: str, offset: int, reason: str, *, path: Path, where: str = "", fix: str = _DAMAGED_FIX) -> LogFormatError:
    """The error for a damaged record: ``the <kind> record at byte <offset><where> is damaged (<reason>)``."""
    return LogFormatError(f"the {kind} record at byte {offset}{where} is damaged ({reason})", path=path, fix=fix)


def parse_record(cls: type, body: bytes, *, offset: int, path: Path, where: str = "", fix: str = _DAMAGED_FIX):
    """Parse a record body with the official :mod:`mcap.records` class ``cls``.

    ``offset`` is the byte offset of the record's opcode (in the file, or in the decompressed chunk
    that ``where`` names, e.g. ``" of the chunk at byte 1234"``). Raises :class:`LogFormatError`
    naming the record kind and the offset on any damage.
    """
    stream = _StrictStream(io.BytesIO(body))
    try:
        return cls.read(stream, len(body)) if cls is Message else cls.read(stream)
    except Exception as exc:  # EndOfFile, struct.error, UnicodeDecodeError, ...
        raise damaged(_class_kind(cls), offset, _reason(exc), path=path, where=where, fix=fix) from None


def read_record_head(buf: bytes, pos: int, *, offset: int, path: Path, section: str) -> tuple[int, int]:
    """``(opcode, body length)`` of the record starting at ``buf[pos]`` (file offset ``offset``)."""
    if pos + 9 > len(buf):
        raise LogFormatError(
            f"{section} ends inside a record header at byte {offset} (truncated)", path=path, fix=_RECOVER_FIX
        )
    return _RECORD_HEAD.unpack_from(buf, pos)


def iter_records(buf: bytes, *, base_offset: int, path: Path, section: str, where: str = "") -> Iterator[tuple[int, int, bytes]]:
    """Yield ``(opcode, offset, body)`` for the consecutive records of ``buf``.

    ``base_offset`` is the offset of ``buf[0]``; ``section`` names ``buf`` in messages ("the summary
    section"). A record whose declared length runs past the end of ``buf`` raises
    :class:`LogFormatError` naming its kind and offset.
    """
    pos = 0
    while pos < len(buf):
        opcode, length = read_record_head(buf, pos, offset=base_offset + pos, path=path, section=section)
        end = pos + 9 + length
        if end > len(buf):
            raise damaged(
                record_kind(opcode),
                base_offset + pos,
                f"it declares {length} bytes, past the end of {section}",
                path=path,
                where=where,
            )
        yield opcode, base_offset + pos, buf[pos + 9 : end]
        pos = end


def decompress_chunk(body: bytes, file_offset: int, path: Path) -> bytes:
    """The records of a chunk record body: parsed, decompressed, size and CRC checked."""
    chunk = parse_record(Chunk, body, offset=file_offset, path=path)
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        raise damaged("chunk", file_offset, f"it declares {chunk.uncompressed_size} uncompressed bytes", path=path)
    what = f"the chunk at byte {file_offset}"
    try:
        if chunk.compression == "zstd":
            import zstandard

            content_size = zstandard.frame_content_size(chunk.data)
            if content_size > chunk.uncompressed_size:
                raise ValueError(f"its zstd frame declares {content_size} bytes, the chunk {chunk.uncompressed_size}")
            data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
        elif chunk.compression == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(chunk.data)
        elif chunk.compression == "":
            data = chunk.data
        else:
            raise LogFormatError(
                f"{what} uses unsupported compression {chunk.compression!r}",
                path=path,
                fix="re-encode the file with zstd, lz4 or no compression (mcap convert)",
            )
    except LogFormatError:
        raise
    except Exception as exc:  # zstd/lz4 errors, MemoryError on a damaged size
        raise LogFormatError(f"{what} cannot be decompressed ({exc})", path=path, fix=_DAMAGED_FIX) from None
    if len(data) != chunk.uncompressed_size:
        raise LogFormatError(
            f"{what} decompresses to {len(data)} bytes, expected {chunk.uncompressed_size}", path=path, fix=_DAMAGED_FIX
        )
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise LogFormatError(
            f"{what} fails its CRC check (stored 0x{chunk.uncompressed_crc:08x}, computed 0x{zlib.crc32(data):08x})",
            path=path,
            fix="the file is corrupted; re-copy it, or " + _RECOVER_FIX + " that pass",
        )
    return data


def _read_chunk(f, chunk: ChunkInfo, path: Path) -> bytes:
    f.seek(chunk.file_offset + 9)
    body = f.read(chunk.record_length)
    if len(body) != chunk.record_length:
        raise LogFormatError(f"the chunk at byte {chunk.file_offset} is cut off (truncated file)", path=path, fix=_RECOVER_FIX)
    return decompress_chunk(body, chunk.file_offset, path)


def _pread(f, offset: int, length: int) -> bytes:
    f.seek(offset)
    return f.read(length)


# -- opening ----------------------------------------------------------------------------------------
def load_container(path: str | Path, *, recover: bool = False) -> Container:
    """Index an MCAP file without decoding its chunks (see the module docstring).

    Raises:
        LogFormatError: not a file, not an MCAP, truncated or with bytes appended (unless
            ``recover``), a damaged summary, index or record; the message names the record kind
            and the byte offset.
    """
    path = Path(path)
    if not path.exists():
        raise LogFormatError("file not found", path=path, fix="check the path")
    if not path.is_file():
        raise LogFormatError("not a file", path=path, fix="pass an .mcap file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(8)
        if head != MAGIC:
            what = "the file is empty" if size == 0 else "not an MCAP file (no MCAP magic bytes at the start)"
            raise LogFormatError(what, path=path, fix="pass a log written by 'lcv-replay record' (or any MCAP file)")
        container = Container(path=path, file_size_bytes=size)
        if recover:
            _linear_scan(f, container, size, recover=True)
            return container
        footer = _read_footer(f, size, path)
        container.library = _read_header(f, path).library
        footer_offset = size - 8 - _FOOTER_SIZE
        if footer.summary_start == 0:
            _linear_scan(f, container, footer_offset, recover=False)
        else:
            _load_from_summary(f, container, footer_offset, footer)
    return container


def _read_footer(f, size: int, path: Path) -> Footer:
    """The Footer record before the closing magic; a precise error when it is not there."""
    footer_offset = size - 8 - _FOOTER_SIZE
    if footer_offset >= 8:
        tail = _pread(f, footer_offset, _FOOTER_SIZE + 8)
        opcode, length = _RECORD_HEAD.unpack_from(tail)
        looks_like_footer = opcode == Opcode.FOOTER and length == 20
        if tail[-8:] == MAGIC:
            if looks_like_footer:
                return parse_record(Footer, tail[9:_FOOTER_SIZE], offset=footer_offset, path=path, fix=_RECOVER_FIX)
            end = _find_mcap_end(f, size)
            if end is None:
                raise damaged(
                    "footer", footer_offset, f"found opcode 0x{opcode:02x} with length {length}", path=path, fix=_RECOVER_FIX
                )
        elif looks_like_footer:
            raise LogFormatError(
                f"the closing magic bytes at byte {size - 8} are damaged", path=path, fix=_RECOVER_FIX
            )
    end = _find_mcap_end(f, size)
    if end is not None and end < size:
        raise LogFormatError(
            f"{size - end} bytes of unexpected data follow the end of the MCAP at byte {end} (appended to the file)",
            path=path,
            fix=f"cut them off with 'truncate -s {end} {path}', or {_RECOVER_FIX}",
        )
    raise LogFormatError(
        f"the file ends early (truncated at byte {size}: no MCAP footer and closing magic at its end)",
        path=path,
        fix=_RECOVER_FIX,
    )


def _find_mcap_end(f, size: int, max_candidates: int = 256) -> int | None:
    """Offset just past the last "footer record + magic" inside the file, or ``None``."""
    if size < 8 + _FOOTER_SIZE + 8:
        return None
    with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        end = size
        for _ in range(max_candidates):
            pos = data.rfind(MAGIC, 8 + _FOOTER_SIZE, end)
            if pos < 0:
                return None
            opcode, length = _RECORD_HEAD.unpack_from(data, pos - _FOOTER_SIZE)
            if opcode == Opcode.FOOTER and length == 20:
                return pos + 8
            end = pos + len(MAGIC) - 1
    return None


def _read_header(f, path: Path) -> Header:
    """The Header record that follows the magic."""
    head = _pread(f, 8, 9)
    if len(head) < 9 or head[0] != Opcode.HEADER:
        raise LogFormatError("the MCAP header record is missing after the magic bytes (at byte 8)", path=path, fix=_RECOVER_FIX)
    (length,) = struct.unpack_from("<Q", head, 1)
    body = f.read(min(length, 1 << 20))
    if len(body) != length:
        raise damaged("header", 8, f"it declares {length} bytes", path=path, fix=_RECOVER_FIX)
    return parse_record(Header, body, offset=8, path=path, fix=_RECOVER_FIX)


def _load_from_summary(f, container: Container, footer_offset: int, footer: Footer) -> None:
    path = container.path
    summary_start = footer.summary_start
    if not 8 < summary_start <= footer_offset:
        raise damaged(
            "footer", footer_offset, f"it points to a summary at byte {summary_start}, outside the file", path=path, fix=_RECOVER_FIX
        )
    summary = _pread(f, summary_start, footer_offset - summary_start)
    if footer.summary_crc != 0:
        footer_fields = struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, footer.summary_offset_start)
        if zlib.crc32(footer_fields, zlib.crc32(summary)) != footer.summary_crc:
            raise LogFormatError(f"the summary section at byte {summary_start} fails its CRC check", path=path, fix=_RECOVER_FIX)
    chunk_indexes: list[tuple[int, ChunkIndex]] = []
    metadata_indexes: list[tuple[int, MetadataIndex]] = []
    summary_records = iter_records(summary, base_offset=summary_start, path=path, section="the summary section")
    for opcode, offset, body in summary_records:
        if opcode == Opcode.SCHEMA:
            schema = parse_record(Schema, body, offset=offset, path=path, fix=_RECOVER_FIX)
            container.schemas[schema.id] = schema
        elif opcode == Opcode.CHANNEL:
            channel = parse_record(Channel, body, offset=offset, path=path, fix=_RECOVER_FIX)
            container.channels[channel.id] = channel
        elif opcode == Opcode.CHUNK_INDEX:
            chunk_indexes.append((offset, parse_record(ChunkIndex, body, offset=offset, path=path, fix=_RECOVER_FIX)))
        elif opcode == Opcode.METADATA_INDEX:
            metadata_indexes.append((offset, parse_record(MetadataIndex, body, offset=offset, path=path, fix=_RECOVER_FIX)))

    # The data section ends with a DataEnd record right before the summary.
    data_end = summary_start - _DATA_END_SIZE
    if data_end >= 8 and _pread(f, data_end, 1) == bytes([Opcode.DATA_END]):
        container.data_end_offset = data_end
    for index_offset, index in metadata_indexes:
        if not (8 <= index.offset and index.length >= 9 and index.offset + index.length <= summary_start):
            raise damaged(
                "metadata index", index_offset, f"it points to bytes {index.offset}..{index.offset + index.length}, "
                f"outside the data section", path=path, fix=_RECOVER_FIX,
            )
        raw = _pread(f, index.offset, index.length)
        opcode, length = _RECORD_HEAD.unpack_from(raw)
        if opcode != Opcode.METADATA or 9 + length != len(raw):
            raise damaged(
                "metadata index", index_offset,
                f"it points to byte {index.offset}, where a {record_kind(opcode)} record of {length} bytes lies, not its metadata",
                path=path, fix=_RECOVER_FIX,
            )
        record = parse_record(Metadata, raw[9:], offset=index.offset, path=path)
        container.metadata[record.name] = dict(record.metadata)

    if not chunk_indexes:  # an unchunked file: its messages are top-level records, found by a scan
        _linear_scan(f, container, footer_offset, recover=False)
        return
    tables: dict[int, list[np.ndarray]] = {}
    chunk_indexes.sort(key=lambda item: item[1].chunk_start_offset)
    for chunk_no, (index_offset, index) in enumerate(chunk_indexes):
        info = _check_chunk_index(f, index, index_offset, summary_start, path)
        container.chunks.append(info)
        where = f" of the chunk at byte {info.file_offset}"
        if index.message_index_offsets:
            mi_start = index.chunk_start_offset + index.chunk_length
            raw = _pread(f, mi_start, index.message_index_length)
            section = f"the message indexes{where}"
            for opcode, offset, body in iter_records(raw, base_offset=mi_start, path=path, section=section):
                if opcode == Opcode.MESSAGE_INDEX:
                    channel_id, table = _message_index_table(body, offset, chunk_no, index, container, path)
                    tables.setdefault(channel_id, []).append(table)
        else:  # no message index: scan this chunk's records once
            data = _read_chunk(f, info, path)
            for channel_id, table in _scan_chunk(data, chunk_no, info.file_offset, container, path).items():
                tables.setdefault(channel_id, []).append(table)
    container.entries = {cid: _file_order(np.concatenate(parts), path) for cid, parts in tables.items()}


def _check_chunk_index(f, index: ChunkIndex, index_offset: int, data_end: int, path: Path) -> ChunkInfo:
    """A :class:`ChunkInfo` from a chunk index whose offsets, lengths and target record check out."""
    start, length = index.chunk_start_offset, index.chunk_length
    mi_end = start + length + index.message_index_length
    if not (8 <= start and length >= 9 and mi_end <= data_end):
        raise damaged(
            "chunk index", index_offset, f"it points to bytes {start}..{mi_end}, outside the data section", path=path, fix=_RECOVER_FIX
        )
    head = _pread(f, start, 9)
    opcode, body_length = _RECORD_HEAD.unpack_from(head)
    if opcode != Opcode.CHUNK or body_length != length - 9:
        raise damaged(
            "chunk index", index_offset,
            f"it points to a chunk of {length - 9} bytes at byte {start}, where a {record_kind(opcode)} record of "
            f"{body_length} bytes lies", path=path, fix=_RECOVER_FIX,
        )
    if index.message_end_time > _MAX_LOG_TIME_NS or index.message_start_time > index.message_end_time:
        raise damaged(
            "chunk index", index_offset,
            f"its time range {index.message_start_time}..{index.message_end_time} ns is invalid", path=path, fix=_RECOVER_FIX,
        )
    return ChunkInfo(start, length - 9, index.message_start_time, index.message_end_time)


def _message_index_table(
    body: bytes, offset: int, chunk_no: int, index: ChunkIndex, container: Container, path: Path
) -> tuple[int, np.ndarray]:
    """A message-index record as ``(channel id, ENTRY_DTYPE table)``, checked against its chunk index.

    Message indexes carry no CRC: every entry must point inside the chunk, within the chunk's time
    range, on a channel the summary defines (the message itself is checked when it is read).
    """
    where = f" of the chunk at byte {index.chunk_start_offset}"

    def bad(reason: str) -> LogFormatError:
        return damaged("message index", offset, reason, path=path, where="", fix=_INDEX_FIX)

    if len(body) < 6:
        raise bad("it is shorter than its fields")
    channel_id, records_len = struct.unpack_from("<HI", body)
    if records_len % 16 or 6 + records_len > len(body):
        raise bad(f"its entries declare {records_len} bytes; the record holds {len(body) - 6}")
    if channel_id not in container.channels:
        raise bad(f"it refers to channel {channel_id}, which the summary does not define")
    pairs = np.frombuffer(body, dtype="<u8", count=records_len // 8, offset=6).reshape(-1, 2)
    times, offsets = pairs[:, 0], pairs[:, 1]
    outside = (times < index.message_start_time) | (times > index.message_end_time)
    if outside.any():
        k = int(np.argmax(outside))
        raise bad(
            f"entry {k} has log_time {int(times[k])} ns, outside the time range "
            f"{index.message_start_time}..{index.message_end_time} ns{where}"
        )
    past = offsets + 9 + _MESSAGE_HEADER.size > index.uncompressed_size
    if past.any():
        k = int(np.argmax(past))
        raise bad(f"entry {k} points to byte {int(offsets[k])}, past the end{where} ({index.uncompressed_size} bytes)")
    table = np.empty(len(pairs), dtype=ENTRY_DTYPE)
    table["log_time"] = times.astype(np.int64)
    table["chunk"] = chunk_no
    table["offset"] = offsets.astype(np.int64)
    table["channel"] = channel_id
    return channel_id, table


def _file_order(table: np.ndarray, path: Path) -> np.ndarray:
    """The table sorted by location; two entries pointing to the same message are a damaged index."""
    table = table[np.lexsort((table["offset"], table["chunk"]))]
    same = (table["chunk"][1:] == table["chunk"][:-1]) & (table["offset"][1:] == table["offset"][:-1])
    if same.any():
        k = int(np.argmax(same))
        raise LogFormatError(
            f"the message index lists the message at byte {int(table['offset'][k])} of chunk {int(table['chunk'][k])} twice",
            path=path,
            fix=_INDEX_FIX,
        )
    return table


def _scan_chunk(data: bytes, chunk_no: int, chunk_offset: int, container: Container, path: Path) -> dict[int, np.ndarray]:
    """Register the schemas/channels of a decompressed chunk and return its message tables."""
    rows: dict[int, list[tuple[int, int, int, int]]] = {}
    where = f" of the chunk at byte {chunk_offset}"
    section = f"the chunk at byte {chunk_offset}"
    for opcode, offset, body in iter_records(data, base_offset=0, path=path, section=section, where=where):
        if opcode == Opcode.MESSAGE:
            channel_id, log_time = _message_head(body, offset, path, where)
            rows.setdefault(channel_id, []).append((log_time, chunk_no, offset, channel_id))
        else:
            _register_definition(container, opcode, body, offset, path, where)
    return {cid: np.array(r, dtype=ENTRY_DTYPE) for cid, r in rows.items()}


def _message_head(body: bytes, offset: int, path: Path, where: str) -> tuple[int, int]:
    """``(channel_id, log_time)`` of a message record body (checked)."""
    if len(body) < _MESSAGE_HEADER.size:
        raise damaged("message", offset, "it is shorter than its header", path=path, where=where)
    channel_id, _seq, log_time, _pub = _MESSAGE_HEADER.unpack_from(body)
    if log_time > _MAX_LOG_TIME_NS:
        raise damaged("message", offset, f"its log_time {log_time} ns is past the year 2262", path=path, where=where)
    return channel_id, log_time


def _register_definition(container: Container, opcode: int, body: bytes, offset: int, path: Path, where: str = "") -> None:
    """Record a Schema or Channel record (the first definition of an id wins); ignore other opcodes."""
    if opcode == Opcode.SCHEMA:
        schema = parse_record(Schema, body, offset=offset, path=path, where=where)
        container.schemas.setdefault(schema.id, schema)
    elif opcode == Opcode.CHANNEL:
        channel = parse_record(Channel, body, offset=offset, path=path, where=where)
        container.channels.setdefault(channel.id, channel)


def _remaining_chunks(f, pos: int, size: int) -> Iterator[int]:
    """Yield the offsets of the complete chunk records from ``pos`` on (for counting what recover drops)."""
    while pos + 9 <= size:
        opcode, length = _RECORD_HEAD.unpack(_pread(f, pos, 9))
        if pos + 9 + length > size or opcode in (Opcode.DATA_END, Opcode.FOOTER):
            return
        if opcode == Opcode.CHUNK:
            yield pos
        pos += 9 + length


def _linear_scan(f, container: Container, end: int, *, recover: bool) -> None:
    """Index the file by reading its records in order, up to byte ``end`` (no summary, or ``--recover``).

    In recover mode, reading stops at the first record that is cut off or at the first chunk that
    is damaged (it and the chunks after it are counted in :attr:`Container.skipped_chunks`): the
    salvaged part is always a prefix of the recording, so frame indices keep their meaning.
    :attr:`Container.damage` says what stopped it.
    """
    path = container.path
    tables: dict[int, list[np.ndarray]] = {}
    top_level: dict[int, list[tuple[int, int, int, int]]] = {}
    pos = 8
    stop: str | None = None  # why reading stopped before a DataEnd/Footer record
    while True:
        head = _pread(f, pos, 9)
        if len(head) < 9 or pos + 9 > end:
            if recover or pos != end:  # without recover, ``end`` is the footer: reaching it is fine
                stop = f"the file ends at byte {container.file_size_bytes} without an MCAP footer (truncated)"
            break
        opcode, length = _RECORD_HEAD.unpack(head)
        if opcode in (Opcode.DATA_END, Opcode.FOOTER):
            if opcode == Opcode.DATA_END:
                container.data_end_offset = None if recover else pos
            break
        if pos + 9 + length > end:
            stop = (
                f"the {record_kind(opcode)} record at byte {pos} declares {length} bytes, past the end of the file "
                "(the file is truncated there, or that record's length is damaged)"
            )
            break
        if opcode == Opcode.CHUNK:
            body = f.read(length)
            try:
                data = decompress_chunk(body, pos, path)
                found = _scan_chunk(data, len(container.chunks), pos, container, path)
            except LogFormatError as exc:
                if not recover:
                    raise
                # Stop at the first damaged chunk: keeping later chunks would renumber the frames
                # after the gap and break the frame indices that loop candidates refer to.
                container.skipped_chunks = 1 + sum(1 for _ in _remaining_chunks(f, pos + 9 + length, end))
                container.damage = exc.message
                log.warning(
                    "%s: %s; keeping the %d chunks before it, dropping it and the %d chunks after it",
                    path, exc.message, len(container.chunks), container.skipped_chunks - 1,
                )
                break
            start_time, end_time = struct.unpack_from("<QQ", body)  # the chunk parsed: these are there
            for channel_id, table in found.items():
                tables.setdefault(channel_id, []).append(table)
            container.chunks.append(ChunkInfo(pos, length, start_time, end_time))
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA, Opcode.MESSAGE, Opcode.HEADER):
            body = f.read(length)
            try:
                if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                    _register_definition(container, opcode, body, pos, path)
                elif opcode == Opcode.METADATA:
                    record = parse_record(Metadata, body, offset=pos, path=path)
                    container.metadata[record.name] = dict(record.metadata)
                elif opcode == Opcode.HEADER:
                    container.library = parse_record(Header, body, offset=pos, path=path).library
                else:
                    channel_id, log_time = _message_head(body, pos, path, "")
                    top_level.setdefault(channel_id, []).append((log_time, -1, pos, channel_id))
            except LogFormatError as exc:
                if not recover:
                    raise
                container.damage = container.damage or exc.message
                log.warning("%s: skipping it: %s", path, exc.message)
        pos += 9 + length
    for channel_id, rows in top_level.items():
        tables.setdefault(channel_id, []).append(np.array(rows, dtype=ENTRY_DTYPE))
    container.entries = {cid: _file_order(np.concatenate(parts), path) for cid, parts in tables.items()}
    if recover:
        container.recovered_messages = int(sum(len(t) for t in container.entries.values()))
        if stop is not None:
            container.damage = container.damage or stop
            log.warning(
                "%s: %s; recovered %d messages from %d complete chunks",
                path, stop, container.recovered_messages, len(container.chunks),
            )
    elif stop is not None:
        raise LogFormatError(f"the data section is cut off: {stop}", path=path, fix=_RECOVER_FIX)
