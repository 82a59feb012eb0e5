"""Log I/O benchmark: write and read throughput and file size of 640x480 RGB stereo PNG logs.

``lcv-replay bench log`` runs :func:`run_log_benchmark`, prints a table and writes JSON. Images are
the real RTAB-Map corridor camera images (``shared/data/rtabmap_corridor``, 512x384 colour JPEGs)
resized to the requested resolution, the right image being the left one shifted by 12 px (a constant
disparity), so PNG sizes are those of real camera images; or, with ``source="synthetic"``,
procedural texture (gradients, blocks and sensor-like noise), which compresses worse.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lcv_replay.errors import ConfigError
from lcv_replay.log.reader import open_log
from lcv_replay.log.writer import LogWriter
from lcv_replay.records import Pose2D, StereoCalibration


@dataclass(frozen=True)
class LogBenchResult:
    """Medians over ``repeats`` runs. MB are 10^6 bytes of the MCAP file."""

    source: str
    frames: int
    width_px: int
    height_px: int
    image_format: str
    compression: str
    repeats: int
    file_size_bytes: int
    mb_per_1000_frames: float
    write_fps: float
    write_mb_per_s: float
    open_s: float
    read_decode_fps: float  # frames() with both images decoded to pixels
    read_decode_mb_per_s: float
    read_lazy_fps: float  # frames() without decoding pixels (index, chunk decompression, protobuf)
    read_lazy_mb_per_s: float
    odometry_s: float  # LogReader.odometry() over the whole log
    write_cpu_ms_per_frame: float  # process CPU time (all threads): robust to a loaded machine
    read_decode_cpu_ms_per_frame: float
    load_average_1min: float  # os.getloadavg() at the end: wall-clock rates are only meaningful if low


def _source_images(source: str, corridor: Path | None, width: int, height: int, count: int) -> list[np.ndarray]:
    import cv2

    rng = np.random.default_rng(0)
    if source == "corridor":
        if corridor is None or not corridor.is_dir():
            raise ConfigError(f"corridor images not found at {corridor}", fix="pass --corridor or use --source synthetic")
        files = sorted(corridor.glob("*.jpg"), key=lambda p: int(p.stem) if p.stem.isdigit() else 0)
        images = []
        for file in files[:count]:
            bgr = cv2.imread(str(file), cv2.IMREAD_COLOR)
            images.append(cv2.cvtColor(cv2.resize(bgr, (width, height), interpolation=cv2.INTER_LINEAR), cv2.COLOR_BGR2RGB))
        return images
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    images = []
    for _ in range(count):
        phase = rng.uniform(0, 2 * np.pi, 3)
        base = np.stack([128 + 70 * np.sin(xx / (9 + 4 * c) + phase[c]) * np.cos(yy / 13 + phase[c]) for c in range(3)], -1)
        blocks = 40 * (((xx // 32 + yy // 24) % 2)[..., None])
        images.append(np.clip(base + blocks + rng.normal(0, 6, base.shape), 0, 255).astype(np.uint8))
    return images


def run_log_benchmark(
    *,
    frames: int = 300,
    width_px: int = 640,
    height_px: int = 480,
    source: str = "corridor",
    corridor: Path | None = None,
    image_format: str = "png",
    compression: str = "zstd",
    repeats: int = 3,
    work_dir: Path | None = None,
) -> LogBenchResult:
    """Write ``frames`` stereo frames, then read them back, ``repeats`` times; return the medians."""
    if frames < 2 or repeats < 1:
        raise ConfigError("need frames >= 2 and repeats >= 1")
    pool = _source_images(source, corridor, width_px, height_px, 84)
    calib = StereoCalibration(width_px, height_px, 0.8 * width_px, 0.8 * width_px, width_px / 2, height_px / 2, 0.5)
    runs: list[dict] = []
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        path = Path(tmp) / "bench.mcap"
        for _ in range(repeats):
            path.unlink(missing_ok=True)
            t0, c0 = time.perf_counter(), time.process_time()
            with LogWriter(
                path, dataset=f"bench/{source}", recorder="bench", nominal_rate_hz=10.0,
                recorder_config={"frames": frames}, image_format=image_format, compression=compression,  # type: ignore[arg-type]
            ) as writer:
                writer.write_calibration(calib, 0)
                for i in range(frames):
                    left = pool[i % len(pool)]
                    right = np.roll(left, -12, axis=1)
                    writer.write_frame(i, i * 100_000_000, left=left, right=right, odom=Pose2D(0.1 * i, 0.0, 0.001 * i))
            write_s, write_cpu = time.perf_counter() - t0, time.process_time() - c0
            size = path.stat().st_size

            t0 = time.perf_counter()
            reader = open_log(path)
            open_s = time.perf_counter() - t0
            t0, c0 = time.perf_counter(), time.process_time()
            for frame in reader.frames():
                frame.left.decode()
                frame.right.decode()
            decode_s, decode_cpu = time.perf_counter() - t0, time.process_time() - c0
            reader = open_log(path)
            t0 = time.perf_counter()
            for frame in reader.frames():
                pass
            lazy_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            reader.odometry()
            odometry_s = time.perf_counter() - t0
            runs.append(
                dict(
                    write_s=write_s, write_cpu=write_cpu, size=size, open_s=open_s, decode_s=decode_s,
                    decode_cpu=decode_cpu, lazy_s=lazy_s, odometry_s=odometry_s,
                )
            )

    def med(key: str) -> float:
        return statistics.median(r[key] for r in runs)

    size = int(med("size"))
    mb = size / 1e6
    return LogBenchResult(
        source=source,
        frames=frames,
        width_px=width_px,
        height_px=height_px,
        image_format=image_format,
        compression=compression,
        repeats=repeats,
        file_size_bytes=size,
        mb_per_1000_frames=mb * 1000 / frames,
        write_fps=frames / med("write_s"),
        write_mb_per_s=mb / med("write_s"),
        open_s=med("open_s"),
        read_decode_fps=frames / med("decode_s"),
        read_decode_mb_per_s=mb / med("decode_s"),
        read_lazy_fps=frames / med("lazy_s"),
        read_lazy_mb_per_s=mb / med("lazy_s"),
        odometry_s=med("odometry_s"),
        write_cpu_ms_per_frame=1000 * med("write_cpu") / frames,
        read_decode_cpu_ms_per_frame=1000 * med("decode_cpu") / frames,
        load_average_1min=os.getloadavg()[0],
    )


def format_results(results: list[LogBenchResult]) -> str:
    """A plain-text table of benchmark results."""
    header = (
        f"{'source':<10} {'res':>8} {'fmt':>4} {'comp':>5} {'frames':>6} {'MB/1k fr':>9} "
        f"{'write fr/s':>10} {'write MB/s':>10} {'read fr/s':>9} {'read MB/s':>9} {'lazy fr/s':>9} {'lazy MB/s':>9} {'open s':>7} "
        f"{'w cpu ms/fr':>11} {'r cpu ms/fr':>11} {'load':>5}"
    )
    lines = [header, "-" * len(header)]
    for r in results:
        lines.append(
            f"{r.source:<10} {f'{r.width_px}x{r.height_px}':>8} {r.image_format:>4} {r.compression:>5} {r.frames:>6} "
            f"{r.mb_per_1000_frames:>9.1f} {r.write_fps:>10.1f} {r.write_mb_per_s:>10.1f} {r.read_decode_fps:>9.1f} "
            f"{r.read_decode_mb_per_s:>9.1f} {r.read_lazy_fps:>9.1f} {r.read_lazy_mb_per_s:>9.1f} {r.open_s:>7.3f} "
            f"{r.write_cpu_ms_per_frame:>11.1f} {r.read_decode_cpu_ms_per_frame:>11.1f} {r.load_average_1min:>5.1f}"
        )
    return "\n".join(lines)


def results_to_json(results: list[LogBenchResult]) -> list[dict]:
    return [asdict(r) for r in results]
