"""List the wrong loop closures of a replay, straight from its .rrd (a scripted post-mortem).

Usage::

    python examples/list_wrong_loops.py kitti_00_alpha_0.50.rrd

For every constraint that the rank-1 hypothesis accepted although the log's labels (or ground
truth) say it is false, it prints the frames it joins, the frame at which it was first accepted and
the frame at which it was dropped again (if ever), read from the ``/events`` text log; then the
true loops that were never accepted. The same facts are what the viewer shows: red segments in the
map (state "accepted but truly false"), WARN lines in the Events panel.
"""

from __future__ import annotations

import re
import sys
from collections import defaultdict
from pathlib import Path

import pyarrow as pa
from rerun.chunk import RrdReader

ACCEPTED = re.compile(r"constraint (\d+) \((\d+)↔(\d+)\) accepted at frame (\d+)")
DROPPED = re.compile(r"constraint (\d+) \((\d+)↔(\d+)\) no longer accepted at frame (\d+)")


def tables(path: Path) -> dict[str, pa.Table]:
    """``{entity path: table}`` of a recording (chunks concatenated)."""
    parts: dict[str, list[pa.Table]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        parts[chunk.entity_path].append(pa.Table.from_batches([chunk.to_record_batch()]))
    return {entity: pa.concat_tables(p, promote_options="permissive") for entity, p in parts.items()}


def col(table: pa.Table, suffix: str) -> list:
    (name,) = [n for n in table.column_names if n.endswith(suffix)]
    return table.column(name).to_pylist()


def main(path: Path) -> int:
    t = tables(path)
    segments = t["/constraints/segments"]
    frames = segments.column("frame").to_pylist()
    last = max(range(len(frames)), key=lambda i: (frames[i] if col(segments, "constraint_id")[i] else -1, i))
    ids = col(segments, "constraint_id")[last]
    states = col(segments, "state")[last]
    q, m = col(segments, "query_frame")[last], col(segments, "match_frame")[last]

    accepted_at: dict[int, list[int]] = defaultdict(list)
    dropped_at: dict[int, list[int]] = defaultdict(list)
    events = t["/events"]
    for frame, text in zip(events.column("frame").to_pylist(), col(events, "TextLog:text")):
        line = text[0] if isinstance(text, list) else text
        if (hit := ACCEPTED.match(line)) is not None:
            accepted_at[int(hit[1])].append(frame)
        elif (hit := DROPPED.match(line)) is not None:
            dropped_at[int(hit[1])].append(frame)

    def history(cid: int) -> str:
        steps = sorted([(f, "accepted") for f in accepted_at[cid]] + [(f, "dropped") for f in dropped_at[cid]])
        return ", ".join(f"{what} at frame {f}" for f, what in steps) or "never accepted"

    print(f"{path}: {len(ids)} constraints at the last step (frame {frames[last]})")
    wrong = [i for i, s in enumerate(states) if s == "accepted but truly false"]
    print(f"\naccepted but truly false: {len(wrong)}")
    for i in wrong:
        print(f"  constraint {ids[i]:4d}  {q[i]:5d} ↔ {m[i]:5d}   {history(ids[i])}")
    transient = sorted(cid for cid in accepted_at if cid in dropped_at)
    print(f"\naccepted for a while, then dropped: {len(transient)}")
    for cid in transient:
        i = ids.index(cid)
        print(f"  constraint {cid:4d}  {q[i]:5d} ↔ {m[i]:5d}   {states[i]:<32s} {history(cid)}")
    missed = [i for i, s in enumerate(states) if s == "rejected but truly true (missed)"]
    print(f"\ntrue loops never accepted at the end: {len(missed)}")
    for i in missed:
        print(f"  constraint {ids[i]:4d}  {q[i]:5d} ↔ {m[i]:5d}   {history(ids[i])}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    sys.exit(main(Path(sys.argv[1])))
