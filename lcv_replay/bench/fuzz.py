"""Fuzzing the log reader: mutated copies of real logs through ``info`` and the replay.

``lcv-replay bench fuzz`` (and the fuzz test of the suite) mutates small logs in six ways, each
seeded and reproducible (mutant ``i`` of seed ``s`` is drawn from ``numpy.random.default_rng([s,
i])``):

* ``bit_flip``: 1 to 3 bits within 8 bytes; ``overwrite``: 1 to 64 random bytes; ``zero_range``: 1 to 512 bytes.
  Half of these land anywhere in the file, half in the first 64 bytes of a record (its opcode,
  length and first fields: where parsers trip);
* ``truncate``: the file cut at a random byte;
* ``duplicate_chunk``: a chunk record copied to a random record boundary;
* ``append_garbage``: 1 to 4096 random bytes, or the file's own first bytes, appended.

Each mutant goes through the CLI commands (by default ``info``, ``info --recover`` and the replay),
run in-process by one worker subprocess (:mod:`lcv_replay.cli.inprocess`) that the harness restarts
when a file hangs (per-file timeout) or kills it. Every command run is classified:

* ``ok``: exit 0; ``error``: exit 2 with exactly one ``error:`` line, naming the file, and no
  traceback (the promise for bad input);
* ``bad_error``: exit 2 but not exactly one ``error:`` line naming the file; ``bad_exit``: another
  exit code without a traceback; ``traceback``: an exception escaped; ``hang``: over the per-file
  timeout; ``crash``: the worker died (a signal, the memory limit).

The goal is that only ``ok`` and ``error`` occur.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import select
import subprocess
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

MUTATIONS: tuple[str, ...] = ("bit_flip", "overwrite", "truncate", "duplicate_chunk", "zero_range", "append_garbage")
#: Outcome classes, worst last (a file's outcome is the worst of its command runs).
OUTCOMES: tuple[str, ...] = ("ok", "error", "bad_error", "bad_exit", "traceback", "hang", "crash")
GOOD_OUTCOMES = frozenset({"ok", "error"})


# -- mutants ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SeedLog:
    """A log to mutate: a short name, its bytes and its top-level records ``(opcode, offset, length)``."""

    name: str
    data: bytes
    records: tuple[tuple[int, int, int], ...]

    @classmethod
    def from_bytes(cls, name: str, data: bytes) -> "SeedLog":
        from lcv_replay.log.container import iter_records

        records = iter_records(data[8:-8], base_offset=8, path=Path(name), section="the file")
        return cls(name, data, tuple((op, off, 9 + len(body)) for op, off, body in records))

    @classmethod
    def pair(cls, path: str | Path, name: str | None = None) -> tuple["SeedLog", "SeedLog"]:
        """The log as it is, and its :func:`plain_copy` (named ``<name>-plain``)."""
        name = name or Path(path).stem
        return cls.from_bytes(name, Path(path).read_bytes()), cls.from_bytes(f"{name}-plain", plain_copy(path))


def plain_copy(path: str | Path) -> bytes:
    """The log at ``path`` rewritten uncompressed and without CRCs (the same records otherwise).

    Damage to such a copy reaches the record parsers that compression and CRCs would shield: the
    fuzz uses both kinds of seed.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from lcv_replay.log.writer import MessageCopier

    out = io.BytesIO()
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        writer = Writer(out, chunk_size=4096, compression=CompressionType.NONE, enable_crcs=False)
        writer.start(profile=header.profile, library=header.library)
        copier = MessageCopier(writer)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            copier.add(schema, channel, message)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        writer.finish()
    return out.getvalue()


@dataclass(frozen=True)
class Mutant:
    """Mutant ``index`` of a fuzz run: which log, how it was damaged, and the damaged bytes."""

    index: int
    log: str
    mutation: str
    description: str
    data: bytes = field(repr=False)


def _position(rng: np.random.Generator, seed: SeedLog, span: int) -> int:
    """A byte offset for a damage of ``span`` bytes: anywhere, or in the first 64 bytes of a record."""
    size = len(seed.data)
    if rng.random() < 0.5 or not seed.records:
        return int(rng.integers(0, max(size - span, 1)))
    _op, offset, length = seed.records[int(rng.integers(len(seed.records)))]
    return min(offset + int(rng.integers(0, min(length, 64))), max(size - span, 0))


