"""describe_frames: batching, corrupt images, the on-disk cache (hit, partial, corrupt, stale)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lcv_replay.log.images import decode_compressed, encode_compressed
from lcv_replay.records import Frame, ImageRef
from lcv_replay.retrieval.cache import (
    DescribeStats,
    cache_path_for,
    default_cache_dir,
    describe_frames,
    log_cache_key,
)
from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.retrieval.descriptors import make_backend


class CountingBackend:
    """The real thumbnail backend, counting the images it is asked to describe."""

    def __init__(self):
        self.inner = make_backend("thumbnail", RetrievalConfig())
        self.name, self.dim, self.input_size_px = self.inner.name, self.inner.dim, self.inner.input_size_px
        self.signature = self.inner.signature
        self.images = 0
        self.calls = 0

    def describe(self, images):
        self.images += len(images)
        self.calls += 1
        return self.inner.describe(images)


def _png(seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    return encode_compressed(rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8), "png")


def _frames(n: int, *, corrupt: tuple[int, ...] = (), missing: tuple[int, ...] = ()) -> list[Frame]:
    frames = []
    for i in range(n):
        data = _png(i)
        if i in corrupt:
            data = data[: len(data) // 3]  # a truncated PNG message
        left = None if i in missing else ImageRef(i, "png", lambda data=data: decode_compressed(data, "png"))
        frames.append(Frame(index=i, stamp_ns=i, left=left))
    return frames


def test_descriptors_come_in_order_in_batches_and_equal_direct_calls(tmp_path):
    backend = CountingBackend()
    rows = list(describe_frames(_frames(11), backend, cache_key=None, batch_size=4))
    assert [f.index for f, _ in rows] == list(range(11))
    assert backend.calls == 3 and backend.images == 11
    direct = backend.inner.describe([decode_compressed(_png(i), "png") for i in range(11)])
    assert np.allclose(np.stack([d for _, d in rows]), direct)


def test_corrupt_and_missing_images_are_skipped_counted_and_named(caplog):
    backend = CountingBackend()
    stats = DescribeStats()
    with caplog.at_level(logging.WARNING):
        rows = list(describe_frames(_frames(8, corrupt=(2, 5), missing=(6,)), backend, cache_key=None, batch_size=3, stats=stats))
    assert [f.index for f, _ in rows] == list(range(8))
    assert [f.index for f, d in rows if d is None] == [2, 5, 6]
    assert stats.corrupt == 2 and stats.corrupt_frames == [2, 5] and stats.missing == 1 and stats.described == 5
    warnings = [r.getMessage() for r in caplog.records]
    assert any("frame 2" in w for w in warnings) and any("frame 5" in w for w in warnings)


def test_second_run_uses_the_cache_and_does_not_describe(tmp_path):
    backend = CountingBackend()
    first = [d for _, d in describe_frames(_frames(10, corrupt=(4,)), backend, cache_key="log-a", cache_dir=tmp_path)]
    assert backend.images == 9
    stats = DescribeStats()
    again = CountingBackend()
    second = [d for _, d in describe_frames(_frames(10, corrupt=(4,)), again, cache_key="log-a", cache_dir=tmp_path, stats=stats)]
    assert again.images == 0 and stats.cached == 9 and stats.corrupt == 1
    assert all((a is None and b is None) or np.array_equal(a, b) for a, b in zip(first, second))
    assert stats.cache_path == cache_path_for("log-a", again, tmp_path) and stats.cache_path.exists()
    # another log key or other backend settings do not hit
    other = CountingBackend()
    list(describe_frames(_frames(10), other, cache_key="log-b", cache_dir=tmp_path))
    assert other.images == 10
    small = CountingBackend()
    small.signature = "32x16,patch=8"
    assert cache_path_for("log-a", small, tmp_path) != cache_path_for("log-a", again, tmp_path)


def test_an_interrupted_run_keeps_what_was_described(tmp_path):
    backend = CountingBackend()
    gen = describe_frames(_frames(20), backend, cache_key="log", cache_dir=tmp_path, batch_size=4)
    for frame, _ in gen:
        if frame.index == 9:
            break
    gen.close()  # what a replay's Ctrl-C does to the generator
    assert cache_path_for("log", backend, tmp_path).exists()
    rest = CountingBackend()
    stats = DescribeStats()
    rows = list(describe_frames(_frames(20), rest, cache_key="log", cache_dir=tmp_path, batch_size=4, stats=stats))
    assert len(rows) == 20 and all(d is not None for _, d in rows)
    assert stats.cached == backend.images and rest.images == 20 - backend.images


@pytest.mark.parametrize("damage", ["garbage", "truncate", "flip-descriptor"])
def test_a_corrupt_cache_is_detected_and_rebuilt(tmp_path, caplog, damage):
    backend = CountingBackend()
    reference = [d for _, d in describe_frames(_frames(6), backend, cache_key="log", cache_dir=tmp_path)]
    path = cache_path_for("log", backend, tmp_path)
    data = bytearray(path.read_bytes())
    if damage == "garbage":
        data = bytearray(b"not a cache at all")
    elif damage == "truncate":
        data = data[: len(data) // 2]
    else:  # change one float inside the descriptors array: only the checksum can tell
        import io

        with np.load(io.BytesIO(bytes(data))) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["descriptors"][2, 5] += 0.25
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        data = bytearray(buffer.getvalue())
    path.write_bytes(bytes(data))
    again = CountingBackend()
    stats = DescribeStats()
    with caplog.at_level(logging.WARNING):
        rebuilt = [d for _, d in describe_frames(_frames(6), again, cache_key="log", cache_dir=tmp_path, stats=stats)]
    assert again.images == 6 and stats.cache_rebuilt
    assert any("rebuilding" in r.getMessage() for r in caplog.records)
    assert all(np.array_equal(a, b) for a, b in zip(reference, rebuilt))
    third = CountingBackend()
    list(describe_frames(_frames(6), third, cache_key="log", cache_dir=tmp_path))
    assert third.images == 0  # the rebuilt cache is good


def test_log_cache_key_follows_the_bytes(tmp_path):
    a = tmp_path / "a.mcap"
    a.write_bytes(b"x" * 3_000_000)
    key = log_cache_key(a)
    assert key.startswith("b2-") and key == log_cache_key(a)
    a.write_bytes(b"x" * 2_999_999 + b"y")
    assert log_cache_key(a) != key
    from lcv_replay.errors import RetrievalError

    with pytest.raises(RetrievalError, match="cannot read the log"):
        log_cache_key(tmp_path / "missing.mcap")


def test_default_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("LCV_CACHE_DIR", str(tmp_path / "c"))
    assert default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("LCV_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert default_cache_dir() == tmp_path / "x" / "lcv-replay" / "descriptors"


def test_no_frames_yield_nothing_and_write_no_cache(tmp_path):
    backend = CountingBackend()
    assert list(describe_frames([], backend, cache_key="empty", cache_dir=tmp_path)) == []
    assert backend.calls == 0 and not any(tmp_path.iterdir())
