"""``lcv-replay batch`` and ``lcv-replay compare``: fleet runs on Ray (see :mod:`lcv_replay.fleet`)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import app, bench_app, check_outputs, force_option
from lcv_replay.cli.replay import ConstraintChoice

_ADDRESS_HELP = (
    "Join a running Ray cluster: auto (the one 'ray start' left on this machine, or $RAY_ADDRESS), "
    "HOST:PORT (its GCS) or ray://HOST:PORT (Ray Client). The logs and RUN_DIR must be on storage that "
    "every node mounts at the same path. Default: an embedded local cluster (loopback only, no dashboard)."
)


def cluster_options(address: Optional[str], workers: Optional[int], cpus_per_task: int = 1, max_retries: int = 3):
    """``--address``/``--workers``/... as a :class:`~lcv_replay.fleet.engine.ClusterSpec` (validated)."""
    from lcv_replay.fleet.engine import ClusterSpec

    return ClusterSpec(address=address, workers=workers, cpus_per_task=cpus_per_task, max_retries=max_retries)


@app.command(
    "batch",
    help=(
        "Replay many logs on Ray, one task per log (the same replay as 'lcv-replay LOG.mcap --rate max'), into "
        "RUN_DIR: logs/<name>/recording.rrd and summary.json, run.json, fleet.md/.html (worst first), "
        "fleet.csv/.parquet. A rerun resumes: logs done with the same config and log hash are skipped. "
        "Exit 0 if every log succeeded, 2 otherwise."
    ),
)
def batch_command(
    logs: list[str] = typer.Argument(..., metavar="LOGS...", help="MCAP files, folders (searched recursively for *.mcap) or quoted glob patterns ('fleet/**/*.mcap')."),
    out: Path = typer.Option(..., "--out", "-o", metavar="RUN_DIR", help="The run folder (created; an earlier run's folder is resumed)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="TOML config over the paper defaults, for every log."),
    method: Optional[str] = typer.Option(None, "--method", "-m", help="Verifier (default: the config's verification.method)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Seed of retrieval and verification (default: the config's)."),
    constraints: Optional[ConstraintChoice] = typer.Option(None, "--constraints", case_sensitive=False, help="images, log or both (default: per log, log if it has candidates, else images)."),
    address: Optional[str] = typer.Option(None, "--address", help=_ADDRESS_HELP),
    workers: Optional[int] = typer.Option(None, "--workers", "-j", help="Logs replayed at once (default: this machine's cores; with --address: as many as the cluster's CPUs allow)."),
    cpus_per_task: int = typer.Option(1, "--cpus-per-task", help="CPUs each log's task declares; its torch/BLAS threads are capped to this."),
    max_retries: int = typer.Option(3, "--max-retries", help="Times Ray re-runs a log whose worker process died (killed, out of memory)."),
    export: bool = typer.Option(False, "--export", help="Also write each log's export (trajectories, loops.csv, accepted.g2o) into logs/<name>/export/."),
    report: bool = typer.Option(False, "--report", help="Also write each log's logs/<name>/report.html."),
    resume: bool = typer.Option(True, "--resume/--no-resume", help="Skip logs already done with the same config and log hash (default), or replay every log again."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    from rich.console import Console

    from lcv_replay.config import load_config
    from lcv_replay.fleet.batch import BatchSpec, check_run_dir, run_batch
    from lcv_replay.fleet.engine import Cluster
    from lcv_replay.fleet.inputs import discover_logs
    from lcv_replay.replay import ReplayOptions, StopToken, sigint_requests_stop
    from lcv_replay.verification.registry import available_methods

    # Everything that can be refused is refused before a file is written or Ray is started.
    spec_cluster = cluster_options(address, workers, cpus_per_task, max_retries)
    replay_config = load_config(config)
    options = ReplayOptions(log_path=Path("."), config=replay_config, method=method, seed=seed,
                            constraints=None if constraints is None else constraints.value, rate=None)
    chosen = options.resolved_config().verification.method
    if chosen not in available_methods():
        from lcv_replay.errors import ConfigError

        raise ConfigError(f"unknown verification method '{chosen}'", fix=f"use one of {', '.join(sorted(available_methods()))}")
    check_run_dir(out)
    found = discover_logs(logs, exclude=out)
    spec = BatchSpec(logs=found, run_dir=out, options=options, export=export, report=report, resume=resume,
                     command=tuple(["lcv-replay", *sys.argv[1:]]))

    console = Console(stderr=True)
    stop = StopToken()
    progress = _BatchProgress(console, quiet=quiet)
    with Cluster(spec_cluster) as cluster:
        progress.cluster_started(cluster)
        with sigint_requests_stop(stop, what="no new log is started; the running ones finish and run.json is written"), progress:
            state = run_batch(spec, cluster, stop=stop, on_event=progress.on_event)
    _report(state)


class _BatchProgress:
    """One rich bar over logs (done/failed/running, logs per minute, × real time); one line per
    finished log when stderr is not a terminal."""

    def __init__(self, console, *, quiet: bool):
        self.console = console
        self.quiet = quiet
        self.bar = None
        self.task = None
        self._swapped: list = []

    def cluster_started(self, cluster) -> None:
        if self.quiet:
            return
        info = cluster.describe()
        where = "embedded local Ray" if info["embedded"] else f"Ray at {info['address']}"
        self.console.print(
            f"{where}: {info['nodes']} node(s), {info['cluster_cpus']:g} CPUs, {info['concurrent_tasks']} logs at a time"
            + (f" (started in {info['startup_s']:.1f} s)" if info["embedded"] and info["startup_s"] else ""),
            markup=False, highlight=False,
        )

    def __enter__(self):
        if self.quiet or not self.console.is_terminal:
            return self
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        from lcv_replay.sinks.progress import route_logging_to

        self.bar = Progress(
            TextColumn("[bold]logs"), BarColumn(bar_width=24), MofNCompleteColumn(),
            TextColumn("{task.fields[counts]}"), TextColumn("{task.fields[rate]}"), TimeElapsedColumn(),
            console=self.console, transient=False, redirect_stderr=False, redirect_stdout=False, expand=False,
        )
        self.task = self.bar.add_task("logs", total=None, counts="", rate="")
        self.bar.start()
        self._swapped = route_logging_to(self.console)
        return self

    def __exit__(self, *exc_info) -> None:
        for handler, stream in self._swapped:
            handler.setStream(stream)
        self._swapped = []
        if self.bar is not None:
            self.bar.stop()
            self.bar = None

    def on_event(self, event) -> None:
        from lcv_replay.fleet.table import fmt

        state = event.state
        done = state.count("ok") + state.count("failed") + state.count("skipped")
        elapsed = state.elapsed_s
        finished_here = state.count("ok") + state.count("failed")
        per_min = f"{60.0 * finished_here / elapsed:.1f} logs/min" if elapsed > 0 and finished_here else "– logs/min"
        xrt = f"{state.replayed_log_s / elapsed:.1f}× real time" if elapsed > 0 and state.replayed_log_s else "–× real time"
        counts = (f"{state.count('ok')} ok · {state.count('failed')} failed · {state.count('skipped')} skipped · "
                  f"{len(state.running)} running")
        if self.bar is not None:
            self.bar.update(self.task, total=state.total, completed=done, counts=counts, rate=f"{per_min} · {xrt}")
            if event.kind == "finished" and event.entry is not None and event.entry.status == "failed":
                self.console.print(f"failed: {event.log.name}: {event.entry.error}", markup=False, highlight=False)
        elif not self.quiet and event.kind in ("planned", "finished"):
            if event.kind == "planned":
                line = f"batch: {state.total} logs, {state.count('skipped')} already done"
            elif event.entry is None:
                line = f"[{done}/{state.total}] {event.log.name}: not finished (stopped)"
            else:
                e = event.entry
                s = e.summary or {}
                what = (e.error if e.status == "failed" else
                        f"FP {s.get('false_positives')} R {fmt(s.get('recall'))} ATE {fmt(s.get('ate_rmse_m'), 2)} m, "
                        f"{fmt(s.get('wall_time_s'), 1)} s")
                retried = f" after {e.attempts} attempts" if e.attempts > 1 else ""
                line = f"[{done}/{state.total}] {event.log.name}: {e.status}{retried}: {what} ({counts}; {per_min}, {xrt})"
            self.console.print(line, markup=False, highlight=False, soft_wrap=True)


def _report(state) -> None:
    """The run's verdict and its worst logs on stdout; the exit code (0, 2, or 130 when stopped)."""
    from lcv_replay.fleet.batch import failed_entries
    from lcv_replay.fleet.table import aggregate, rows_of_run, table_cells, verdict, worst_first

    run = state.as_dict()
    rows = rows_of_run(run)
    agg = aggregate(rows, pending=len(run["pending"]), wall_time_s=run["wall_time_s"])
    typer.echo(verdict(agg)[1])
    worst = worst_first(rows)[:10]
    if worst:
        typer.echo("worst logs:")
        for k, row in enumerate(worst, 1):
            c = table_cells(k, row)
            typer.echo(f"  {c[0]:>3}. {c[1]}  {c[2]}  FP {c[3]}  R {c[7]}  ATE {c[8]} m  ATE/oracle {c[9]}")
    typer.echo(f"run folder: {state.spec.run_dir}  (fleet.md, fleet.html, run.json)")
    failed = failed_entries(state)
    for entry in failed:
        typer.echo(f"failed: {entry.log.name}: {entry.error}", err=True)
    if state.interrupted:
        typer.echo(f"interrupted: {len(state.pending)} log(s) not run; run the same command again to finish them", err=True)
        raise typer.Exit(130)
    if failed:
        typer.echo(f"error: {len(failed)} of {state.total} logs failed (listed above; see {state.spec.run_dir / 'run.json'})", err=True)
        raise typer.Exit(2)


