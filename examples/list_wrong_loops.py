"""List the wrong loop closures of a replay from its recording (a scripted post-mortem).

Usage::

    python examples/list_wrong_loops.py kitti00_ilv.rrd

It reads the run record the replay stored in the recording (``lcv_replay.report.rrd``: the fate of
every constraint, as ``--export DIR`` writes it to ``loops.csv``) and prints the constraints the
final estimate accepted although the log's labels (or ground truth) say they are false, the ones
accepted for a while and then dropped, and the true loops that were not accepted. The viewer shows
the same facts: red segments on the map, ``WRONG`` rows in the Events table.
"""

from __future__ import annotations

import sys
from pathlib import Path

from lcv_replay.errors import LcvError
from lcv_replay.report.rrd import read_run_record


def _history(loop) -> str:
    parts = []
    if loop.first_accepted_frame is not None:
        parts.append(f"first accepted at frame {loop.first_accepted_frame}")
    if loop.dropped_frame is not None:
        parts.append(f"last dropped at frame {loop.dropped_frame}")
    return ", ".join(parts) or "never accepted"


def main(path: Path) -> int:
    try:
        record = read_run_record(path)
    except LcvError as exc:
        print(f"error: {exc.format()}", file=sys.stderr)
        return 2
    print(f"{path}: {record.method} on {Path(record.log).name}, {len(record.loops)} constraints, truth from {record.truth_source}")
    groups = (
        ("accepted but truly false", [l for l in record.loops if l.wrong]),
        ("accepted for a while, then dropped", [l for l in record.loops if l.dropped_frame is not None]),
        ("true loops not accepted at the end", [l for l in record.loops if l.missed]),
    )
    for title, loops in groups:
        print(f"\n{title}: {len(loops)}")
        for l in loops:
            d2 = "" if l.d2 is None else f"d² {l.d2:10.4g}"
            print(f"  constraint {l.constraint_id:4d}  {l.query_frame:5d} ↔ {l.match_frame:5d}  {l.state:<9s} {d2}  {_history(l)}")
    first = record.first_wrong_acceptance()
    if first is not None:
        print(f"\nfirst wrong acceptance at frame {first.first_accepted_frame}: lcv-replay open {path} --frame {first.first_accepted_frame}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    sys.exit(main(Path(sys.argv[1])))
