"""``lcv-replay vo LOG.mcap -o OUT.mcap``: add stereo visual odometry (``/odom``) to a log.

The command validates its arguments, runs :func:`lcv_replay.vo.log_vo.add_vo_odometry` with a
progress bar, and prints a summary (plus drift against the log's ground truth when it has one).
OpenCV and the VO modules are imported inside the command so that ``--help`` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import app, check_outputs, config_option, force_option
from lcv_replay.cli.record import recording_progress


def load_vo_config(path: Path | None):
    """The ``[vo]`` table of a TOML config (the one config tree, :class:`lcv_replay.config.ReplayConfig`)."""
    from lcv_replay.config import load_config

    return load_config(path).vo


def vo_summary_lines(result, ground_truth) -> list[str]:
    """Human summary of a VO run, with KITTI drift and ATE when ground truth is given."""
    import numpy as np

    s = result.summary()
    counts = ", ".join(f"{k} {v}" for k, v in sorted(s["status_counts"].items()) if k not in ("ok", "first"))
    lines = [
        f"stereo VO: {s['frames']} frames, {s['fallback_frames']} constant-velocity fallbacks"
        + (f" ({counts})" if counts else "")
        + f", median {s['median_inliers']:.0f} inliers, {s['median_reprojection_rmse_px'] or float('nan'):.2f} px RMSE, "
        f"{s['pairs_per_s']:.1f} pairs/s"
    ]
    if ground_truth is not None and np.all(np.isfinite(ground_truth)) and len(ground_truth) == s["frames"] > 1:
        from lcv_replay.evaluation.metrics import absolute_trajectory_error
        from lcv_replay.vo.drift import kitti_drift, path_length_m

        drift = kitti_drift(result.poses, ground_truth)
        ate = absolute_trajectory_error(result.poses, ground_truth)
        lines.append(
            f"vs ground truth ({path_length_m(ground_truth)[-1]:.0f} m): translational error "
            f"{drift.translation_error_pct:.2f} %, rotational error {drift.rotation_error_deg_per_m:.4f} deg/m "
            f"(segments {', '.join(f'{L:g}' for L in drift.lengths_m)} m), ATE {ate.rmse_m:.2f} m"
        )
    return lines


@app.command("vo", help="Add stereo visual odometry (/odom, /tf) to a log with stereo images; writes a new file.")
def vo_command(
    log: Path = typer.Argument(..., help="An lcv-replay MCAP log with stereo images and calibration."),
    out: Path = typer.Option(..., "--out", "-o", help="Output .mcap (written atomically; never the input)."),
    config: Optional[Path] = config_option("its [vo] table (keys of VoConfig) applies"),
    replace_odometry: bool = typer.Option(False, "--replace-odometry", help="Replace the log's existing /odom and /tf."),
    summary_json: Optional[Path] = typer.Option(None, "--json", help="Also write the run summary (per-frame quality included) as JSON."),
    force: bool = force_option("OUT and the --json summary"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary."),
) -> None:
    import json

    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.log.reader import open_log
    from lcv_replay.shutdown import StopToken, stop_on_signals
    from lcv_replay.vo.log_vo import add_vo_odometry

    vo_config = load_vo_config(config)
    check_outputs(summary_json, force=force)
    with open_log(log) as reader:
        frames, ground_truth = reader.info.frames, reader.ground_truth()
    stop = StopToken()
    with stop_on_signals(stop, what="stopping after this frame and writing the log so far"), \
            recording_progress("stereo VO", quiet=quiet) as progress:
        on_step = None if progress is None else (lambda step: progress(step.index + 1, frames))
        stats = add_vo_odometry(log, out, vo_config, force=force, replace_odometry=replace_odometry, on_step=on_step)
    if summary_json is not None:
        report = {
            "log": str(log),
            "out": str(out),
            "summary": stats.result.summary(),
            "frames": [{**s.quality.as_dict(), "odom": list(s.T_odom_base)} for s in stats.result.steps],
        }
        write_text_atomic(summary_json, json.dumps(report, indent=1))
    if not quiet:
        for line in vo_summary_lines(stats.result, ground_truth):
            typer.echo(line)
        typer.echo(f"wrote {stats.path}" + (" (replaced the log's odometry)" if stats.replaced_odometry else ""))
    if stats.interrupted:
        typer.echo(f"INTERRUPTED: {stats.path} holds the first {len(stats.result.steps)} of {stats.frames_planned} frames", err=True)
        raise typer.Exit(stop.exit_code)
