"""``lcv-replay bench rosbag``: import speed of a bag, against ``rosbags`` alone on the same messages.

Three runs over the messages of the topics the import uses (side by side, so the ratios hold on a
loaded machine):

* ``rosbags read``: ``AnyReader.messages`` (raw bytes only);
* ``rosbags read + deserialise``: the same, deserialised with the bag's typestore;
* ``record rosbag``: our import end to end (both passes, TF, interpolation, writing the log).

Each is repeated; the first run warms the page cache and is dropped, the medians are reported as
messages per second of wall time and of process CPU time.
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable


@dataclass(frozen=True)
class ImportSpeed:
    """Medians of ``repeats`` runs (the warm-up run excluded); ``messages`` is per run."""

    bag: str
    what: str
    messages: int
    wall_s: float
    cpu_s: float
    messages_per_s: float
    messages_per_cpu_s: float
    relative_to_deserialise: float
    load_average_1min: float


def run_import_benchmark(bag: Path, options: Any, *, repeats: int = 4) -> list[ImportSpeed]:
    """Time the three runs of the module docstring on ``bag`` with the import ``options``."""
    from recorders.bags import open_bag, resolve_source
    from recorders.rosbag import choose_topics, record_rosbag, topic_roles

    source = resolve_source([bag])
    with open_bag(source) as reader:
        topics, plan = choose_topics(reader, source, options)
        wanted = set(topic_roles(plan, topics, options, name=source.name).values())
        if plan.needs_tf:
            wanted |= {t for t, ty in topics.items() if ty in ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")}

    def read(deserialise: bool) -> int:
        with open_bag(source) as reader:
            count = 0
            for connection, _t, raw in reader.messages(connections=[c for c in reader.connections if c.topic in wanted]):
                if deserialise:
                    reader.deserialize(raw, connection.msgtype)
                count += 1
            return count

    def ours() -> int:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "bench.mcap"
            record_rosbag(bag, out, options)
            from lcv_replay.log.reader import open_log

            with open_log(out) as log:
                return int(log.info.recorder_config["messages_read"])

    runs: dict[str, list[tuple[float, float, int]]] = {}
    steps: list[tuple[str, Callable[[], int]]] = [
        ("rosbags read", lambda: read(False)), ("rosbags read + deserialise", lambda: read(True)), ("record rosbag", ours),
    ]
    for _ in range(repeats + 1):
        for name, fn in steps:
            t0, c0 = time.perf_counter(), time.process_time()
            count = fn()
            runs.setdefault(name, []).append((time.perf_counter() - t0, time.process_time() - c0, count))
    load = os.getloadavg()[0]
    medians = {name: (statistics.median(r[0] for r in rows[1:]), statistics.median(r[1] for r in rows[1:]), rows[-1][2])
               for name, rows in runs.items()}
    reference = medians["rosbags read + deserialise"][0]
    return [
        ImportSpeed(str(bag), name, count, wall, cpu, count / wall, count / cpu if cpu > 0 else float("inf"), wall / reference, load)
        for name, (wall, cpu, count) in medians.items()
    ]


def format_results(results: list[ImportSpeed]) -> str:
    header = f"{'run':<28} {'messages':>8} {'wall s':>7} {'cpu s':>6} {'msg/s':>8} {'msg/cpu-s':>9} {'time / deserialise':>18} {'load':>5}"
    lines = [header, "-" * len(header)]
    for r in results:
        lines.append(
            f"{r.what:<28} {r.messages:>8} {r.wall_s:>7.3f} {r.cpu_s:>6.3f} {r.messages_per_s:>8,.0f} {r.messages_per_cpu_s:>9,.0f} "
            f"{r.relative_to_deserialise:>18.2f} {r.load_average_1min:>5.1f}"
        )
    return "\n".join(lines)


def results_to_json(results: list[ImportSpeed]) -> list[dict]:
    return [dataclasses.asdict(r) for r in results]
