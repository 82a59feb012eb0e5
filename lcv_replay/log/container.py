"""Low-level MCAP container access for the reader: index, chunk cache, recovery.

This module knows MCAP records but nothing about lcv-replay topics. :func:`load_container` builds a
:class:`Container`: schemas, channels, metadata, the list of chunks and, per channel, a table of
every message's ``log_time`` and location, in file order. It is built from the summary section and
the message-index records that follow each chunk, so opening a log decodes no chunk. Without a
summary (or with ``recover=True``) it falls back to one linear scan over the records.

Chunks are decompressed (and their CRC checked) only when a message in them is read;
:attr:`Container.chunks_decoded` counts that, so tests can prove that time-window reads skip
chunks.
"""

from __future__ import annotations

import io
import logging
import struct
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, ChunkIndex, Metadata, MetadataIndex, Schema, Statistics

from lcv_replay.errors import LogFormatError

log = logging.getLogger(__name__)

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
_OP_CHUNK, _OP_MESSAGE_INDEX, _OP_CHUNK_INDEX = 0x06, 0x07, 0x08
_OP_STATISTICS, _OP_METADATA, _OP_METADATA_INDEX, _OP_DATA_END = 0x0B, 0x0C, 0x0D, 0x0F
_FOOTER_SIZE = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc
_MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time
_RECOVER_FIX = "re-run with --recover to salvage the complete chunks"

# Entries of the per-channel message tables: log_time, chunk number (-1: a message record outside
# any chunk, located in the file itself) and byte offset (in the decompressed chunk, or the file).
ENTRY_DTYPE = np.dtype([("log_time", "<i8"), ("chunk", "<i4"), ("offset", "<i8")])


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
            data = _decompress_chunk(f, self.chunks[chunk_no], self.path)
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
                opcode, length = struct.unpack("<BQ", head)
                body = f.read(length)
            return _parse_message(opcode, body, self.path, offset)
        data = self.chunk_data(chunk_no)
        if offset + 9 > len(data):
            raise LogFormatError(f"message index points past the end of chunk {chunk_no}", path=self.path, fix=_RECOVER_FIX)
        opcode, length = struct.unpack_from("<BQ", data, offset)
        return _parse_message(opcode, data[offset + 9 : offset + 9 + length], self.path, offset)

    def verify_chunks(self) -> None:
        """Decompress every chunk once and check its CRC (raises :class:`LogFormatError`)."""
        with open(self.path, "rb") as f:
            for chunk in self.chunks:
                _decompress_chunk(f, chunk, self.path)

    def topic_channels(self, topic: str) -> list[int]:
        """Channel ids on ``topic`` (usually zero or one)."""
        return [cid for cid, ch in self.channels.items() if ch.topic == topic]


def _parse_message(opcode: int, body: bytes, path: Path, offset: int) -> RawMessage:
    if opcode != _OP_MESSAGE or len(body) < _MESSAGE_HEADER.size:
        raise LogFormatError(
            f"expected a message record at offset {offset}, found opcode 0x{opcode:02x}",
            path=path,
            fix="the message index is damaged; " + _RECOVER_FIX,
        )
    channel_id, sequence, log_time, publish_time = _MESSAGE_HEADER.unpack_from(body)
    return RawMessage(channel_id, sequence, log_time, publish_time, body[_MESSAGE_HEADER.size :])


def _decompress_chunk(f: io.BufferedReader, chunk: ChunkInfo, path: Path) -> bytes:
    f.seek(chunk.file_offset + 9)
    body = f.read(chunk.record_length)
    if len(body) != chunk.record_length:
        raise LogFormatError(f"the chunk at byte {chunk.file_offset} is cut off (truncated file)", path=path, fix=_RECOVER_FIX)
    return _decompress_chunk_body(body, chunk.file_offset, path)


