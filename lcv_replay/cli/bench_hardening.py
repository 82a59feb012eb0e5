"""``lcv-replay bench fuzz`` and ``lcv-replay bench soak``: robustness benchmarks (tables and JSON)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import bench_app, check_outputs, force_option

_REPO = Path(__file__).resolve().parents[2]
GOLDEN_LOG = _REPO / "tests" / "data" / "golden.mcap"


def _ring_seed_log(data: Optional[Path], workdir: Path) -> Path | None:
    """``record g2o`` of Vertigo ring (434 poses) with 20 injected outliers, or ``None`` without the data."""
    from lcv_replay.bench.suite import resolve_data_dir
    from lcv_replay.errors import RecorderError
    from recorders.g2o import G2oOptions, record_g2o

    try:
        ring = resolve_data_dir(data) / "vertigo" / "ring"
    except RecorderError:
        return None
    if not (ring / "originalDataset" / "ring.g2o").is_file():
        return None
    out = workdir / "seed-ring.mcap"
    options = G2oOptions(ground_truth=ring / "groundTruth" / "ring.g2o", outliers=20, seed=1)
    record_g2o(ring / "originalDataset" / "ring.g2o", out, options, force=True)
    return out


@bench_app.command(
    "fuzz",
    help=(
        "Mutate small logs (bit flips, overwrites, truncation, duplicated chunks, zeroed ranges, appended bytes) "
        "and run info, info --recover and the replay on each; counts by outcome class (goal: no traceback, no hang)."
    ),
)
def bench_fuzz_command(
    files: int = typer.Option(10_000, "--files", min=1, help="Mutated files."),
    seed: int = typer.Option(0, "--seed", help="Seed of the mutations (mutant i is reproducible alone)."),
    log: Optional[list[Path]] = typer.Option(None, "--log", help="Log to mutate; repeat for several (default: tests/data/golden.mcap and a 'record g2o' of Vertigo ring). Each is used as it is and uncompressed without CRCs."),
    timeout_s: float = typer.Option(60.0, "--timeout", help="Seconds per file before it counts as a hang."),
    data: Optional[Path] = typer.Option(None, "--data", help="Shared data folder (default $LCV_SHARED_DATA, else ../shared/data)."),
    workdir: Path = typer.Option(Path("bench-out/fuzz"), "--workdir", help="Work folder: the mutant, and every file that was not ok/error (bad/)."),
    output: Path = typer.Option(Path("bench-out/fuzz.json"), "-o", "--output", help="JSON results."),
    force: bool = force_option("the JSON results"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress lines."),
) -> None:
    from lcv_replay.bench.fuzz import GOOD_OUTCOMES, SeedLog, format_report, run_fuzz
    from lcv_replay.errors import ConfigError, require_seed
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.shutdown import StopToken, stop_on_signals

    require_seed(seed, "--seed")
    output.parent.mkdir(parents=True, exist_ok=True)
    check_outputs(output, force=force)
    workdir.mkdir(parents=True, exist_ok=True)
    paths = list(log or [])
    if not paths:
        if GOLDEN_LOG.is_file():
            paths.append(GOLDEN_LOG)
        ring = _ring_seed_log(data, workdir)
        if ring is not None:
            paths.append(ring)
        else:
            typer.echo("note: the shared data (vertigo/ring) is absent: fuzzing without a g2o log", err=True)
    if not paths:
        raise ConfigError("no log to mutate", fix="pass --log LOG.mcap")
    seeds = [s for path in paths for s in SeedLog.pair(path)]
    done = []

    def on_result(result) -> None:
        done.append(result)
        if result.outcome not in GOOD_OUTCOMES:
            typer.echo(f"#{result.index} {result.log} {result.mutation}: {result.outcome}: {result.detail}", err=True)
        elif not quiet and len(done) % 500 == 0:
            bad = sum(r.outcome not in GOOD_OUTCOMES for r in done)
            typer.echo(f"[{len(done)}/{files}] {bad} bad so far", err=True)

    stop = StopToken()
    with stop_on_signals(stop, what="stopping after this file and writing the report so far"):
        report = run_fuzz(seeds, files=files, seed=seed, workdir=workdir, timeout_s=timeout_s, on_result=on_result, should_stop=lambda: stop.requested)
    typer.echo(f"seed logs: {', '.join(f'{s.name} ({len(s.data)} bytes)' for s in seeds)}; load {os.getloadavg()[0]:.1f}")
    typer.echo(format_report(report))
    write_text_atomic(output, json.dumps({**report.as_dict(), "logs": [str(p) for p in paths]}, indent=2) + "\n")
    typer.echo(f"wrote {output}")
    if stop.requested:
        raise typer.Exit(stop.exit_code)
    if report.bad:
        typer.echo(f"error: {len(report.bad)} of {report.files} files did not end in success or one error line (kept in {workdir / 'bad'})", err=True)
        raise typer.Exit(1)


@bench_app.command(
    "soak",
    help=(
        "Replay one long log (real KITTI pose graphs chained to 20,000 frames) and sample RSS and time per frame "
        "every 1,000 frames (goal: both flat after warm-up)."
    ),
)
def bench_soak_command(
    frames: int = typer.Option(20_000, "--frames", min=2000, help="Frames of the chained log."),
    every: int = typer.Option(1000, "--every", min=10, help="Sample every this many frames."),
    alpha: str = typer.Option("0.50", "--alpha", help="robustslam_kitti alpha of the chained graphs."),
    rerun: bool = typer.Option(True, "--rerun/--no-rerun", help="Write the Rerun recording too, as a replay does by default."),
    data: Optional[Path] = typer.Option(None, "--data", help="Shared data folder (default $LCV_SHARED_DATA, else ../shared/data)."),
    workdir: Path = typer.Option(Path("bench-out/soak"), "--workdir", help="Where the chained log and the recording go."),
    output: Path = typer.Option(Path("bench-out/soak.json"), "-o", "--output", help="JSON results."),
    force: bool = force_option("the JSON results"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress lines."),
) -> None:
    from lcv_replay.bench.soak import build_soak_log, format_report, run_soak
    from lcv_replay.bench.suite import resolve_data_dir
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.shutdown import StopToken, stop_on_signals

    output.parent.mkdir(parents=True, exist_ok=True)
    check_outputs(output, force=force)
    data_dir = resolve_data_dir(data)
    workdir.mkdir(parents=True, exist_ok=True)
    log = workdir / f"soak-{frames}-alpha{alpha}.mcap"
    if not log.is_file():
        stats = build_soak_log(data_dir, log, frames=frames, alpha=alpha, force=True)
        typer.echo(stats.summary(), err=True)

    def on_sample(sample) -> None:
        if not quiet:
            typer.echo(f"{sample.frames:>7} frames  RSS {sample.rss_mb:7.1f} MB  {sample.ms_per_frame:7.2f} ms/frame", err=True)

    stop = StopToken()
    with stop_on_signals(stop, what="stopping after this frame and writing the report so far"):
        report = run_soak(log, every=every, rerun=rerun, workdir=workdir, stop=stop, on_sample=on_sample)
    typer.echo(f"soak: {log.name}, {report.frames} frames, Rerun recording {'on' if rerun else 'off'}; load {os.getloadavg()[0]:.1f}")
    typer.echo(format_report(report))
    write_text_atomic(output, json.dumps(report.as_dict(), indent=2) + "\n")
    typer.echo(f"wrote {output}")
    if stop.requested:
        raise typer.Exit(stop.exit_code)
