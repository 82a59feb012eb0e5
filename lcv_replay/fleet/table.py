"""Per-log figures of a fleet run: rows, worst first, aggregates; ``fleet.md``, ``fleet.html``,
``fleet.csv`` and ``fleet.parquet``.

Worst first means: failed logs, then the most wrong loop closures accepted (false positives),
then the lowest recall, then the highest ATE over the oracle's ATE (the error left when exactly
the true loops are accepted). The same rows serve ``compare``.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

#: Files written by :func:`write_fleet`.
FLEET_MD, FLEET_HTML, FLEET_CSV, FLEET_PARQUET = "fleet.md", "fleet.html", "fleet.csv", "fleet.parquet"


@dataclass(frozen=True)
class FleetRow:
    """One log's figures (``None``: unknown: no truth, no ground truth, failed).

    ``folder`` is the log's output folder relative to the run folder (``logs/<name>``), ``None`` for
    rows that do not come from a batch (a bench JSON).
    """

    name: str
    log: str
    status: str
    error: str | None = None
    method: str | None = None
    frames: int | None = None
    log_duration_s: float | None = None
    wall_time_s: float | None = None
    x_real_time: float | None = None
    constraints: int | None = None
    accepted: int | None = None
    true_positives: int | None = None
    false_positives: int | None = None
    false_negatives: int | None = None
    precision: float | None = None
    recall: float | None = None
    ate_rmse_m: float | None = None
    oracle_ate_rmse_m: float | None = None
    ate_over_oracle: float | None = None
    hypotheses: int | None = None
    truth_source: str | None = None
    attempts: int | None = None
    folder: str | None = None

    @property
    def done(self) -> bool:
        return self.status in ("ok", "skipped")


COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(FleetRow))


def rows_of_run(run: Mapping[str, Any]) -> list[FleetRow]:
    """The rows of a ``run.json`` document, in its log order."""
    rows = []
    for entry in run.get("logs", []):
        s = entry.get("summary") or {}
        rows.append(FleetRow(
            name=entry["name"], log=entry["log"], status=entry["status"], error=entry.get("error"),
            method=s.get("method"), frames=s.get("frames"), log_duration_s=s.get("log_duration_s"),
            wall_time_s=s.get("wall_time_s"), x_real_time=s.get("x_real_time"), constraints=s.get("constraints"),
            accepted=s.get("accepted"), true_positives=s.get("true_positives"), false_positives=s.get("false_positives"),
            false_negatives=s.get("false_negatives"), precision=s.get("precision"), recall=s.get("recall"),
            ate_rmse_m=s.get("ate_rmse_m"), oracle_ate_rmse_m=entry.get("oracle_ate_rmse_m"),
            ate_over_oracle=entry.get("ate_over_oracle"), hypotheses=s.get("hypotheses"),
            truth_source=s.get("truth_source"), attempts=entry.get("attempts"), folder=entry.get("folder"),
        ))
    return rows


def severity_key(row: FleetRow) -> tuple:
    """Sort key, worst first: failed; most false positives; lowest recall; highest ATE/oracle."""
    unknown = math.inf
    return (
        0 if row.status == "failed" else 1,
        -(row.false_positives or 0),
        row.recall if row.recall is not None else unknown,
        -row.ate_over_oracle if row.ate_over_oracle is not None else unknown,
        -(row.ate_rmse_m or 0.0),
        row.name,
    )


def worst_first(rows: Iterable[FleetRow]) -> list[FleetRow]:
    return sorted(rows, key=severity_key)


# --------------------------------------------------------------------------------------- aggregates
@dataclass(frozen=True)
class FleetAggregate:
    """Fleet-wide figures over the done logs (``ok`` and ``skipped``).

    ``pooled_*`` are micro-averages (total true accepted over total accepted, over total true
    loops); ``ate_*_m`` are quantiles of the per-log ATE; ``x_real_time`` is the log time replayed
    by this run over the run's wall time (``None`` when nothing ran).
    """

    logs: int
    ok: int
    skipped: int
    failed: int
    pending: int
    logs_with_wrong: int
    false_positives: int
    true_positives: int
    false_negatives: int
    pooled_precision: float | None
    pooled_recall: float | None
    ate_logs: int
    ate_min_m: float | None
    ate_median_m: float | None
    ate_p90_m: float | None
    ate_max_m: float | None
    ate_over_oracle_median: float | None
    ate_over_oracle_max: float | None
    log_duration_s: float
    replay_time_s: float
    wall_time_s: float | None
    x_real_time: float | None


def _quantile(values: Sequence[float], q: float) -> float | None:
    return float(np.quantile(np.asarray(values, dtype=float), q)) if values else None


def aggregate(rows: Sequence[FleetRow], *, pending: int = 0, wall_time_s: float | None = None) -> FleetAggregate:
    done = [r for r in rows if r.done]
    tp = sum(r.true_positives or 0 for r in done)
    fp = sum(r.false_positives or 0 for r in done)
    fn = sum(r.false_negatives or 0 for r in done)
    judged = [r for r in done if r.true_positives is not None]
    ates = [r.ate_rmse_m for r in done if r.ate_rmse_m is not None]
    ratios = [r.ate_over_oracle for r in done if r.ate_over_oracle is not None]
    replayed = sum(r.log_duration_s or 0.0 for r in rows if r.status == "ok")
    return FleetAggregate(
        logs=len(rows) + pending,
        ok=sum(1 for r in rows if r.status == "ok"),
        skipped=sum(1 for r in rows if r.status == "skipped"),
        failed=sum(1 for r in rows if r.status == "failed"),
        pending=pending,
        logs_with_wrong=sum(1 for r in done if (r.false_positives or 0) > 0),
        false_positives=fp, true_positives=tp, false_negatives=fn,
        pooled_precision=tp / (tp + fp) if judged and tp + fp else None,
        pooled_recall=tp / (tp + fn) if judged and tp + fn else None,
        ate_logs=len(ates),
        ate_min_m=min(ates) if ates else None,
        ate_median_m=_quantile(ates, 0.5),
        ate_p90_m=_quantile(ates, 0.9),
        ate_max_m=max(ates) if ates else None,
        ate_over_oracle_median=_quantile(ratios, 0.5),
        ate_over_oracle_max=max(ratios) if ratios else None,
        log_duration_s=float(sum(r.log_duration_s or 0.0 for r in done)),
        replay_time_s=float(sum(r.wall_time_s or 0.0 for r in rows if r.status == "ok")),
        wall_time_s=wall_time_s,
        x_real_time=replayed / wall_time_s if wall_time_s and replayed else None,
    )


# --------------------------------------------------------------------------------------- text
def fmt(value: Any, digits: int = 3) -> str:
    """A figure for the text tables: floats with ``digits`` decimals, ``None`` as an en dash."""
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def verdict(agg: FleetAggregate) -> tuple[str, str]:
    """``(css class, sentence)``: the run in one line."""
    parts = [f"{agg.logs} logs: {agg.ok} replayed, {agg.skipped} already done, {agg.failed} failed"]
    if agg.pending:
        parts.append(f"{agg.pending} not run (interrupted)")
    text = ", ".join(parts) + ". "
    if agg.logs_with_wrong:
        text += f"{agg.logs_with_wrong} log(s) accepted wrong loop closures ({agg.false_positives} in all)."
        cls = "bad"
    elif agg.true_positives or agg.false_negatives:
        text += "No wrong loop closure accepted."
        cls = "bad" if agg.failed else "good"
    else:
        text += "No truth to judge the loop closures."
        cls = "bad" if agg.failed else ""
    return cls, text


def aggregate_items(agg: FleetAggregate) -> list[tuple[str, str]]:
    """``(figure, value)`` rows of the aggregate table."""
    return [
        ("logs", f"{agg.logs} ({agg.ok} ok, {agg.skipped} skipped, {agg.failed} failed, {agg.pending} pending)"),
        ("logs with wrong loop closures", str(agg.logs_with_wrong)),
        ("accepted loops: true / false", f"{agg.true_positives} / {agg.false_positives}"),
        ("true loops missed", str(agg.false_negatives)),
        ("pooled precision", fmt(agg.pooled_precision)),
        ("pooled recall", fmt(agg.pooled_recall)),
        ("ATE m: min / median / p90 / max", f"{fmt(agg.ate_min_m, 2)} / {fmt(agg.ate_median_m, 2)} / {fmt(agg.ate_p90_m, 2)} / {fmt(agg.ate_max_m, 2)} ({agg.ate_logs} logs with ground truth)"),
        ("ATE / oracle: median / max", f"{fmt(agg.ate_over_oracle_median, 2)} / {fmt(agg.ate_over_oracle_max, 2)}"),
        ("log time (done logs)", f"{agg.log_duration_s:.1f} s"),
        ("replay time (this run, sum over logs)", f"{agg.replay_time_s:.1f} s"),
        ("batch wall time", "–" if agg.wall_time_s is None else f"{agg.wall_time_s:.1f} s"),
        ("corpus × real time", fmt(agg.x_real_time, 1)),
    ]


TABLE_HEADER = ("#", "log", "status", "FP", "TP", "FN", "P", "R", "ATE m", "ATE/oracle", "frames", "log s", "replay s", "×RT", "open")
_NUMERIC = (True, False, False, True, True, True, True, True, True, True, True, True, True, True, False)


def _open_target(row: FleetRow, run_dir: Path | None) -> str | None:
    """The log's report if it has one, else its recording (relative to the run folder)."""
    if row.folder is None or not row.done:
        return None
    if run_dir is not None and (run_dir / row.folder / "report.html").exists():
        return f"{row.folder}/report.html"
    return f"{row.folder}/recording.rrd"


