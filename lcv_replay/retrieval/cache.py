"""Descriptor cache: re-running a replay on the same log does not recompute the CNN.

Descriptors are cached per ``(log identity, backend, input size, backend settings)`` in one ``.npz``
file in the cache folder:

* the folder is ``$LCV_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/lcv-replay/descriptors``
  (``~/.cache/lcv-replay/descriptors``), or the ``retrieval.cache_dir`` config value;
* the log identity is :func:`log_cache_key`: a BLAKE2b digest of the log file's bytes (any change
  to the file, images included, gives a new key);
* a file holds ``frames`` (N,), ``descriptors`` (N, D) float32, the frames whose image could not be
  decoded, and a JSON header with a checksum of the arrays. A file that cannot be read, whose header
  does not match, or whose checksum fails is reported with a warning and rebuilt;
* it is written atomically (temp file, then rename) when the iteration ends, also when the consumer
  stops early (Ctrl-C in a replay): the frames described so far are kept and the next run
  describes only the rest.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from lcv_replay.errors import RetrievalError
from lcv_replay.fileio import atomic_output, user_cache_dir
from lcv_replay.records import Frame
from lcv_replay.retrieval.descriptors import DescriptorBackend

log = logging.getLogger(__name__)

CACHE_FORMAT = 1
_DIGEST_CHUNK = 1 << 20


@dataclass
class DescribeStats:
    """Counters filled in by :func:`describe_frames` as it runs.

    Attributes:
        described: frames whose descriptor was computed in this run.
        cached: frames whose descriptor came from the cache.
        corrupt: frames whose image could not be decoded (skipped, ``None`` yielded).
        missing: frames without a left image (``None`` yielded).
        corrupt_frames: the indices of the corrupt frames.
        cache_path: the cache file used, if any.
        cache_rebuilt: the cache file existed but was unusable and was rebuilt.
    """

    described: int = 0
    cached: int = 0
    corrupt: int = 0
    missing: int = 0
    corrupt_frames: list[int] = field(default_factory=list)
    cache_path: Path | None = None
    cache_rebuilt: bool = False


def default_cache_dir() -> Path:
    """``$LCV_CACHE_DIR``, else ``$XDG_CACHE_HOME/lcv-replay/descriptors`` (``~/.cache/...``)."""
    if os.environ.get("LCV_CACHE_DIR"):
        return Path(os.environ["LCV_CACHE_DIR"])
    return user_cache_dir("descriptors")


def log_cache_key(path: Path) -> str:
    """Identity of a log file: ``"b2-"`` + 32 hex digits of the BLAKE2b digest of its bytes."""
    path = Path(path)
    try:
        digest = hashlib.blake2b(digest_size=16)
        with path.open("rb") as f:
            while chunk := f.read(_DIGEST_CHUNK):
                digest.update(chunk)
    except OSError as exc:
        raise RetrievalError(f"cannot read the log to key its descriptor cache: {exc.strerror}", path=path) from None
    return "b2-" + digest.hexdigest()


def backend_signature(backend: DescriptorBackend) -> str:
    """Everything about a backend that changes its vectors: name, input size, dim, settings."""
    extra = getattr(backend, "signature", "")
    return f"{backend.name}|{backend.input_size_px}px|{backend.dim}d|{extra}"


def cache_path_for(cache_key: str, backend: DescriptorBackend, cache_dir: Path | None = None) -> Path:
    """The cache file of ``cache_key`` for ``backend`` in ``cache_dir`` (default folder if None)."""
    folder = Path(cache_dir) if cache_dir else default_cache_dir()
    signature = hashlib.blake2b(backend_signature(backend).encode(), digest_size=4).hexdigest()
    safe_key = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in cache_key)[:80]
    return folder / f"{safe_key}.{backend.name}.{backend.input_size_px}px.{signature}.npz"


@dataclass(frozen=True)
class CachedDescriptors:
    """The contents of a cache file: descriptors by frame and the frames known to be corrupt."""

    descriptors: dict[int, np.ndarray]
    corrupt_frames: frozenset[int]


def _checksum(frames: np.ndarray, descriptors: np.ndarray, corrupt: np.ndarray) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in (frames, descriptors, corrupt):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def load_cache(path: Path, *, cache_key: str, backend: DescriptorBackend) -> CachedDescriptors | None:
    """Read a cache file; ``None`` (with a warning) when it is unusable, ``None`` silently if absent."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"]))
            frames = np.asarray(data["frames"], dtype=np.int64)
            descriptors = np.asarray(data["descriptors"], dtype=np.float32)
            corrupt = np.asarray(data["corrupt_frames"], dtype=np.int64)
    except Exception as exc:  # zip, npy or JSON damage: all mean "rebuild"
        log.warning("descriptor cache %s is unreadable (%s); rebuilding it", path, exc)
        return None
    expected = {"format": CACHE_FORMAT, "cache_key": cache_key, "backend": backend_signature(backend)}
    problems = [k for k, v in expected.items() if header.get(k) != v]
    if not problems and (descriptors.ndim != 2 or descriptors.shape != (frames.shape[0], backend.dim)):
        problems.append("shape")
    if not problems and header.get("checksum") != _checksum(frames, descriptors, corrupt):
        problems.append("checksum")
    if problems:
        log.warning("descriptor cache %s does not match (%s); rebuilding it", path, ", ".join(problems))
        return None
    return CachedDescriptors({int(f): d for f, d in zip(frames, descriptors)}, frozenset(int(c) for c in corrupt))