def _decompress_chunk_body(body: bytes, file_offset: int, path: Path) -> bytes:
    """Decompress a chunk record body and check its CRC; :class:`LogFormatError` when damaged."""
    try:
        _start, _end, uncompressed_size, crc, comp_len = struct.unpack_from("<QQQII", body)
        compression = body[32 : 32 + comp_len].decode()
        (data_len,) = struct.unpack_from("<Q", body, 32 + comp_len)
        payload = body[40 + comp_len : 40 + comp_len + data_len]
        if len(payload) != data_len:
            raise ValueError("chunk data is shorter than its declared length")
        if compression == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompress(payload, max_output_size=uncompressed_size)
        elif compression == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(payload)
        elif compression == "":
            data = payload
        else:
            raise LogFormatError(
                f"chunk at byte {file_offset} uses unsupported compression {compression!r}",
                path=path,
                fix="re-encode the file with zstd, lz4 or no compression (mcap convert)",
            )
    except LogFormatError:
        raise
    except Exception as exc:  # zstd/lz4 errors, struct errors, bad utf-8
        raise LogFormatError(
            f"the chunk at byte {file_offset} cannot be decompressed ({exc})",
            path=path,
            fix="the file is corrupted; re-copy it, or " + _RECOVER_FIX,
        ) from None
    if len(data) != uncompressed_size:
        raise LogFormatError(
            f"the chunk at byte {file_offset} decompresses to {len(data)} bytes, expected {uncompressed_size}",
            path=path,
            fix="the file is corrupted; re-copy it, or " + _RECOVER_FIX,
        )
    if crc != 0 and zlib.crc32(data) != crc:
        raise LogFormatError(
            f"the chunk at byte {file_offset} fails its CRC check (stored 0x{crc:08x}, computed 0x{zlib.crc32(data):08x})",
            path=path,
            fix="the file is corrupted; re-copy it, or " + _RECOVER_FIX + " that pass",
        )
    return data


def _read_record(cls, body: bytes):
    return cls.read(ReadDataStream(io.BytesIO(body)))