def table_cells(k: int, row: FleetRow) -> list[Any]:
    return [
        k, row.name, row.status if row.attempts is None or row.attempts <= 1 else f"{row.status} ({row.attempts} attempts)",
        fmt(row.false_positives), fmt(row.true_positives), fmt(row.false_negatives), fmt(row.precision), fmt(row.recall),
        fmt(row.ate_rmse_m, 2), fmt(row.ate_over_oracle, 2), fmt(row.frames), fmt(row.log_duration_s, 1),
        fmt(row.wall_time_s, 1), fmt(row.x_real_time, 0),
    ]


def fleet_markdown(rows: Sequence[FleetRow], agg: FleetAggregate, *, title: str, run_dir: Path | None = None) -> str:
    ordered = worst_first(rows)
    lines = [f"# {title}", "", verdict(agg)[1], "", "## Aggregates", "", "| figure | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in aggregate_items(agg)]
    lines += ["", "## Logs, worst first", "",
              "Wrong acceptances (FP), then recall, then ATE over the oracle's ATE. `open`: the log's report, else its recording (`rerun logs/<name>/recording.rrd`).", "",
              "| " + " | ".join(TABLE_HEADER) + " |", "|" + "|".join("---:" if n else "---" for n in _NUMERIC) + "|"]
    for k, row in enumerate(ordered, 1):
        target = _open_target(row, run_dir)
        cells = table_cells(k, row) + [f"[{Path(target).name}]({target})" if target else "–"]
        lines.append("| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |")
    failed = [r for r in ordered if r.status == "failed"]
    if failed:
        lines += ["", "## Failed logs", ""]
        lines += [f"- **{r.name}**: {r.error}" for r in failed]
    return "\n".join(lines) + "\n"


def fleet_html(rows: Sequence[FleetRow], agg: FleetAggregate, *, title: str, run_dir: Path | None = None,
               subtitle: str = "") -> str:
    from lcv_replay import htmlpage as hp
    from lcv_replay.fleet import plots

    ordered = worst_first(rows)
    cls, text = verdict(agg)
    body = [f"<h1>{hp.esc(title)}</h1>"]
    if subtitle:
        body.append(f'<p class="muted">{hp.esc(subtitle)}</p>')
    body.append(f'<p class="verdict {cls}">{hp.esc(text)}</p>')
    body.append("<h2>Aggregates</h2>" + hp.table(("figure", "value"), aggregate_items(agg)))
    body.append("<h2>Logs, worst first</h2><p>Wrong acceptances (FP), then recall, then ATE over the oracle's ATE "
                "(the error left when exactly the true loops are accepted). <code>open</code>: the log's report, "
                "else its Rerun recording.</p>")
    cells, classes = [], []
    for k, row in enumerate(ordered, 1):
        target = _open_target(row, run_dir)
        cells.append(table_cells(k, row) + [hp.link(target, Path(target).name) if target else "–"])
        classes.append("bad" if row.status == "failed" or (row.false_positives or 0) > 0 else "muted" if row.status == "skipped" else "")
    body.append(hp.table(TABLE_HEADER, cells, numeric=_NUMERIC, row_classes=classes))
    failed = [r for r in ordered if r.status == "failed"]
    if failed:
        body.append("<h2>Failed logs</h2>" + hp.table(("log", "error"), [(r.name, r.error) for r in failed]))
    body.append("<h2>Figures</h2>")
    body.append(hp.figure(plots.detection_figure(ordered), "wrong acceptances and recall per log",
                          "Each dot is a log: recall (x) and wrong loop closures accepted (y); red: at least one wrong acceptance."))
    body.append(hp.figure(plots.ate_figure(ordered), "ATE distribution",
                          "ATE RMSE per log (left) and over the oracle's ATE (right); 1.0 is the best a verifier can do on the log's constraints."))
    body.append(hp.figure(plots.speed_figure(ordered), "replay time per log",
                          "Replay wall time against log duration; the dashed lines are 1×, 10× and 100× real time."))
    return hp.page(title, "\n".join(body))


# --------------------------------------------------------------------------------------- files
def csv_text(rows: Sequence[FleetRow]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else v) for k, v in asdict(row).items()})
    return buffer.getvalue()