def mutate(seed: SeedLog, mutation: str, rng: np.random.Generator) -> tuple[bytes, str]:
    """One damaged copy of ``seed.data`` and a description of the damage."""
    data = bytearray(seed.data)
    size = len(data)
    if mutation == "bit_flip":
        start, flips = _position(rng, seed, 8), []
        for _ in range(int(rng.integers(1, 4))):
            pos, bit = min(start + int(rng.integers(8)), size - 1), int(rng.integers(8))
            data[pos] ^= 1 << bit
            flips.append(f"{pos}.{bit}")
        return bytes(data), "flipped bits (byte.bit) " + ", ".join(flips)
    if mutation == "overwrite":
        length = int(rng.integers(1, 65))
        pos = _position(rng, seed, length)
        data[pos : pos + length] = rng.integers(0, 256, size=length, dtype=np.uint8).tobytes()
        return bytes(data[:size]), f"overwrote bytes {pos}..{pos + length} with random bytes"
    if mutation == "zero_range":
        length = int(rng.integers(1, 513))
        pos = _position(rng, seed, length)
        data[pos : pos + length] = bytes(min(length, size - pos))
        return bytes(data), f"zeroed bytes {pos}..{min(pos + length, size)}"
    if mutation == "truncate":
        cut = int(rng.integers(0, size))
        return bytes(data[:cut]), f"cut at byte {cut} of {size}"
    if mutation == "duplicate_chunk":
        chunks = [r for r in seed.records if r[0] == 0x06] or list(seed.records)
        _op, offset, length = chunks[int(rng.integers(len(chunks)))]
        boundaries = [off for _op, off, _len in seed.records] + [size - 8]
        at = boundaries[int(rng.integers(len(boundaries)))]
        copy = data[offset : offset + length]
        return bytes(data[:at] + copy + data[at:]), f"copied the {length}-byte record at byte {offset} to byte {at}"
    if mutation == "append_garbage":
        length = int(rng.integers(1, 4097))
        if rng.random() < 0.2:
            extra, what = bytes(data[:length]), f"the file's first {min(length, size)} bytes"
        else:
            extra, what = rng.integers(0, 256, size=length, dtype=np.uint8).tobytes(), f"{length} random bytes"
        return bytes(data) + extra, f"appended {what}"
    raise ValueError(f"unknown mutation {mutation!r}")