@app.command(
    "compare",
    help=(
        "Join two batch runs (or two 'bench verify/suite --json' files) by log and print the logs whose figures "
        "changed: new wrong acceptances, recall lost or gained, ATE worse or better beyond a tolerance, time. "
        "Writes compare.md and compare.html. Exit 1 when any log regressed (a CI gate), 0 otherwise."
    ),
)
def compare_command(
    run_a: Path = typer.Argument(..., metavar="RUN_A", help="The reference: a batch run folder or a bench JSON."),
    run_b: Path = typer.Argument(..., metavar="RUN_B", help="The candidate: a batch run folder or a bench JSON."),
    out: Path = typer.Option(Path("."), "--out", "-o", help="Folder for compare.md and compare.html (default: the current folder)."),
    recall_tol: float = typer.Option(0.0, "--recall-tol", help="Recall may drop this much (absolute) before a log counts as regressed."),
    ate_tol: float = typer.Option(0.05, "--ate-tol", help="ATE may grow by this fraction (or by --ate-tol-m, whichever is larger)."),
    ate_tol_m: float = typer.Option(0.01, "--ate-tol-m", help="ATE may grow by this many metres (or by --ate-tol, whichever is larger)."),
    time_tol: Optional[float] = typer.Option(None, "--time-tol", help="Also gate on replay time: slower by more than this fraction is a regression (default: report time only)."),
    force: bool = force_option("compare.md and compare.html"),
) -> None:
    from lcv_replay.fleet.compare import CHANGE_HEADER, COMPARE_HTML, COMPARE_MD, Tolerances, change_cells, compare, headline, load_figures, write_compare

    tolerances = Tolerances(recall_tol=recall_tol, ate_tol=ate_tol, ate_tol_m=ate_tol_m, time_tol=time_tol)
    check_outputs(out / COMPARE_MD, out / COMPARE_HTML, force=force)
    result = compare(load_figures(run_a), load_figures(run_b), tolerances)
    typer.echo(headline(result))
    for warning in result.warnings:
        typer.echo(f"warning: {warning}", err=True)
    changed = [c for c in result.changes if c.verdict != "same"]
    if changed:
        widths = [max(len(str(x)) for x in col) for col in zip(CHANGE_HEADER, *(change_cells(c) for c in changed))]
        for cells in [CHANGE_HEADER, *(change_cells(c) for c in changed)]:
            typer.echo("  ".join(str(x).ljust(w) for x, w in zip(cells, widths)).rstrip())
    paths = write_compare(result, out)
    typer.echo(f"wrote {paths[0]} and {paths[1]}")
    if result.regressed:
        typer.echo(f"regression: {len(result.of('regressed'))} log(s) got worse from A to B", err=True)
        raise typer.Exit(1)


