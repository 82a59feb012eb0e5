"""`lcv-replay demo`: record the built-in synthetic world (once, cached) and replay it with defaults.

The recording is cached in ``$LCV_CACHE_DIR/demo`` if that variable is set, else in
``$XDG_CACHE_HOME/lcv-replay/demo`` (``~/.cache/lcv-replay/demo``); a cached recording is reused
when its frames, seed, image size and the lcv-replay version match. ``--rerecord`` records anew.
"""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import app, check_outputs, force_option

log = logging.getLogger(__name__)

DEMO_FRAMES = 1500  # three windows of W = 500 (paper sec. II-D); a few minutes on 2 CPU cores
DEMO_WIDTH_PX = 320
DEMO_HEIGHT_PX = 240
DEMO_SEED = 0
DEFAULT_DEMO_RRD = Path("demo.rrd")
DEMO_JPEG_QUALITY = 90  # the cached log stays small (PNG stereo pairs would be ~0.5 GB)


def demo_cache_dir() -> Path:
    """Where the demo recording is cached (see the module docstring)."""
    if os.environ.get("LCV_CACHE_DIR"):
        return Path(os.environ["LCV_CACHE_DIR"]) / "demo"
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "lcv-replay" / "demo"


def demo_log_path(frames: int, seed: int, width_px: int, height_px: int, folder: Path | None = None) -> Path:
    """The cached log of these settings; the name changes with the lcv-replay version."""
    from lcv_replay import __version__

    settings = f"{__version__}|{frames}|{seed}|{width_px}x{height_px}|jpeg{DEMO_JPEG_QUALITY}"
    tag = hashlib.blake2b(settings.encode(), digest_size=4).hexdigest()
    return (folder or demo_cache_dir()) / f"synthetic-{frames}f-seed{seed}-{width_px}x{height_px}-{tag}.mcap"


def ensure_demo_log(frames: int, seed: int, width_px: int, height_px: int, *, rerecord: bool = False, quiet: bool = False) -> Path:
    """Record the synthetic world into the cache unless an identical recording is there."""
    from recorders.synthetic import SyntheticOptions, record_synthetic

    path = demo_log_path(frames, seed, width_px, height_px)
    if path.is_file() and not rerecord:
        log.info("reusing the cached demo recording %s", path)
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    if not quiet:
        typer.echo(f"recording the synthetic world ({frames} frames, {width_px}x{height_px}) into {path} (once) ...", err=True)
    options = SyntheticOptions(frames=frames, seed=seed, width_px=width_px, height_px=height_px, image_format="jpeg", jpeg_quality=DEMO_JPEG_QUALITY)
    stats = record_synthetic(path, options, force=True)
    if not quiet and hasattr(stats, "summary"):
        typer.echo(stats.summary(), err=True)
    return path


@app.command("demo", help="Record the synthetic stereo world (cached) and replay it with the defaults into demo.rrd.")
def demo_command(
    frames: int = typer.Option(DEMO_FRAMES, "--frames", min=50, help="Frames of the synthetic drive."),
    save: Optional[Path] = typer.Option(None, "--save", help="Rerun recording to write (default: demo.rrd, replaced by each run)."),
    summary_json: Optional[Path] = typer.Option(None, "--summary-json", help="Also write the summary as JSON (docs/summary-json.md)."),
    export: Optional[Path] = typer.Option(None, "--export", metavar="DIR", help="Write trajectories (TUM, KITTI), loops.csv, accepted.g2o, config.toml and summary.json into DIR."),
    report: Optional[Path] = typer.Option(None, "--report", metavar="FILE.html", help="Write a self-contained HTML report of the run."),
    spawn: bool = typer.Option(False, "--spawn", help="Open a Rerun viewer and stream to it."),
    method: Optional[str] = typer.Option(None, "--method", "-m", help="Verifier (default: the config's)."),
    seed: int = typer.Option(DEMO_SEED, "--seed", help="Seed of the world, the route and the replay."),
    rerecord: bool = typer.Option(False, "--rerecord", help="Record the synthetic world again even if it is cached."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    force: bool = force_option("the recording, the summary JSON, the report and the export folder's files"),
) -> None:
    from lcv_replay.cli.replay import build_sinks
    from lcv_replay.config import ReplayConfig
    from lcv_replay.errors import require_seed
    from lcv_replay.replay import ReplayOptions, replay
    from lcv_replay.shutdown import StopToken
    from lcv_replay.sinks.config import RerunOutputs

    require_seed(seed, "--seed")
    check_outputs(summary_json, report, force=force, folder=export)
    check_outputs(save or DEFAULT_DEMO_RRD, force=force or save is None)  # the default recording is replaced
    save = save or DEFAULT_DEMO_RRD
    config = ReplayConfig()
    outputs = RerunOutputs(save=save, spawn=spawn)
    # Every output is checked before the (possibly long) recording of the world.
    build_sinks(rerun_config=config.rerun, outputs=None, summary_json=summary_json, quiet=True, export=export, report=report)
    log_path = ensure_demo_log(frames, seed, DEMO_WIDTH_PX, DEMO_HEIGHT_PX, rerecord=rerecord, quiet=quiet)
    sinks = build_sinks(rerun_config=config.rerun, outputs=outputs, summary_json=summary_json, quiet=quiet,
                        export=export, report=report)
    stop = StopToken()
    summary = replay(ReplayOptions(log_path=log_path, config=config, method=method, seed=seed), sinks, stop=stop)
    if summary.interrupted:
        raise typer.Exit(stop.exit_code)