def mutants(seeds: Sequence[SeedLog], count: int, seed: int = 0, *, start: int = 0) -> Iterator[Mutant]:
    """``count`` mutants, cycling over mutations and seed logs; mutant ``i`` is reproducible alone."""
    for i in range(start, start + count):
        mutation = MUTATIONS[i % len(MUTATIONS)]
        log = seeds[(i // len(MUTATIONS)) % len(seeds)]
        data, description = mutate(log, mutation, np.random.default_rng([seed, i]))
        yield Mutant(i, log.name, mutation, description, data)


# -- running the CLI in-process -------------------------------------------------------------------
@dataclass(frozen=True)
class CliRun:
    """One CLI command run: arguments, exit code, captured output, and the traceback if one escaped."""

    args: tuple[str, ...]
    exit_code: int
    stdout: str
    stderr: str
    traceback: str | None = None

    def error_lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.startswith("error:")]



def classify(run: CliRun, path: str | Path) -> str:
    """The outcome class of one command run on the file ``path`` (see the module docstring)."""
    if run.traceback is not None or "Traceback (most recent call last)" in run.stderr:
        return "traceback"
    if run.exit_code == 0:
        return "ok"
    if run.exit_code == 2:
        lines = run.error_lines()
        return "error" if len(lines) == 1 and str(path) in lines[0] else "bad_error"
    return "bad_exit"


def worst(outcomes: Sequence[str]) -> str:
    return max(outcomes, key=OUTCOMES.index)


def default_commands(path: Path, workdir: Path) -> dict[str, list[str]]:
    """``info``, ``info --recover`` and the replay (no Rerun output; summary JSON in ``workdir``), by name."""
    return {
        "info": ["info", str(path)],
        "info --recover": ["info", str(path), "--recover"],
        "replay": [str(path), "--no-rerun", "--quiet", "--summary-json", str(workdir / "summary.json"), "--force"],
    }


# -- the worker process -----------------------------------------------------------------------------
class Worker:
    """One subprocess (:mod:`lcv_replay.cli.inprocess`) that runs CLI commands in-process; restarted
    after a hang or a crash."""

    def __init__(self, *, timeout_s: float, startup_timeout_s: float = 120.0):
        self.timeout_s = timeout_s
        self.startup_timeout_s = startup_timeout_s
        self.restarts = 0
        self._proc: subprocess.Popen | None = None

    def _start(self) -> None:
        env = dict(os.environ, PYTHONFAULTHANDLER="1")
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "lcv_replay.cli.inprocess"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env,
        )
        if self._readline(self.startup_timeout_s) is None:
            raise RuntimeError("the fuzz worker did not start")

    def _readline(self, timeout_s: float) -> str | None:
        assert self._proc is not None and self._proc.stdout is not None
        ready, _, _ = select.select([self._proc.stdout], [], [], timeout_s)
        if not ready:
            return None
        line = self._proc.stdout.readline()
        return line or None

    def run(self, commands: list[list[str]]) -> tuple[list[CliRun] | None, str | None]:
        """The runs of ``commands``, or ``(None, "hang" | "crash")``."""
        if self._proc is None or self._proc.poll() is not None:
            self._start()
        assert self._proc is not None and self._proc.stdin is not None
        try:
            self._proc.stdin.write(json.dumps({"commands": commands}) + "\n")
            self._proc.stdin.flush()
        except BrokenPipeError:
            self.close()
            return None, "crash"
        line = self._readline(self.timeout_s)
        if line is None:
            outcome = "hang" if self._proc.poll() is None else "crash"
            self.close()
            self.restarts += 1
            return None, outcome
        return [CliRun(tuple(r["args"]), r["exit_code"], r["stdout"], r["stderr"], r["traceback"]) for r in json.loads(line)], None

    def close(self) -> None:
        if self._proc is None:
            return
        with contextlib.suppress(Exception):
            self._proc.kill()
        with contextlib.suppress(Exception):
            self._proc.wait(timeout=10)
        self._proc = None

    def __enter__(self) -> "Worker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- a fuzz run ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FileResult:
    """The outcome of one mutant: per command, and the worst of them."""

    index: int
    log: str
    mutation: str
    description: str
    outcomes: tuple[str, ...]  # one per command ("hang"/"crash" for all of them when the worker failed)
    outcome: str
    seconds: float
    detail: str = ""  # the error line, or the traceback's last line, of the worst run


@dataclass
class FuzzReport:
    """Counts by outcome class, per mutation and per command, plus every file that was not ``ok``/``error``."""

    seed: int
    files: int = 0
    commands: tuple[str, ...] = ()
    by_mutation: dict[str, Counter] = field(default_factory=dict)
    by_command: dict[str, Counter] = field(default_factory=dict)
    bad: list[FileResult] = field(default_factory=list)
    wall_time_s: float = 0.0
    worker_restarts: int = 0
    complete: bool = True

    def add(self, result: FileResult) -> None:
        self.files += 1
        self.by_mutation.setdefault(result.mutation, Counter())[result.outcome] += 1
        for name, outcome in zip(self.commands, result.outcomes):
            self.by_command.setdefault(name, Counter())[outcome] += 1
        if result.outcome not in GOOD_OUTCOMES:
            self.bad.append(result)

    def totals(self) -> Counter:
        total: Counter = Counter()
        for counts in self.by_mutation.values():
            total.update(counts)
        return total

    def as_dict(self) -> dict:
        return {
            "seed": self.seed,
            "files": self.files,
            "complete": self.complete,
            "wall_time_s": self.wall_time_s,
            "worker_restarts": self.worker_restarts,
            "outcomes": list(OUTCOMES),
            "totals": {k: self.totals().get(k, 0) for k in OUTCOMES},
            "by_mutation": {m: {k: c.get(k, 0) for k in OUTCOMES} for m, c in self.by_mutation.items()},
            "by_command": {m: {k: c.get(k, 0) for k in OUTCOMES} for m, c in self.by_command.items()},
            "bad_files": [asdict(r) for r in self.bad],
        }


