"""``lcv-replay compare RUN_A RUN_B``: two batch runs (or two ``bench`` JSONs) joined by log.

A log **regressed** from A to B when it failed in B but not in A, accepted more wrong loop
closures, lost recall beyond ``recall_tol``, got an ATE worse by more than ``max(ate_tol_m,
ate_tol * ATE_A)``, or (only with ``time_tol``) got slower by more than that fraction. It
**improved** on the mirror conditions; it **changed** when a figure moved within tolerance or the
accepted set changed. This is the gate a SLAM team runs before merging a loop-closure change.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from lcv_replay.errors import FleetError
from lcv_replay.fleet.table import FleetRow, fmt

COMPARE_MD, COMPARE_HTML = "compare.md", "compare.html"


# --------------------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class RunFigures:
    """One side of a comparison: where it came from and its rows by key (log name, or
    ``case · method`` for a bench JSON with several methods)."""

    source: Path
    kind: str  # "batch", "bench suite", "bench verify"
    rows: dict[str, FleetRow]
    label: str

    @property
    def method(self) -> str | None:
        methods = {r.method for r in self.rows.values() if r.method}
        return next(iter(methods)) if len(methods) == 1 else None


def _bench_rows(items: Sequence[Mapping[str, Any]]) -> list[FleetRow]:
    """``bench verify``/``suite`` rows as fleet rows (ATE over the oracle from the oracle's rows)."""
    oracle = {(r.get("case") or r.get("log")): r.get("ate_rmse_m") for r in items if r.get("method") == "oracle"}
    methods = {r.get("method") for r in items}
    rows = []
    for r in items:
        base = r.get("case") or Path(str(r.get("log"))).stem
        name = base if len(methods) == 1 else f"{base} · {r.get('method')}"
        reference = oracle.get(r.get("case") or r.get("log"))
        ate = r.get("ate_rmse_m")
        rows.append(FleetRow(
            name=name, log=str(r.get("log")), status="failed" if r.get("error") else "ok", error=r.get("error"),
            method=r.get("method"), frames=r.get("frames"), log_duration_s=r.get("log_duration_s"),
            wall_time_s=r.get("wall_time_s"), x_real_time=r.get("realtime_factor"), constraints=r.get("constraints"),
            accepted=r.get("accepted"), true_positives=r.get("true_positives"), false_positives=r.get("false_positives"),
            false_negatives=r.get("false_negatives"), precision=r.get("precision"), recall=r.get("recall"),
            ate_rmse_m=ate, oracle_ate_rmse_m=reference,
            ate_over_oracle=ate / reference if ate is not None and reference else None,
            truth_source=r.get("truth_source"),
        ))
    return rows


def load_figures(path: str | Path) -> RunFigures:
    """A batch run folder (``run.json``) or a ``bench verify``/``bench suite`` JSON file.

    Raises:
        FleetError: neither.
    """
    from lcv_replay.fleet.batch import RUN_JSON, load_run
    from lcv_replay.fleet.table import rows_of_run

    path = Path(path)
    if path.is_dir() or path.name == RUN_JSON:
        folder = path if path.is_dir() else path.parent
        run = load_run(folder)
        rows = [r for r in rows_of_run(run)]
        return RunFigures(folder, "batch", {r.name: r for r in rows}, folder.resolve().name)
    if not path.is_file():
        raise FleetError("no such run folder or bench JSON", path=path, fix="pass two 'lcv-replay batch' folders or two 'bench ... --json' files")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        raise FleetError("not a JSON file", path=path, fix="pass a batch run folder or a 'bench verify/suite --json' file") from None
    if isinstance(data, dict) and data.get("format", "").startswith("lcv-replay-batch"):
        return load_figures(path.parent)
    if isinstance(data, dict) and isinstance(data.get("rows"), list):
        kind, items = "bench suite", data["rows"]
    elif isinstance(data, list) and all(isinstance(r, dict) for r in data):
        kind, items = "bench verify", data
    else:
        raise FleetError("neither a batch's run.json nor a bench JSON (rows)", path=path,
                         fix="pass a batch run folder or a 'bench verify/suite --json' file")
    if not all(isinstance(r, dict) and "method" in r and ("log" in r or "case" in r) for r in items):
        raise FleetError("the JSON rows lack 'method' and 'log'", path=path, fix="pass a 'bench verify/suite --json' file")
    rows = _bench_rows(items)
    return RunFigures(path, kind, {r.name: r for r in rows}, path.stem)


# --------------------------------------------------------------------------------------- rules
@dataclass(frozen=True)
class Tolerances:
    """What counts as a change.

    Attributes:
        recall_tol: recall may drop this much (absolute) before it is a regression.
        ate_tol, ate_tol_m: ATE may grow by ``max(ate_tol_m, ate_tol * ATE_A)`` (m).
        time_tol: replay time may grow by this fraction before it is a regression; ``None``:
            time is reported, never gated (wall time on a shared machine is noisy).
    """

    recall_tol: float = 0.0
    ate_tol: float = 0.05
    ate_tol_m: float = 0.01
    time_tol: float | None = None

    def __post_init__(self) -> None:
        from lcv_replay.errors import ConfigError

        for name in ("recall_tol", "ate_tol", "ate_tol_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"--{name.replace('_', '-')} {value} is out of range", fix="pass a number >= 0")
        if self.time_tol is not None and not (math.isfinite(self.time_tol) and self.time_tol >= 0):
            raise ConfigError(f"--time-tol {self.time_tol} is out of range", fix="pass a fraction >= 0, e.g. 0.5")


_EPS = 1e-9


@dataclass(frozen=True)
class LogChange:
    """One log in both runs: ``verdict`` is ``regressed``, ``improved``, ``changed`` or ``same``;
    ``reasons`` say why, one short phrase each."""

    name: str
    a: FleetRow
    b: FleetRow
    verdict: str
    regressions: tuple[str, ...] = ()
    improvements: tuple[str, ...] = ()
    changes: tuple[str, ...] = ()

    @property
    def reasons(self) -> tuple[str, ...]:
        return self.regressions + self.improvements + self.changes


def _ratio(a: float | None, b: float | None) -> float | None:
    return b / a if a and b is not None else None


def compare_rows(a: FleetRow, b: FleetRow, tol: Tolerances) -> LogChange:
    """The rules of the module docstring for one log."""
    worse: list[str] = []
    better: list[str] = []
    moved: list[str] = []
    a_ok, b_ok = a.status != "failed", b.status != "failed"
    if a_ok and not b_ok:
        worse.append(f"failed in B: {b.error}")
    elif b_ok and not a_ok:
        better.append("failed in A, ok in B")
    if a_ok and b_ok:
        fa, fb = a.false_positives, b.false_positives
        if fa is not None and fb is not None and fa != fb:
            (worse if fb > fa else better).append(f"wrong acceptances {fa} → {fb}")
        ra, rb = a.recall, b.recall
        if ra is not None and rb is not None and abs(rb - ra) > _EPS:
            text = f"recall {ra:.3f} → {rb:.3f}"
            if rb < ra - tol.recall_tol - _EPS:
                worse.append(text)
            elif rb > ra + _EPS:
                better.append(text)
            else:
                moved.append(text)
        ea, eb = a.ate_rmse_m, b.ate_rmse_m
        if ea is not None and eb is not None and abs(eb - ea) > _EPS:
            allowed = max(tol.ate_tol_m, tol.ate_tol * ea)
            text = f"ATE {ea:.3f} → {eb:.3f} m"
            if eb - ea > allowed:
                worse.append(text)
            elif ea - eb > allowed:
                better.append(text)
            else:
                moved.append(text + " (within tolerance)")
        ta, tb = a.wall_time_s, b.wall_time_s
        if tol.time_tol is not None and ta and tb:
            if tb > ta * (1 + tol.time_tol):
                worse.append(f"time {ta:.1f} → {tb:.1f} s")
            elif tb < ta / (1 + tol.time_tol):
                better.append(f"time {ta:.1f} → {tb:.1f} s")
        if not (worse or better or moved) and (a.accepted, a.true_positives) != (b.accepted, b.true_positives):
            moved.append(f"accepted {a.accepted} → {b.accepted}")
    verdict = "regressed" if worse else "improved" if better else "changed" if moved else "same"
    return LogChange(a.name, a, b, verdict, tuple(worse), tuple(better), tuple(moved))


@dataclass(frozen=True)
class Comparison:
    """The join of two runs."""

    a: RunFigures
    b: RunFigures
    tolerances: Tolerances
    changes: tuple[LogChange, ...]
    only_a: tuple[str, ...] = ()
    only_b: tuple[str, ...] = ()
    warnings: tuple[str, ...] = field(default_factory=tuple)

    def of(self, verdict: str) -> list[LogChange]:
        return [c for c in self.changes if c.verdict == verdict]

    @property
    def regressed(self) -> bool:
        return any(c.verdict == "regressed" for c in self.changes)

    def time_ratio(self) -> float | None:
        """Total replay time of B over A on the logs ok in both."""
        both = [(c.a.wall_time_s, c.b.wall_time_s) for c in self.changes if c.a.wall_time_s and c.b.wall_time_s]
        ta, tb = sum(x for x, _ in both), sum(y for _, y in both)
        return tb / ta if ta else None


def compare(a: RunFigures, b: RunFigures, tolerances: Tolerances | None = None) -> Comparison:
    """Join ``a`` and ``b`` by key and judge every common log.

    Raises:
        FleetError: no log in common.
    """
    tolerances = tolerances or Tolerances()
    common = [name for name in a.rows if name in b.rows]
    if not common:
        raise FleetError(
            f"{a.source} and {b.source} have no log in common ({len(a.rows)} and {len(b.rows)} logs; "
            f"e.g. {next(iter(a.rows), '-')!r} and {next(iter(b.rows), '-')!r})",
            fix="compare two runs over the same logs (logs are joined by name, bench rows by case and method)",
        )
    warnings = []
    if a.method and b.method and a.method != b.method:
        warnings.append(f"the runs use different methods ({a.method} in A, {b.method} in B)")
    order = {"regressed": 0, "improved": 1, "changed": 2, "same": 3}
    changes = sorted((compare_rows(a.rows[n], b.rows[n], tolerances) for n in common), key=lambda c: (order[c.verdict], c.name))
    return Comparison(
        a, b, tolerances, tuple(changes),
        only_a=tuple(n for n in a.rows if n not in b.rows), only_b=tuple(n for n in b.rows if n not in a.rows),
        warnings=tuple(warnings),
    )


# --------------------------------------------------------------------------------------- text
def _arrow(a: Any, b: Any, digits: int = 3) -> str:
    return fmt(a, digits) if a == b else f"{fmt(a, digits)} → {fmt(b, digits)}"


CHANGE_HEADER = ("log", "verdict", "FP", "recall", "ATE m", "replay s", "why")


def change_cells(c: LogChange) -> list[str]:
    return [c.name, c.verdict, _arrow(c.a.false_positives, c.b.false_positives), _arrow(c.a.recall, c.b.recall),
            _arrow(c.a.ate_rmse_m, c.b.ate_rmse_m, 2), _arrow(c.a.wall_time_s, c.b.wall_time_s, 1), "; ".join(c.reasons)]


def headline(cmp: Comparison) -> str:
    n = len(cmp.changes)
    counts = {v: len(cmp.of(v)) for v in ("regressed", "improved", "changed", "same")}
    ratio = cmp.time_ratio()
    text = (f"A = {cmp.a.label} ({cmp.a.kind}, {len(cmp.a.rows)} logs), B = {cmp.b.label} ({cmp.b.kind}, {len(cmp.b.rows)} logs): "
            f"{n} in common; {counts['regressed']} regressed, {counts['improved']} improved, {counts['changed']} changed "
            f"within tolerance, {counts['same']} the same.")
    if ratio is not None:
        text += f" Replay time B/A: {ratio:.2f}."
    return text


def tolerance_text(tol: Tolerances) -> str:
    return (f"regression: a failure, more wrong acceptances, recall lower by more than {tol.recall_tol:g}, "
            f"ATE higher by more than max({tol.ate_tol_m:g} m, {tol.ate_tol:.0%})"
            + ("" if tol.time_tol is None else f", replay time higher by more than {tol.time_tol:.0%}") + ".")


def compare_markdown(cmp: Comparison) -> str:
    lines = [f"# lcv-replay compare: {cmp.a.label} → {cmp.b.label}", "", headline(cmp), "", tolerance_text(cmp.tolerances), ""]
    lines += [f"**warning**: {w}" for w in cmp.warnings]
    changed = [c for c in cmp.changes if c.verdict != "same"]
    lines += ["## Logs that changed", ""]
    if changed:
        lines += ["| " + " | ".join(CHANGE_HEADER) + " |", "|---|---|---:|---:|---:|---:|---|"]
        lines += ["| " + " | ".join(str(x).replace("|", "\\|") for x in change_cells(c)) + " |" for c in changed]
    else:
        lines.append("None: every common log has the same figures.")
    if cmp.only_a or cmp.only_b:
        lines += ["", "## Logs in one run only", ""]
        lines += [f"- only in A ({len(cmp.only_a)}): {', '.join(cmp.only_a[:50])}" if cmp.only_a else "- only in A: none"]
        lines += [f"- only in B ({len(cmp.only_b)}): {', '.join(cmp.only_b[:50])}" if cmp.only_b else "- only in B: none"]
    return "\n".join(lines) + "\n"


def compare_html(cmp: Comparison) -> str:
    from lcv_replay import htmlpage as hp
    from lcv_replay.fleet import plots

    title = f"lcv-replay compare: {cmp.a.label} → {cmp.b.label}"
    cls = "bad" if cmp.regressed else "good"
    body = [f"<h1>{hp.esc(title)}</h1>", f'<p class="muted">A: {hp.esc(cmp.a.source)}<br>B: {hp.esc(cmp.b.source)}</p>',
            f'<p class="verdict {cls}">{hp.esc(headline(cmp))}</p>', f"<p>{hp.esc(tolerance_text(cmp.tolerances))}</p>"]
    body += [f'<p class="verdict bad">warning: {hp.esc(w)}</p>' for w in cmp.warnings]
    changed = [c for c in cmp.changes if c.verdict != "same"]
    body.append("<h2>Logs that changed</h2>")
    if changed:
        classes = ["bad" if c.verdict == "regressed" else "good" if c.verdict == "improved" else "" for c in changed]
        body.append(hp.table(CHANGE_HEADER, [change_cells(c) for c in changed],
                             numeric=(False, False, True, True, True, True, False), row_classes=classes))
    else:
        body.append("<p>None: every common log has the same figures.</p>")
    if cmp.only_a or cmp.only_b:
        body.append("<h2>Logs in one run only</h2>" + hp.table(("run", "logs"), [
            ("only in A", ", ".join(cmp.only_a) or "none"), ("only in B", ", ".join(cmp.only_b) or "none")]))
    regressed = {c.name for c in cmp.of("regressed")}
    body.append("<h2>A against B, per log</h2>")
    body.append(hp.figure(plots.compare_figure([(c.a, c.b) for c in cmp.changes], regressed, ("A: " + cmp.a.label, "B: " + cmp.b.label)),
                          "A against B", "Each dot is a log in both runs; above the diagonal B is higher. Red: regressed."))
    return hp.page(title, "\n".join(body))


def write_compare(cmp: Comparison, out_dir: Path) -> list[Path]:
    """``compare.md`` and ``compare.html`` in ``out_dir`` (atomically)."""
    from lcv_replay.fileio import write_text_atomic

    return [write_text_atomic(Path(out_dir) / COMPARE_MD, compare_markdown(cmp)),
            write_text_atomic(Path(out_dir) / COMPARE_HTML, compare_html(cmp))]