def write_parquet(path: Path, rows: Sequence[FleetRow]) -> None:
    """``fleet.parquet`` (typed columns, nulls for unknowns), atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from lcv_replay.fileio import atomic_output

    types = {"str": pa.string(), "int": pa.int64(), "float": pa.float64()}
    schema = []
    for f in fields(FleetRow):
        kind = str(f.type).split("|")[0].strip()
        schema.append(pa.field(f.name, types.get(kind, pa.string())))
    table = pa.Table.from_pylist([asdict(r) for r in rows], schema=pa.schema(schema))
    with atomic_output(path, force=True) as tmp:
        pq.write_table(table, tmp)


def write_fleet(run_dir: Path, rows: Sequence[FleetRow], *, run: Mapping[str, Any]) -> list[Path]:
    """Write the four fleet files into ``run_dir`` (each atomically); returns their paths."""
    from lcv_replay.fileio import write_text_atomic

    run_dir = Path(run_dir)
    agg = aggregate(rows, pending=len(run.get("pending", [])), wall_time_s=run.get("wall_time_s"))
    title = f"lcv-replay fleet: {run_dir.resolve().name}"
    subtitle = (f"method {run.get('method')}, seed {run.get('seed')}, config {run.get('config_hash')}, "
                f"lcv-replay {run.get('code', {}).get('lcv_replay')} ({run.get('code', {}).get('git') or 'no git'}), "
                f"started {run.get('started')}")
    out = [
        write_text_atomic(run_dir / FLEET_MD, fleet_markdown(rows, agg, title=title, run_dir=run_dir)),
        write_text_atomic(run_dir / FLEET_HTML, fleet_html(rows, agg, title=title, run_dir=run_dir, subtitle=subtitle)),
        write_text_atomic(run_dir / FLEET_CSV, csv_text(worst_first(rows))),
    ]
    write_parquet(run_dir / FLEET_PARQUET, worst_first(rows))
    out.append(run_dir / FLEET_PARQUET)
    return out
