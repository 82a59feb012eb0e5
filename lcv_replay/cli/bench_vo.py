"""``lcv-replay bench vo``: stereo VO drift on the synthetic world, speed, a real KITTI step, end to end.

Prints one table per part and writes everything as JSON (see :mod:`lcv_replay.bench.vo`).
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
from pathlib import Path
from typing import Any, Iterator, Optional

import typer

from lcv_replay.cli.app import bench_app, check_outputs, config_option, force_option

DEFAULT_KITTI_FRAMES = Path("../shared/data/kitti06_frames")


def format_table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    """Aligned text table; ``columns`` are ``(key, title, format spec)``; ``None`` prints ``n/a``."""

    def cell(value: Any, spec: str) -> str:
        if value is None:
            return "n/a"
        if isinstance(value, (tuple, list)):
            return ",".join(format(v, "g") for v in value)
        return format(value, spec) if spec else str(value)

    cells = [[cell(row[key], spec) for key, _, spec in columns] for row in rows]
    widths = [max([len(title)] + [len(c[i]) for c in cells]) for i, (_, title, _) in enumerate(columns)]
    lines = ["  ".join(title.rjust(w) for (_, title, _), w in zip(columns, widths))]
    lines.append("-" * len(lines[0]))
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)


DRIFT_COLUMNS = [
    ("source", "odometry", ""),
    ("resolution", "images", ""),
    ("frames", "frames", "d"),
    ("path_length_m", "path m", ".0f"),
    ("translation_error_pct", "t_err %", ".3f"),
    ("rotation_error_deg_per_m", "r_err deg/m", ".5f"),
    ("segment_lengths_m", "segments m", ""),
    ("segments", "n_seg", "d"),
    ("ate_rmse_m", "ATE m", ".3f"),
    ("end_point_error_m", "end err m", ".2f"),
    ("fallback_frames", "fallbacks", "d"),
    ("median_inliers", "inliers", ".0f"),
]
SPEED_COLUMNS = [
    ("resolution", "images", ""),
    ("pairs", "pairs", "d"),
    ("runs", "runs", "d"),
    ("pairs_per_s", "pairs/s (median)", ".1f"),
    ("pairs_per_s_min", "min", ".1f"),
    ("pairs_per_s_max", "max", ".1f"),
    ("ms_per_pair", "ms/pair", ".1f"),
    ("cpu_ms_per_pair", "CPU ms/pair", ".1f"),
    ("with_png_decode_pairs_per_s", "with PNG decode pairs/s", ".1f"),
    ("opencv_threads", "cv2 threads", "d"),
    ("loadavg_1min", "load avg", ".1f"),
]
KITTI_COLUMNS = [
    ("gt_step_m", "GT step m", ".4f"),
    ("estimated_step_m", "VO step m", ".4f"),
    ("translation_error_m", "t_err m", ".4f"),
    ("translation_error_pct", "t_err %", ".2f"),
    ("rotation_error_deg", "r_err deg", ".4f"),
    ("gt_rotation_deg", "GT rot deg", ".4f"),
    ("stereo_points", "stereo pts", "d"),
    ("inliers", "inliers", "d"),
    ("reprojection_rmse_px", "RMSE px", ".3f"),
]
E2E_COLUMNS = [
    ("odometry", "odometry", ""),
    ("frames", "frames", "d"),
    ("odometry_translation_error_pct", "odom t_err %", ".3f"),
    ("odometry_ate_m", "odom ATE m", ".2f"),
    ("constraints", "constraints", "d"),
    ("accepted", "accepted", "d"),
    ("true_positives", "TP", "d"),
    ("false_positives", "FP", "d"),
    ("false_negatives", "FN", "d"),
    ("precision", "precision", ".3f"),
    ("recall", "recall", ".3f"),
    ("ate_rmse_m", "ATE m", ".2f"),
    ("replay_wall_s", "replay s", ".0f"),
]


@contextlib.contextmanager
def _progress(quiet: bool) -> Iterator:
    if quiet:
        yield None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=Console(stderr=True), transient=True) as bar:
        tasks: dict[str, Any] = {}

        def update(label: str, done: int, total: int) -> None:
            if label not in tasks:
                tasks[label] = bar.add_task(label, total=total)
            bar.update(tasks[label], completed=done, total=total)

        yield update


@bench_app.command("vo")
def bench_vo_command(
    frames: int = typer.Option(1500, "--frames", min=20, help="Frames of the synthetic route for the drift table."),
    resolution: str = typer.Option("640x480", "--resolution", help="Image size WIDTHxHEIGHT for drift and speed."),
    seed: int = typer.Option(0, "--seed", help="Seed of the synthetic world and route."),
    noise: Optional[list[float]] = typer.Option(None, "--noise", help="Sensor noise (grey-level sigma) of a drift row; repeat (default: 0 and 2)."),
    speed_pairs: int = typer.Option(200, "--speed-pairs", min=10, help="Pre-rendered pairs for the speed measurement."),
    speed_runs: int = typer.Option(5, "--speed-runs", min=1, help="Timed runs over them (median reported)."),
    kitti_frames: Path = typer.Option(DEFAULT_KITTI_FRAMES, "--kitti-frames", help="Folder with kitti06-12.png, kitti06-12-R.png, kitti06-13.png, 06.txt (skipped if absent)."),
    end_to_end: bool = typer.Option(False, "--end-to-end/--no-end-to-end", help="Also record the demo with simulated and VO odometry and replay both (minutes)."),
    e2e_frames: int = typer.Option(1500, "--e2e-frames", min=50, help="Frames of each end-to-end recording."),
    replay_config: Optional[Path] = typer.Option(None, "--replay-config", help="TOML config of the end-to-end replays (default: the paper defaults)."),
    vo_config: Optional[Path] = config_option("its [vo] table (keys of VoConfig) applies"),
    workdir: Path = typer.Option(Path("bench-out"), "--workdir", help="Scratch folder for the end-to-end logs (scratch files, always overwritten)."),
    output: Path = typer.Option(Path("bench-out/vo_bench.json"), "-o", "--output", help="JSON results."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    force: bool = force_option("the JSON results"),
) -> None:
    """Stereo VO: KITTI drift metric and ATE on the synthetic world, pairs/s, KITTI 06 12->13, end to end."""
    from lcv_replay.bench import vo as bench
    from lcv_replay.cli.record_synthetic import parse_resolution
    from lcv_replay.cli.vo import load_vo_config
    from lcv_replay.config import load_config, to_dict
    from lcv_replay.errors import require_seed
    from lcv_replay.fileio import write_text_atomic

    require_seed(seed, "--seed")
    width_px, height_px = parse_resolution(resolution)
    config = load_vo_config(vo_config)
    output.parent.mkdir(parents=True, exist_ok=True)
    check_outputs(output, force=force)
    replay_cfg = load_config(replay_config) if end_to_end else None
    results: dict[str, Any] = {
        "machine": {"cpu_count": os.cpu_count(), "machine": platform.machine(), "python": platform.python_version()},
        "vo_config": to_dict(config),
        "seed": seed,
    }
    with _progress(quiet) as progress:
        drift = bench.synthetic_drift(
            seed=seed, frames=frames, width_px=width_px, height_px=height_px,
            noise_levels_grey=tuple(noise) if noise else (0.0, 2.0), config=config, progress=progress,
        )
        typer.echo("\nDrift on the synthetic route (KITTI metric: mean over segments of the stated lengths; ATE SE(2)-aligned)")
        typer.echo(format_table([r.as_dict() for r in drift], DRIFT_COLUMNS))
        results["drift"] = [r.as_dict() for r in drift]

        speed = bench.vo_speed(seed=seed, pairs=speed_pairs, width_px=width_px, height_px=height_px, runs=speed_runs, config=config)
        typer.echo(f"\nSpeed (tracker only, images in memory; and with PNG decoding; {os.cpu_count()} cores, shared)")
        typer.echo(format_table([speed.as_dict()], SPEED_COLUMNS))
        results["speed"] = speed.as_dict()

        if all((kitti_frames / n).is_file() for n in ("kitti06-12.png", "kitti06-12-R.png", "kitti06-13.png", "06.txt")):
            step = bench.kitti_step(kitti_frames, config)
            typer.echo("\nKITTI 06, frame 12 (stereo) -> 13 (left), against 06.txt")
            typer.echo(format_table([step.as_dict()], KITTI_COLUMNS))
            results["kitti06_12_13"] = step.as_dict()
        else:
            typer.echo(f"\nKITTI 06 12->13: skipped ({kitti_frames} not found; pass --kitti-frames)")
            results["kitti06_12_13"] = None

        if end_to_end:
            rows = bench.end_to_end(workdir, seed=seed, frames=e2e_frames, width_px=width_px, height_px=height_px, replay_config=replay_cfg, progress=progress)
            typer.echo("\nEnd to end: the demo replayed through retrieval and verification, simulated drift vs stereo VO")
            typer.echo(format_table([r.as_dict() for r in rows], E2E_COLUMNS))
            results["end_to_end"] = [r.as_dict() for r in rows]
            results["replay_config"] = to_dict(replay_cfg)
    results["machine"]["loadavg_1min_at_end"] = os.getloadavg()[0]
    write_text_atomic(output, json.dumps(results, indent=2, default=float) + "\n")
    typer.echo(f"\nwrote {output}", err=True)