def run_fuzz(
    seeds: Sequence[SeedLog],
    *,
    files: int,
    seed: int = 0,
    workdir: Path,
    timeout_s: float = 60.0,
    commands: Callable[[Path, Path], dict[str, list[str]]] = default_commands,
    keep_bad: bool = True,
    on_result: Callable[[FileResult], None] | None = None,
    should_stop: Callable[[], bool] = lambda: False,
) -> FuzzReport:
    """Run ``files`` mutants of ``seeds`` through ``commands`` and count the outcomes.

    Mutants whose outcome is not ``ok``/``error`` are kept as ``workdir/bad/NNNNN-<mutation>.mcap``
    (with ``keep_bad``) to reproduce them. ``should_stop`` is polled between files (Ctrl-C or
    SIGTERM: the report then covers the files done, with ``complete = False``).
    """
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    path = workdir / "mutant.mcap"
    report = FuzzReport(seed=seed, commands=tuple(commands(path, workdir)))
    started = time.perf_counter()
    with Worker(timeout_s=timeout_s) as worker:
        for mutant in mutants(seeds, files, seed):
            if should_stop():
                report.complete = False
                break
            path.write_bytes(mutant.data)
            t0 = time.perf_counter()
            runs, failure = worker.run(list(commands(path, workdir).values()))
            seconds = time.perf_counter() - t0
            if runs is None:
                outcomes = (failure,) * len(report.commands)
                detail = f"the worker {'hung' if failure == 'hang' else 'died'} on this file"
            else:
                outcomes = tuple(classify(r, path) for r in runs)
                k = max(range(len(runs)), key=lambda j: OUTCOMES.index(outcomes[j]))
                detail = _detail(runs[k])
            result = FileResult(mutant.index, mutant.log, mutant.mutation, mutant.description, outcomes, worst(outcomes), seconds, detail)
            report.add(result)
            if keep_bad and result.outcome not in GOOD_OUTCOMES:
                bad = workdir / "bad"
                bad.mkdir(exist_ok=True)
                (bad / f"{mutant.index:05d}-{mutant.log}-{mutant.mutation}.mcap").write_bytes(mutant.data)
            if on_result is not None:
                on_result(result)
        report.worker_restarts = worker.restarts
    report.wall_time_s = time.perf_counter() - started
    return report


def _detail(run: CliRun) -> str:
    if run.traceback:
        return run.traceback.strip().splitlines()[-1]
    lines = run.error_lines()
    if lines:
        return lines[0] if len(lines) == 1 else f"{len(lines)} error lines: {lines[0]}"
    tail = (run.stderr.strip().splitlines() or [""])[-1]
    return f"exit {run.exit_code}: {tail}"


def format_report(report: FuzzReport) -> str:
    """Plain-text tables: outcome counts per mutation (files) and per command (runs)."""

    def table(title: str, rows: dict[str, Counter]) -> list[str]:
        head = f"{title:<18}" + "".join(f"{k:>10}" for k in OUTCOMES) + f"{'total':>8}"
        lines = [head, "-" * len(head)]
        total: Counter = Counter()
        for name, counts in rows.items():
            total.update(counts)
            lines.append(f"{name:<18}" + "".join(f"{counts.get(k, 0):>10}" for k in OUTCOMES) + f"{sum(counts.values()):>8}")
        lines.append(f"{'all':<18}" + "".join(f"{total.get(k, 0):>10}" for k in OUTCOMES) + f"{sum(total.values()):>8}")
        return lines

    ordered = {m: report.by_mutation[m] for m in MUTATIONS if m in report.by_mutation}
    lines = table("mutation (files)", ordered) + [""] + table("command (runs)", report.by_command)
    lines.append("")
    lines.append(
        f"{report.files} files in {report.wall_time_s:.0f} s, seed {report.seed}, {report.worker_restarts} worker restarts"
        + ("" if report.complete else " (INTERRUPTED)")
    )
    for result in report.bad[:20]:
        lines.append(f"  #{result.index} {result.log} {result.mutation} ({result.description}): {result.outcome}: {result.detail}")
    if len(report.bad) > 20:
        lines.append(f"  ... and {len(report.bad) - 20} more (see the JSON)")
    return "\n".join(lines)