def load_container(path: str | Path, *, recover: bool = False) -> Container:
    """Index an MCAP file without decoding its chunks (see the module docstring).

    Raises:
        LogFormatError: not a file, not an MCAP, truncated (unless ``recover``), damaged summary.
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
        footer = _read_footer(f, size)
        if recover:
            _linear_scan(f, container, size, recover=True)
            return container
        if footer is None:
            raise LogFormatError(
                f"the file ends early (truncated: no MCAP footer in its last {_FOOTER_SIZE + 8} bytes)",
                path=path,
                fix=_RECOVER_FIX,
            )
        summary_start, summary_offset_start, summary_crc = footer
        container.library = _read_library(f, path)
        if summary_start == 0:
            _linear_scan(f, container, size, recover=False)
        else:
            _load_from_summary(f, container, size, summary_start, summary_offset_start, summary_crc)
    return container


def _read_footer(f, size: int) -> tuple[int, int, int] | None:
    if size < 8 + _FOOTER_SIZE + 8:
        return None
    f.seek(size - 8 - _FOOTER_SIZE)
    tail = f.read(_FOOTER_SIZE + 8)
    if tail[-8:] != MAGIC:
        return None
    opcode, length, summary_start, summary_offset_start, summary_crc = struct.unpack_from("<BQQQI", tail)
    if opcode != _OP_FOOTER or length != 20:
        return None
    return summary_start, summary_offset_start, summary_crc


def _iter_records(buf: bytes, start: int, base_offset: int, path: Path):
    """Yield ``(opcode, absolute offset, body)`` for consecutive records of ``buf[start:]``."""
    pos = start
    while pos < len(buf):
        if pos + 9 > len(buf):
            raise LogFormatError(f"a record at byte {base_offset + pos} is cut off", path=path, fix=_RECOVER_FIX)
        opcode, length = struct.unpack_from("<BQ", buf, pos)
        end = pos + 9 + length
        if end > len(buf):
            raise LogFormatError(f"a record at byte {base_offset + pos} is cut off", path=path, fix=_RECOVER_FIX)
        yield opcode, base_offset + pos, buf[pos + 9 : end]
        pos = end


def _read_library(f, path: Path) -> str:
    """The ``library`` string of the Header record that follows the magic."""
    f.seek(8)
    head = f.read(9)
    if len(head) < 9 or head[0] != _OP_HEADER:
        raise LogFormatError("the MCAP header record is missing after the magic bytes", path=path, fix=_RECOVER_FIX)
    return _header_library(f.read(struct.unpack_from("<Q", head, 1)[0]))


def _header_library(body: bytes) -> str:
    profile_len = struct.unpack_from("<I", body)[0]
    return body[4 + profile_len + 4 :].decode(errors="replace")


def _load_from_summary(
    f, container: Container, size: int, summary_start: int, summary_offset_start: int, summary_crc: int
) -> None:
    path = container.path
    footer_offset = size - 8 - _FOOTER_SIZE
    if not 8 <= summary_start <= footer_offset:
        raise LogFormatError(f"the footer points to a summary at byte {summary_start}, outside the file", path=path, fix=_RECOVER_FIX)
    f.seek(summary_start)
    summary = f.read(footer_offset - summary_start)
    if summary_crc != 0:
        footer_fields = struct.pack("<BQQQ", _OP_FOOTER, 20, summary_start, summary_offset_start)
        if zlib.crc32(footer_fields, zlib.crc32(summary)) != summary_crc:
            raise LogFormatError("the summary section fails its CRC check", path=path, fix=_RECOVER_FIX)
    chunk_indexes: list[ChunkIndex] = []
    metadata_indexes: list[MetadataIndex] = []
    try:
        for opcode, _offset, body in _iter_records(summary, 0, summary_start, path):
            if opcode == _OP_SCHEMA:
                schema = _read_record(Schema, body)
                container.schemas[schema.id] = schema
            elif opcode == _OP_CHANNEL:
                channel = _read_record(Channel, body)
                container.channels[channel.id] = channel
            elif opcode == _OP_CHUNK_INDEX:
                chunk_indexes.append(_read_record(ChunkIndex, body))
            elif opcode == _OP_METADATA_INDEX:
                metadata_indexes.append(_read_record(MetadataIndex, body))
            elif opcode == _OP_STATISTICS:
                _read_record(Statistics, body)
    except LogFormatError:
        raise
    except Exception as exc:
        raise LogFormatError(f"the summary section is damaged ({exc})", path=path, fix=_RECOVER_FIX) from None

    for index in metadata_indexes:
        f.seek(index.offset)
        raw = f.read(index.length)
        if len(raw) < 9 or raw[0] != _OP_METADATA:
            raise LogFormatError(f"the metadata index points to a non-metadata record at byte {index.offset}", path=path, fix=_RECOVER_FIX)
        record = _read_record(Metadata, raw[9:])
        container.metadata[record.name] = dict(record.metadata)

    if not chunk_indexes:  # an unchunked file: its messages are top-level records, found by a scan
        _linear_scan(f, container, size, recover=False)
        return
    tables: dict[int, list[np.ndarray]] = {}
    chunk_indexes.sort(key=lambda c: c.chunk_start_offset)
    for chunk_no, index in enumerate(chunk_indexes):
        if index.chunk_start_offset + index.chunk_length > footer_offset:
            raise LogFormatError(f"a chunk index points past the data section (byte {index.chunk_start_offset})", path=path, fix=_RECOVER_FIX)
        info = ChunkInfo(index.chunk_start_offset, index.chunk_length - 9, index.message_start_time, index.message_end_time)
        container.chunks.append(info)
        if index.message_index_offsets:
            mi_start = index.chunk_start_offset + index.chunk_length
            f.seek(mi_start)
            raw = f.read(index.message_index_length)
            for opcode, _off, body in _iter_records(raw, 0, mi_start, path):
                if opcode != _OP_MESSAGE_INDEX:
                    continue
                (channel_id, records_len) = struct.unpack_from("<HI", body)
                pairs = np.frombuffer(body, dtype="<u8", count=records_len // 8, offset=6).reshape(-1, 2)
                table = np.empty(len(pairs), dtype=ENTRY_DTYPE)
                table["log_time"] = pairs[:, 0].astype(np.int64)
                table["chunk"] = chunk_no
                table["offset"] = pairs[:, 1].astype(np.int64)
                tables.setdefault(channel_id, []).append(table)
        else:  # no message index: scan this chunk's records once
            data = _decompress_chunk(f, info, path)
            for channel_id, table in _scan_chunk(data, chunk_no, container, path).items():
                tables.setdefault(channel_id, []).append(table)
    container.entries = {cid: _file_order(np.concatenate(parts)) for cid, parts in tables.items()}


def _file_order(table: np.ndarray) -> np.ndarray:
    return table[np.lexsort((table["offset"], table["chunk"]))]


def _scan_chunk(data: bytes, chunk_no: int, container: Container, path: Path) -> dict[int, np.ndarray]:
    """Register the schemas/channels of a decompressed chunk and return its message tables."""
    rows: dict[int, list[tuple[int, int, int]]] = {}
    for opcode, offset, body in _iter_records(data, 0, 0, path):
        if opcode == _OP_MESSAGE:
            channel_id, _seq, log_time, _pub = _MESSAGE_HEADER.unpack_from(body)
            rows.setdefault(channel_id, []).append((log_time, chunk_no, offset))
        else:
            _register_definition(container, opcode, body)
    return {cid: np.array(r, dtype=ENTRY_DTYPE) for cid, r in rows.items()}


def _register_definition(container: Container, opcode: int, body: bytes) -> None:
    """Record a Schema or Channel record (the first definition of an id wins); ignore other opcodes."""
    if opcode == _OP_SCHEMA:
        schema = _read_record(Schema, body)
        container.schemas.setdefault(schema.id, schema)
    elif opcode == _OP_CHANNEL:
        channel = _read_record(Channel, body)
        container.channels.setdefault(channel.id, channel)


def _remaining_chunks(f, pos: int, size: int):
    """Yield the offsets of the complete chunk records from ``pos`` on (for counting what recover drops)."""
    while pos + 9 <= size:
        f.seek(pos)
        opcode, length = struct.unpack("<BQ", f.read(9))
        if pos + 9 + length > size or opcode in (_OP_DATA_END, _OP_FOOTER):
            return
        if opcode == _OP_CHUNK:
            yield pos
        pos += 9 + length


def _linear_scan(f, container: Container, size: int, *, recover: bool) -> None:
    """Index the file by reading its records in order (no summary, or ``--recover``).

    In recover mode, reading stops at the first record that is cut off or at the first chunk that
    fails to decompress or fails its CRC (it and the chunks after it are counted in
    :attr:`Container.skipped_chunks`): the salvaged part is always a prefix of the recording, so
    frame indices keep their meaning.
    """
    path = container.path
    tables: dict[int, list[np.ndarray]] = {}
    top_level: dict[int, list[tuple[int, int, int]]] = {}
    pos = 8
    truncated_at: int | None = None
    f.seek(pos)
    while True:
        head = f.read(9)
        if len(head) == 0 and pos == size:
            truncated_at = pos
            break
        if len(head) < 9:
            truncated_at = pos
            break
        opcode, length = struct.unpack("<BQ", head)
        if pos + 9 + length > size:
            truncated_at = pos
            break
        if opcode == _OP_CHUNK:
            info_body = f.read(length)
            start_time, end_time = struct.unpack_from("<QQ", info_body)
            info = ChunkInfo(pos, length, start_time, end_time)
            try:
                data = _decompress_chunk_body(info_body, pos, path)
                found = _scan_chunk(data, len(container.chunks), container, path)
            except LogFormatError as exc:
                if not recover:
                    raise
                # Stop at the first damaged chunk: keeping later chunks would renumber the frames
                # after the gap and break the frame indices that loop candidates refer to.
                container.skipped_chunks = 1 + sum(1 for _ in _remaining_chunks(f, pos + 9 + length, size))
                log.warning(
                    "%s: %s; keeping the %d chunks before it, dropping it and the %d chunks after it",
                    path, exc.message, len(container.chunks), container.skipped_chunks - 1,
                )
                truncated_at = None
                break
            else:
                for channel_id, table in found.items():
                    tables.setdefault(channel_id, []).append(table)
                container.chunks.append(info)
        elif opcode in (_OP_SCHEMA, _OP_CHANNEL, _OP_METADATA, _OP_MESSAGE, _OP_HEADER):
            body = f.read(length)
            try:
                if opcode in (_OP_SCHEMA, _OP_CHANNEL):
                    _register_definition(container, opcode, body)
                elif opcode == _OP_METADATA:
                    record = _read_record(Metadata, body)
                    container.metadata[record.name] = dict(record.metadata)
                elif opcode == _OP_HEADER:
                    container.library = _header_library(body)
                else:
                    channel_id, _seq, log_time, _pub = _MESSAGE_HEADER.unpack_from(body)
                    top_level.setdefault(channel_id, []).append((log_time, -1, pos))
            except Exception as exc:
                if not recover:
                    raise LogFormatError(f"a record at byte {pos} is damaged ({exc})", path=path, fix=_RECOVER_FIX) from None
                log.warning("%s: skipping a damaged record at byte %d", path, pos)
        elif opcode in (_OP_DATA_END, _OP_FOOTER):
            break
        else:
            f.seek(length, io.SEEK_CUR)
        pos += 9 + length
    for channel_id, rows in top_level.items():
        tables.setdefault(channel_id, []).append(np.array(rows, dtype=ENTRY_DTYPE))
    container.entries = {cid: _file_order(np.concatenate(parts)) for cid, parts in tables.items()}
    if recover:
        container.recovered_messages = int(sum(len(t) for t in container.entries.values()))
        if truncated_at is not None:
            log.warning(
                "%s: the file is truncated at byte %d of %d; recovered %d messages from %d complete chunks",
                path, truncated_at, size, container.recovered_messages, len(container.chunks),
            )
    elif truncated_at is not None:
        raise LogFormatError(f"the data section is cut off at byte {truncated_at}", path=path, fix=_RECOVER_FIX)
