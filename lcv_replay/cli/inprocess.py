"""Run ``lcv-replay`` commands in this process with captured output, as a shell would see them.

:func:`run_cli` is what the fuzz benchmark, the fuzz test and the full-disk tests use to run
hundreds of commands without paying a Python start-up each. ``python -m lcv_replay.cli.inprocess``
is the fuzz benchmark's worker: it reads JSON lists of commands on stdin and answers one JSON list
of :class:`~lcv_replay.bench.fuzz.CliRun` per line.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import sys
import traceback
from dataclasses import asdict
from typing import Sequence

from lcv_replay.bench.fuzz import CliRun

#: The worker's address-space limit: a runaway allocation is a MemoryError, not a machine in swap.
WORKER_MEMORY_LIMIT_BYTES = 12 << 30


def run_cli(args: Sequence[str]) -> CliRun:
    """Run ``lcv-replay ARGS`` in this process with captured stdout/stderr (as a shell would see them).

    The root logger's handlers are swapped for the run, so that the CLI's logging goes to this run's
    stderr (``logging.basicConfig`` binds its stream once per process).
    """
    from lcv_replay.cli import app

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    saved = root.handlers[:]
    root.handlers.clear()
    code, trace = 0, None
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                app(args=list(args), prog_name="lcv-replay", standalone_mode=True)
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except Exception:  # what a user would see as a Python traceback
        code, trace = 1, traceback.format_exc()
    finally:
        for handler in root.handlers:
            with contextlib.suppress(Exception):
                handler.close()
        root.handlers[:] = saved
    return CliRun(tuple(args), code, out.getvalue(), err.getvalue(), trace)


def _worker_main() -> None:
    """``python -m lcv_replay.cli.inprocess``: read JSON command lists on stdin, answer JSON results."""
    with contextlib.suppress(ValueError, OSError):
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (WORKER_MEMORY_LIMIT_BYTES, WORKER_MEMORY_LIMIT_BYTES))
    import lcv_replay.cli  # noqa: F401 - import once, before the first timed file

    reply = sys.stdout
    sys.stdout = sys.stderr  # stray prints must not corrupt the protocol
    reply.write(json.dumps({"ready": True}) + "\n")
    reply.flush()
    for line in sys.stdin:
        request = json.loads(line)
        runs = [run_cli(args) for args in request["commands"]]
        reply.write(json.dumps([asdict(r) for r in runs]) + "\n")
        reply.flush()


if __name__ == "__main__":
    _worker_main()
