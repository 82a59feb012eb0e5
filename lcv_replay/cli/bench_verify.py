"""`lcv-replay bench verify` and `lcv-replay bench suite`: verification-only benchmarks."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import bench_app, check_outputs, config_option, force_option

_METHOD_HELP = "Verification method (repeatable): ilv, ilv+, none, ir-only, dcs, gm, cauchy, gnc, oracle, ..."


def _load_verification_config(config: Optional[Path]):
    from lcv_replay.config import load_config

    return load_config(config).verification


def _num(value) -> str:
    return "–" if value is None else f"{value:.3f}"


def _check_seed(seed: Optional[int]) -> None:
    if seed is not None:
        from lcv_replay.errors import require_seed

        require_seed(seed, "--seed")


@bench_app.command(
    "verify",
    help=(
        "Verification only (no retrieval, no Rerun) on logs carrying /loop_candidates: one row per "
        "log and method with precision, recall, F1, ATE and time; --json writes the rows."
    ),
)
def bench_verify_command(
    logs: list[Path] = typer.Argument(..., help="lcv-replay MCAP logs with /loop_candidates (e.g. from 'record g2o')."),
    method: list[str] = typer.Option(["ilv+"], "--method", "-m", help=_METHOD_HELP),
    config: Optional[Path] = config_option("its [verification] section is used"),
    seed: Optional[int] = typer.Option(None, "--seed", help="Override verification.seed."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the rows as a JSON list (atomically)."),
    force: bool = force_option("the JSON file"),
) -> None:
    from lcv_replay.bench.suite import CaseRow, markdown_rows
    from lcv_replay.bench.verify import load_inputs, verify_inputs
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.verification.registry import make_verifier

    verification = _load_verification_config(config)
    _check_seed(seed)
    for name in method:  # unknown methods fail before any log is read
        make_verifier(name, verification)
    check_outputs(json_out, force=force)
    rows = []
    for path in logs:
        inputs = load_inputs(path)
        for name in method:
            rows.append(verify_inputs(inputs, name, verification, seed=seed).row)
    typer.echo(markdown_rows([CaseRow(Path(r.log).name, r.method, r) for r in rows]))
    if json_out is not None:
        write_text_atomic(json_out, json.dumps([r.as_dict() for r in rows], indent=2) + "\n")
        typer.echo(f"wrote {json_out}")


@bench_app.command(
    "suite",
    help=(
        "Run methods side by side on a suite of logs built by the g2o recorder from the shared data "
        "(robustslam_kitti and Vertigo Manhattan with outliers); prints markdown tables, writes JSON."
    ),
)
def bench_suite_command(
    quick: bool = typer.Option(False, "--quick", help="The CI subset (suite 'quick')."),
    suite: Optional[str] = typer.Option(None, "--suite", help="Built-in suite name (standard, vertigo, generated, extended, regressions, quick) or a suite TOML file."),
    seeds: Optional[int] = typer.Option(None, "--seeds", min=1, help="Redraw every seeded case (outliers injected, generated worlds) with N new seeds, one case each."),
    first_seed: Optional[int] = typer.Option(None, "--first-seed", min=0, help="With --seeds: use seeds S..S+N-1 (default: drawn at random, printed, so the run can be repeated)."),
    method: list[str] = typer.Option([], "--method", "-m", help=_METHOD_HELP + " Default: the suite's, else none, ir-only, dcs, gm, cauchy, gnc, oracle, ilv, ilv+."),
    config: Optional[Path] = config_option("its [verification] section is used"),
    seed: Optional[int] = typer.Option(None, "--seed", help="Override verification.seed."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the report (rows, summary, config) as JSON."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Where the suite's logs are built and reused (default ~/.cache/lcv-replay/suite)."),
    data: Optional[Path] = typer.Option(None, "--data", help="Shared data folder (default $LCV_SHARED_DATA, else ../shared/data)."),
    rows_table: bool = typer.Option(True, "--rows/--no-rows", help="Print the per-case table, not only the per-method summary."),
    address: Optional[str] = typer.Option(None, "--address", help="Run the (case, method) pairs on this Ray cluster (auto, HOST:PORT, ray://HOST:PORT); see 'lcv-replay batch --help'."),
    workers: Optional[int] = typer.Option(None, "--workers", "-j", help="Run the (case, method) pairs as Ray tasks, this many at a time (an embedded local cluster unless --address); default: serial, in this process."),
    force: bool = force_option("the JSON report"),
) -> None:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from lcv_replay.bench.suite import (
        SuiteReport,
        available_suite_methods,
        default_workdir,
        markdown_rows,
        markdown_summary,
        resolve_data_dir,
        run_suite,
    )
    from lcv_replay.bench.suites import get_suite
    from lcv_replay.errors import ConfigError
    from lcv_replay.fileio import write_text_atomic

    if quick and suite is not None:
        raise ConfigError("--quick and --suite are exclusive", fix="pass one of them")
    if first_seed is not None and seeds is None:
        raise ConfigError("--first-seed needs --seeds N", fix="pass --seeds N as well")
    chosen = get_suite("quick" if quick else (suite or "standard"))
    if seeds is not None:
        from lcv_replay.bench.suites import with_seeds

        if first_seed is None:
            import secrets

            first_seed = 1000 + secrets.randbelow(10**6)
        chosen = with_seeds(chosen, range(first_seed, first_seed + seeds))
        typer.echo(f"seeds {first_seed}..{first_seed + seeds - 1} (repeat with --seeds {seeds} --first-seed {first_seed})", err=True)
    verification = _load_verification_config(config)
    _check_seed(seed)
    data_dir = resolve_data_dir(data)
    workdir = workdir or default_workdir()
    check_outputs(json_out, force=force)
    methods = available_suite_methods(method or chosen.methods)

    done_rows = []

    def write_report(report: SuiteReport) -> None:
        if json_out is not None:
            write_text_atomic(json_out, json.dumps(report.as_dict(), indent=2) + "\n")

    console = Console(stderr=True)
    progress = Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("{task.fields[what]}"), console=console, transient=True,
    )
    task = progress.add_task(chosen.name, total=len(chosen.cases) * len(methods), what="")

    def on_event(event) -> None:
        what = f"building {event.case}" if event.phase == "build" else f"{event.case} · {event.method}" if event.method else ""
        progress.update(task, completed=event.done, what=what)

    def on_row(row) -> None:
        done_rows.append(row)
        if not console.is_terminal:  # no live bar (CI, a pipe): one line per finished run instead
            r = row.row
            status = f"error: {row.error}" if r is None else (
                f"P {_num(r.precision)} R {_num(r.recall)} FP {r.false_positives} ATE {_num(r.ate_rmse_m)} m, {r.wall_time_s:.1f} s"
            )
            console.print(f"[{len(done_rows)}/{len(chosen.cases) * len(methods)}] {row.case} {row.method}: {status}", markup=False, highlight=False)

    import contextlib
    import time

    from lcv_replay.fleet.suite import on_cluster

    cluster = contextlib.nullcontext()
    if address is not None or workers is not None:
        from lcv_replay.cli.fleet import cluster_options
        from lcv_replay.fleet.engine import Cluster

        cluster = Cluster(cluster_options(address, workers))
    started = time.perf_counter()
    try:
        with cluster as connected, progress:
            report = run_suite(
                chosen, data_dir=data_dir, workdir=workdir, config=verification, methods=methods,
                seed=seed, progress=on_event, on_row=on_row, distribute=None if connected is None else on_cluster(connected),
            )
    except KeyboardInterrupt as interrupt:  # Ctrl-C or SIGTERM (lcv_replay.shutdown.Interrupted)
        from lcv_replay.config import to_dict

        partial = SuiteReport(
            chosen.name, chosen.description, data_dir, workdir, methods, tuple(done_rows), (),
            time.perf_counter() - started, to_dict(verification), complete=False,
        )
        write_report(partial)
        typer.echo(f"interrupted after {len(done_rows)} runs" + (f"; partial report in {json_out}" if json_out else ""), err=True)
        raise typer.Exit(getattr(interrupt, "exit_code", 130)) from None

    reused = sum(1 for b in report.builds if b.reused)
    typer.echo(f"suite {report.suite}: {len(chosen.cases)} cases x {len(methods)} methods in {report.wall_time_s:.1f} s "
               f"(logs in {workdir}, {reused} reused)\n")
    if rows_table:
        typer.echo(markdown_rows(report.rows) + "\n")
    typer.echo(markdown_summary(report.summary()))
    write_report(report)
    if json_out is not None:
        typer.echo(f"\nwrote {json_out}")
    errors = [r for r in report.rows if r.error]
    if errors:
        typer.echo(f"error: {len(errors)} runs failed, e.g. {errors[0].method} on {errors[0].case}: {errors[0].error}", err=True)
        raise typer.Exit(1)


@bench_app.command(
    "scale",
    help=(
        "Cost against history: generated worlds of growing length, verified by a method and by "
        "references side by side; prints the totals and the time per window against the number of "
        "constraints already verified, beside the back end's (iSAM2 fed the accepted loops) on the "
        "same windows; writes JSON."
    ),
)
def bench_scale_command(
    poses: Optional[str] = typer.Option(None, "--poses", help="World lengths in poses, comma-separated (default 1000,2000,5000,10000; none with --log unless given)."),
    layout: str = typer.Option("grid", "--layout", help="World layout: grid or ring."),
    noise: str = typer.Option("gaussian", "--noise", help="Noise model: gaussian, heavy or misdeclared."),
    mode: str = typer.Option("random", "--outlier-mode", help="Outlier mode: random, local or group."),
    outliers_per_1000: int = typer.Option(100, "--outliers-per-1000", min=0, help="Injected outliers per 1,000 poses."),
    seed: int = typer.Option(0, "--world-seed", help="Seed of the worlds and their outliers."),
    method: str = typer.Option("ilv+", "--method", "-m", help="The incremental method measured."),
    reference: list[str] = typer.Option(["gnc", "dcs"], "--reference", "-r", help="Methods timed side by side (repeatable)."),
    config: Optional[Path] = config_option("its [verification] section is used"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the report as JSON."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Where the worlds and logs are built and reused (default ~/.cache/lcv-replay/suite)."),
    logs: list[Path] = typer.Option([], "--log", help="Also time this lcv-replay MCAP log (repeatable), e.g. a Vertigo case 'bench suite' built in its work folder, or any log 'record g2o' wrote."),
    repeat: int = typer.Option(1, "--repeat", min=1, help="Rounds per log: every method once a round, the order reversed every other round; prints the medians, their ranges and the rounds' ratios."),
    force: bool = force_option("the JSON report"),
) -> None:
    from lcv_replay.bench.scale import markdown_totals, markdown_windows, run_scale, scale_cases
    from lcv_replay.bench.suite import default_workdir
    from lcv_replay.errors import ConfigError
    from lcv_replay.fileio import write_text_atomic
    from lcv_replay.verification.registry import make_verifier

    if poses is None:
        poses = "" if logs else "1000,2000,5000,10000"
    try:
        lengths = [int(p) for p in poses.split(",") if p.strip()]
    except ValueError:
        raise ConfigError(f"--poses {poses!r} is not a list of integers", fix="pass e.g. --poses 1000,2000,5000") from None
    if not lengths and not logs:
        raise ConfigError("--poses names no world length", fix="pass e.g. --poses 1000,2000,5000")
    for log_path in logs:
        if not log_path.is_file():
            raise ConfigError(f"{log_path}: {'not a file' if log_path.exists() else 'no such log'}", fix="pass an lcv-replay MCAP log with --log (e.g. from 'record g2o' or 'bench suite')")
    verification = _load_verification_config(config)
    for name in (method, *reference):
        make_verifier(name, verification)
    check_outputs(json_out, force=force)
    cases = scale_cases(lengths, layout=layout, noise=noise, mode=mode, outliers_per_1000=outliers_per_1000, seed=seed)

    def on_run(run) -> None:
        rounds = "" if len(run.round_times_s) < 2 else " (rounds " + ", ".join(f"{t:.1f}" for t in run.round_times_s) + ")"
        typer.echo(f"{run.case} {run.method}: {run.wall_time_s:.1f} s{rounds}, P {_num(run.precision)} R {_num(run.recall)}", err=True)

    report = run_scale(
        cases, method=method, references=reference, data_dir=Path("."), workdir=workdir or default_workdir(), config=verification, on_run=on_run,
        logs=logs, repeat=repeat,
    )
    if repeat > 1:
        typer.echo(f"{repeat} rounds per log: times and ratios are medians, with their ranges in parentheses (a ratio's over the rounds, each between two runs one after the other)\n")
    typer.echo(markdown_totals(report) + "\n")
    typer.echo(markdown_windows(report))
    if json_out is not None:
        write_text_atomic(json_out, json.dumps(report.as_dict(), indent=2) + "\n")
        typer.echo(f"\nwrote {json_out}")