def save_cache(path: Path, *, cache_key: str, backend: DescriptorBackend, descriptors: dict[int, np.ndarray], corrupt_frames: Iterable[int]) -> None:
    """Write a cache file atomically (creating its folder)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    order = sorted(descriptors)
    frames = np.array(order, dtype=np.int64)
    matrix = np.stack([descriptors[f] for f in order]).astype(np.float32) if order else np.zeros((0, backend.dim), np.float32)
    corrupt = np.array(sorted(set(corrupt_frames)), dtype=np.int64)
    header = {
        "format": CACHE_FORMAT,
        "cache_key": cache_key,
        "backend": backend_signature(backend),
        "checksum": _checksum(frames, matrix, corrupt),
    }
    with atomic_output(path, force=True) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, header=np.array(json.dumps(header)), frames=frames, descriptors=matrix, corrupt_frames=corrupt)


def describe_frames(
    frames: Iterable[Frame],
    backend: DescriptorBackend,
    *,
    cache_key: str | None,
    cache_dir: Path | None = None,
    batch_size: int = 8,
    stats: DescribeStats | None = None,
) -> Iterator[tuple[Frame, np.ndarray | None]]:
    """Yield ``(frame, descriptor)`` in input order, describing left images in batches.

    Args:
        frames: the log's frames (their ``left`` images are decoded here).
        backend: the descriptor backend.
        cache_key: the log's identity (:func:`log_cache_key`), or ``None`` for no caching.
        cache_dir: the cache folder (default :func:`default_cache_dir`).
        batch_size: images per network call.
        stats: optional counters, updated as frames are yielded.

    Yields:
        ``(frame, (D,) float32 descriptor)``, or ``(frame, None)`` for a frame whose left image is
        absent or cannot be decoded (logged with the frame index and counted in ``stats``).
    """
    stats = stats if stats is not None else DescribeStats()
    path = cache_path_for(cache_key, backend, cache_dir) if cache_key else None
    stats.cache_path = path
    known: dict[int, np.ndarray] = {}
    known_corrupt: set[int] = set()
    if path is not None:
        cached = load_cache(path, cache_key=cache_key, backend=backend)
        if cached is None and path.exists():
            stats.cache_rebuilt = True
        if cached is not None:
            known = dict(cached.descriptors)
            known_corrupt = set(cached.corrupt_frames)
    new_entries = 0
    pending: list[tuple[Frame, np.ndarray | None, np.ndarray | None]] = []  # frame, image, known descriptor

    def flush() -> Iterator[tuple[Frame, np.ndarray | None]]:
        nonlocal new_entries
        todo = [i for i, (_, image, _) in enumerate(pending) if image is not None]
        vectors = backend.describe([pending[i][1] for i in todo]) if todo else None
        computed = {i: np.asarray(vectors[k], dtype=np.float32) for k, i in enumerate(todo)} if todo else {}
        for i, descriptor in computed.items():  # cached before yielding: an early stop keeps the batch
            known[pending[i][0].index] = descriptor
        new_entries += len(computed)
        stats.described += len(computed)
        batch = [(frame, computed.get(i, descriptor)) for i, (frame, _, descriptor) in enumerate(pending)]
        pending.clear()
        yield from batch

    try:
        for frame in frames:
            if frame.index in known:
                stats.cached += 1
                if pending:
                    pending.append((frame, None, known[frame.index]))
                else:
                    yield frame, known[frame.index]
                continue
            image = _decode_left(frame, stats, known_corrupt)
            if image is None and frame.left is not None and frame.index not in known_corrupt:
                known_corrupt.add(frame.index)
                new_entries += 1
            pending.append((frame, image, None))
            if sum(1 for _, im, _ in pending if im is not None) >= batch_size:
                yield from flush()
        if pending:
            yield from flush()
    finally:
        if path is not None and new_entries:
            try:
                save_cache(path, cache_key=cache_key, backend=backend, descriptors=known, corrupt_frames=known_corrupt)
                log.info("descriptor cache: %d frames written to %s", len(known), path)
            except OSError as exc:
                log.warning("cannot write the descriptor cache %s: %s (descriptors will be recomputed next time)", path, exc)


def _decode_left(frame: Frame, stats: DescribeStats, known_corrupt: set[int]) -> np.ndarray | None:
    if frame.left is None:
        stats.missing += 1
        return None
    try:
        image = frame.left.decode()
        image = np.asarray(image)
        if image.ndim not in (2, 3) or image.size == 0 or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
            raise ValueError(f"decoded to an array of shape {image.shape}")
    except Exception as exc:  # any decoder failure (codec, protobuf, size) means "corrupt image"
        stats.corrupt += 1
        stats.corrupt_frames.append(frame.index)
        if frame.index not in known_corrupt:
            log.warning("frame %d: left image (%s) cannot be decoded, skipped: %s", frame.index, frame.left.encoding, exc)
        else:
            log.debug("frame %d: left image known to be corrupt, skipped", frame.index)
        return None
    return image