@bench_app.command(
    "fleet",
    help=(
        "Measure batch on this machine: KITTI g2o logs with 1 then 2 workers (speedup), Ray's start-up and "
        "per-task overheads on a 1-frame log, a camera log's cost per frame against the verifier's, and a simulation "
        "of a 1,000-log corpus on 10 to 1,000 workers. Prints tables; --json writes everything."
    ),
)
def bench_fleet_command(
    data: Optional[Path] = typer.Option(None, "--data", help="Shared data folder (default $LCV_SHARED_DATA, else ../shared/data)."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Where the logs are built and reused (default: the suite's cache)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Folder for the batch runs (default: a temporary folder, removed)."),
    sequence: list[str] = typer.Option(["00", "02", "05", "06", "07"], "--sequence", help="robustslam_kitti sequences (repeatable)."),
    alpha: list[str] = typer.Option(["0.25", "0.75"], "--alpha", help="robustslam_kitti alphas (repeatable)."),
    workers: list[int] = typer.Option([1, 2], "--workers", help="Worker counts to compare (repeatable; the first is the reference)."),
    repeats: int = typer.Option(1, "--repeats", min=1, help="Rounds of the worker counts, interleaved."),
    image_frames: int = typer.Option(300, "--image-frames", min=0, help="Frames of the synthetic camera log (0: skip the image measurement)."),
    corpus: int = typer.Option(1000, "--corpus", min=1, help="Logs in the simulated corpus."),
    storage_gb_s: float = typer.Option(1.0, "--storage-gb-s", help="Assumed aggregate bandwidth of the shared storage in the simulation."),
    method: Optional[str] = typer.Option(None, "--method", "-m", help="Verifier (default: the config's)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write every measurement as JSON."),
    force: bool = force_option("the JSON file"),
) -> None:
    import json
    import shutil
    import tempfile

    from lcv_replay.bench.suite import default_workdir, resolve_data_dir
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.fleet import bench
    from lcv_replay.replay import ReplayOptions

    check_outputs(json_out, force=force)
    data_dir = resolve_data_dir(data)
    base = out or Path(tempfile.mkdtemp(prefix="lcv-bench-fleet-"))
    try:
        doc = bench.run(
            data_dir=data_dir, workdir=workdir or default_workdir(), out=base, sequences=sequence, alphas=alpha,
            workers=workers, repeats=repeats, image_frames=image_frames, corpus_logs=corpus, storage_gb_s=storage_gb_s,
            options=ReplayOptions(log_path=Path("."), method=method, rate=None),
            note=lambda text: typer.echo(text, err=True),
        )
    finally:
        if out is None:
            shutil.rmtree(base, ignore_errors=True)
    typer.echo(bench.markdown(doc))
    if json_out is not None:
        write_text_atomic(json_out, json.dumps(doc, indent=2) + "\n")
        typer.echo(f"\nwrote {json_out}")
