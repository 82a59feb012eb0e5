"""``lcv-replay bench fleet``: what a batch costs on this machine, and what a cluster would take.

Measured in one run, side by side (the machine is shared; ratios are what hold):

* **the session's parallelism**: the same busy loop in 1, then 2 processes of this session. The
  Linux scheduler shares the CPU fairly between sessions (autogroup), not processes; on a shared
  machine a session may get less than one core whatever it starts, and then no worker count
  goes faster. This probe says how much parallelism the scaling run could get at all;
* **scaling**: the same KITTI g2o logs (``robustslam_kitti`` sequences x alphas, built by the
  g2o recorder and cached like the suite's) through ``batch`` on a fresh embedded cluster of 1
  worker, then 2 workers (``repeats`` rounds, interleaved); speedup of the batch wall time, the
  cores the run actually got (task CPU seconds over wall seconds), and the speedup the per-log CPU
  seconds predict on dedicated cores;
* **Ray's overheads**: cluster start-up and shutdown; a fresh worker's first task; the per-task
  cost of a 1-frame replay through Ray against the same wrapper called in this process; the
  driver's cost per task (no-op tasks);
* **images against the verifier** (optional): a synthetic camera log replayed with a cold and a
  warm descriptor cache, per frame, against the g2o logs' per-frame cost (verification only);
* **the simulation** (:mod:`lcv_replay.fleet.simulate`) of a 1,000-log corpus drawn from the
  measured per-log CPU seconds (what a log costs on a dedicated core) plus Ray's measured
  per-task cost, for 10 to 1,000 workers.
"""

from __future__ import annotations

import logging
import os
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence

SIM_WORKERS = (10, 20, 50, 100, 200, 500, 1000)


def _noop(k: int) -> int:
    return k


_BUSY = "import time; t = time.process_time(); x = 0\nfor i in range({n}): x += i * i\nprint(time.process_time() - t)"


def session_parallelism(iterations: int = 5_000_000) -> dict[str, Any]:
    """Throughput of 2 busy processes of this session over 1 (2.0 on two free cores)."""
    import subprocess
    import sys

    def wall(processes: int) -> float:
        started = time.perf_counter()
        procs = [subprocess.Popen([sys.executable, "-c", _BUSY.format(n=iterations)], stdout=subprocess.PIPE) for _ in range(processes)]
        for proc in procs:
            proc.communicate()
        return time.perf_counter() - started

    one, two = wall(1), wall(2)
    return {"one_process_s": one, "two_processes_s": two, "parallelism": 2 * one / two}


def kitti_logs(data_dir: Path, workdir: Path, sequences: Sequence[str], alphas: Sequence[str]) -> list[Path]:
    """The KITTI g2o logs, built (or reused) the way ``bench suite`` builds its cases."""
    from lcv_replay.bench.suite import build_case_log
    from lcv_replay.bench.suites import robustslam_cases

    return [build_case_log(case, data_dir, workdir).path for case in robustslam_cases(sequences, alphas)]


def _per_log(state) -> list[dict[str, Any]]:
    out = []
    for entry in state.entry_list():
        s = entry.summary or {}
        rrd = state.spec.out_dir(entry.log) / "recording.rrd"
        out.append({
            "name": entry.log.name, "path": str(entry.log.path), "status": entry.status, "task_s": entry.seconds, "cpu_s": entry.cpu_s, "replay_s": s.get("wall_time_s"),
            "setup_s": s.get("setup_time_s"), "frames": s.get("frames"), "log_duration_s": s.get("log_duration_s"),
            "log_bytes": entry.log.path.stat().st_size, "rrd_bytes": rrd.stat().st_size if rrd.exists() else None,
            "false_positives": s.get("false_positives"), "recall": s.get("recall"),
        })
    return out


def measure_scaling(logs: Sequence[Path], options: Any, workers: Sequence[int], repeats: int, base: Path,
                    note: Callable[[str], None]) -> list[dict[str, Any]]:
    """One batch per (round, worker count), each on a fresh embedded cluster."""
    from lcv_replay.fleet.batch import BatchSpec, run_batch
    from lcv_replay.fleet.engine import Cluster, ClusterSpec
    from lcv_replay.fleet.inputs import name_logs

    runs = []
    for rep in range(repeats):
        for w in workers:
            spec = BatchSpec(name_logs(list(logs)), base / f"w{w}-r{rep}", options, resume=False)
            cluster = Cluster(ClusterSpec(workers=w))
            cluster.connect()
            try:
                started = time.perf_counter()
                state = run_batch(spec, cluster)
                wall = time.perf_counter() - started
            finally:
                stopped = time.perf_counter()
                cluster.close()
                shutdown = time.perf_counter() - stopped
            ok = state.count("ok")
            per_log = _per_log(state)
            cores = sum(x["cpu_s"] or 0.0 for x in per_log) / wall
            note(f"workers {w} round {rep + 1}: {ok}/{state.total} ok in {wall:.1f} s (start-up {cluster.startup_s:.1f} s, "
                 f"{cores:.2f} cores busy)")
            runs.append({"workers": w, "round": rep, "wall_s": wall, "startup_s": cluster.startup_s, "shutdown_s": shutdown,
                         "ok": ok, "cores_used": cores, "logs": per_log})
    return runs


def measure_overheads(log: Path, options: Any, base: Path, *, tasks: int, note: Callable[[str], None]) -> dict[str, Any]:
    """Ray's own costs around a 1-frame replay (see the module docstring)."""
    from lcv_replay.fleet.inputs import FleetLog
    from lcv_replay.fleet.task import LogJob

    one_frame = replace(options, log_path=log, duration_s=1e-6, rate=None)
    job = LogJob(FleetLog(log, "one-frame"), base / "overhead" / "one-frame", one_frame, "bench")
    # the in-process replays would print their INFO line each, 20 times over: the figures are the output
    package_logger = logging.getLogger("lcv_replay")
    level = package_logger.level
    package_logger.setLevel(max(level, logging.WARNING))
    try:
        return _measure_overheads(job, tasks=tasks, note=note)
    finally:
        package_logger.setLevel(level)


def _measure_overheads(job: Any, *, tasks: int, note: Callable[[str], None]) -> dict[str, Any]:
    import ray

    from lcv_replay.fleet.engine import Cluster, ClusterSpec
    from lcv_replay.fleet.task import run_log

    outcome = run_log(job)  # warm this process's imports
    if outcome.status != "ok":
        raise RuntimeError(f"the 1-frame replay failed: {outcome.error}")
    cluster = Cluster(ClusterSpec(workers=1))
    cluster.connect()
    try:
        task = cluster.remote(run_log)
        started = time.perf_counter()
        first = ray.get(task.remote(job))
        first_s = time.perf_counter() - started
        local, remote, remote_cpu = [], [], []
        for _ in range(tasks):  # interleaved, so that the machine's load hits both alike
            started = time.perf_counter()
            run_log(job)
            local.append(time.perf_counter() - started)
            started = time.perf_counter()
            remote_cpu.append(ray.get(task.remote(job)).cpu_s)
            remote.append(time.perf_counter() - started)
        noop = cluster.remote(_noop)
        ray.get([noop.remote(k) for k in range(20)])  # workers up
        count = 20 * tasks
        started = time.perf_counter()
        ray.get([noop.remote(k) for k in range(count)])
        noop_s = (time.perf_counter() - started) / count
    finally:
        stopped = time.perf_counter()
        startup = cluster.startup_s
        cluster.close()
        shutdown = time.perf_counter() - stopped
    result = {
        "one_frame_in_process_s": statistics.median(local),
        "one_frame_ray_s": statistics.median(remote),
        "ray_per_task_s": statistics.median(remote) - statistics.median(local),
        "first_task_s": first_s,
        "worker_warmup_s": first_s - statistics.median(remote),
        "worker_warmup_cpu_s": first.cpu_s - statistics.median(remote_cpu),
        "one_frame_cpu_s": statistics.median(remote_cpu),
        "noop_task_s": noop_s,
        "startup_s": startup,
        "shutdown_s": shutdown,
        "tasks": tasks,
    }
    note(f"overheads: start-up {startup:.1f} s, first task {first_s:.2f} s, 1-frame task {result['one_frame_ray_s'] * 1e3:.0f} ms "
         f"via Ray vs {result['one_frame_in_process_s'] * 1e3:.0f} ms in process, no-op {noop_s * 1e3:.2f} ms")
    return result


def measure_images(frames: int, workdir: Path, base: Path, options: Any, note: Callable[[str], None]) -> dict[str, Any]:
    """A synthetic camera log (cached in ``workdir``) replayed in this process with a cold, then a
    warm descriptor cache; seconds per frame of each."""
    from lcv_replay.fileio import make_folder
    from lcv_replay.fleet.inputs import FleetLog
    from lcv_replay.fleet.task import LogJob, run_log
    from recorders.synthetic import SyntheticOptions, record_synthetic

    path = workdir / f"synthetic-{frames}f-320x240.mcap"
    if not path.is_file():
        note(f"recording a {frames}-frame synthetic camera log into {path} (once)")
        make_folder(workdir)
        record_synthetic(path, SyntheticOptions(frames=frames, width_px=320, height_px=240, image_format="jpeg", jpeg_quality=90), force=True)
    runs = {}
    previous = os.environ.get("LCV_CACHE_DIR")
    with tempfile.TemporaryDirectory(prefix="lcv-fleet-cache-") as cache:
        os.environ["LCV_CACHE_DIR"] = cache
        try:
            for which in ("cold", "warm"):
                job = LogJob(FleetLog(path, f"images-{which}"), base / "images" / which, replace(options, log_path=path, rate=None), "bench")
                started = time.perf_counter()
                outcome = run_log(job)
                runs[which] = {"task_s": time.perf_counter() - started, "cpu_s": outcome.cpu_s,
                               "replay_s": (outcome.summary or {}).get("wall_time_s"),
                               "setup_s": (outcome.summary or {}).get("setup_time_s"), "status": outcome.status, "error": outcome.error}
        finally:
            if previous is None:
                os.environ.pop("LCV_CACHE_DIR", None)
            else:
                os.environ["LCV_CACHE_DIR"] = previous
    rrd = base / "images" / "cold" / "recording.rrd"
    result = {"frames": frames, "log_bytes": path.stat().st_size, "rrd_bytes": rrd.stat().st_size if rrd.exists() else None,
              **{f"{k}_{key}": v for k, run in runs.items() for key, v in run.items()}}
    note(f"images: {frames} frames, cold cache {runs['cold']['task_s']:.1f} s ({runs['cold']['cpu_s']:.1f} s CPU), "
         f"warm {runs['warm']['task_s']:.1f} s ({runs['warm']['cpu_s']:.1f} s CPU)")
    return result


def per_log_cpu_s(scaling: list[dict[str, Any]], overheads: dict[str, Any]) -> dict[str, float]:
    """Each log's CPU seconds on a warm worker: the median over the 1-worker rounds, the first task
    of each round (the largest log: ``batch`` submits the largest first) less the worker's warm-up."""
    base = min(r["workers"] for r in scaling)
    samples: dict[str, list[float]] = {}
    for run in (r for r in scaling if r["workers"] == base):
        ok = [x for x in run["logs"] if x["status"] == "ok" and x["cpu_s"] is not None]
        first = max(ok, key=lambda x: x["log_bytes"])["name"] if ok else None
        for x in ok:
            warmup = overheads["worker_warmup_cpu_s"] if x["name"] == first else 0.0
            samples.setdefault(x["name"], []).append(max(x["cpu_s"] - warmup, 0.0))
    return {name: statistics.median(v) for name, v in samples.items()}


def cluster_model(overheads: dict[str, Any], *, storage_gb_s: float, startup_s: float = 0.0):
    """The simulation's model from the measured overheads (a cluster that is already running:
    ``startup_s`` 0; the embedded cluster's start-up is reported apart)."""
    from lcv_replay.fleet.simulate import ClusterModel

    return ClusterModel(startup_s=startup_s, worker_warmup_s=max(overheads["worker_warmup_cpu_s"], 0.0),
                        driver_per_task_s=overheads["noop_task_s"], task_overhead_s=max(overheads["ray_per_task_s"], 0.0),
                        storage_bytes_per_s=storage_gb_s * 1e9)


def simulate_corpus(scaling: list[dict[str, Any]], overheads: dict[str, Any], images: dict[str, Any] | None, *,
                    logs: int, workers: Sequence[int], storage_gb_s: float) -> dict[str, Any]:
    """Predictions for a ``logs``-log corpus drawn from the measured per-log CPU seconds (plus
    Ray's per-task cost), on dedicated cores of a running cluster."""
    import numpy as np

    from lcv_replay.fleet.simulate import corpus, sweep

    cpu = per_log_cpu_s(scaling, overheads)
    model = cluster_model(overheads, storage_gb_s=storage_gb_s)
    first = [r for r in scaling if r["workers"] == min(x["workers"] for x in scaling)][0]
    measured = {x["name"]: x for x in first["logs"] if x["name"] in cpu}
    per_log = [cpu[name] + model.task_overhead_s for name in measured]
    bytes_g2o = float(np.mean([x["log_bytes"] + (x["rrd_bytes"] or 0) for x in measured.values()]))
    out: dict[str, Any] = {
        "model": vars(model), "logs": logs, "storage_gb_s": storage_gb_s,
        "g2o": {"bytes_per_log": bytes_g2o, "per_log_s": per_log,
                "predictions": [p.as_dict() for p in sweep(corpus(per_log, logs), workers, model, bytes_per_log=bytes_g2o, longest_first=True)]},
    }
    if images and images.get("cold_status") == "ok":
        per_frame = images["cold_cpu_s"] / images["frames"]
        bytes_per_frame = (images["log_bytes"] + (images["rrd_bytes"] or 0)) / images["frames"]
        frames = [x["frames"] for x in measured.values()]
        image_s = [f * per_frame + model.task_overhead_s for f in frames]
        mean_bytes = float(np.mean(frames)) * bytes_per_frame
        out["images"] = {"s_per_frame": per_frame, "bytes_per_frame": bytes_per_frame, "per_log_s": image_s, "bytes_per_log": mean_bytes,
                         "predictions": [p.as_dict() for p in sweep(corpus(image_s, logs), workers, model, bytes_per_log=mean_bytes, longest_first=True)]}
    return out


def run(*, data_dir: Path, workdir: Path, out: Path, sequences: Sequence[str], alphas: Sequence[str], workers: Sequence[int],
        repeats: int, image_frames: int, corpus_logs: int, storage_gb_s: float, options: Any,
        note: Callable[[str], None]) -> dict[str, Any]:
    """Every measurement of the module docstring; the JSON document of ``bench fleet``."""
    logs = kitti_logs(data_dir, workdir, sequences, alphas)
    note(f"{len(logs)} KITTI g2o logs ready in {workdir}")
    started = time.perf_counter()
    probe = session_parallelism()
    note(f"this session's parallelism: {probe['parallelism']:.2f} (2 busy processes against 1)")
    scaling = measure_scaling(logs, options, workers, repeats, out, note)
    # the overhead probe replays the smallest log that replayed (a log the replay refuses, e.g.
    # KITTI 07 at alpha 1.00 with no candidate at all, is a failed row of the batch, not a probe)
    replayed = {x["path"] for r in scaling for x in r["logs"] if x["status"] == "ok"}
    if not replayed:
        from lcv_replay.errors import FleetError

        raise FleetError("no log of the benchmark replayed, so Ray's overheads cannot be measured", fix="see the failed rows above")
    smallest = min((p for p in logs if str(p) in replayed), key=lambda p: p.stat().st_size)
    overheads = measure_overheads(smallest, options, out, tasks=20, note=note)
    images = measure_images(image_frames, workdir, out, options, note) if image_frames else None
    walls: dict[int, list[float]] = {}
    for r in scaling:
        walls.setdefault(r["workers"], []).append(r["wall_s"])
    base_w = min(walls)
    from lcv_replay.fleet.simulate import predict

    model = cluster_model(overheads, storage_gb_s=storage_gb_s)
    cpu = sorted(per_log_cpu_s(scaling, overheads).values(), reverse=True)
    dedicated = {w: predict(cpu, base_w, model).wall_s / predict(cpu, w, model).wall_s for w in walls}
    return {
        "logs": [str(p) for p in logs],
        "workers": list(workers),
        "repeats": repeats,
        "session_parallelism": probe,
        "scaling": scaling,
        "speedup": {str(w): statistics.median(walls[base_w]) / statistics.median(v) for w, v in walls.items()},
        "speedup_per_round": {str(w): [a / b for a, b in zip(walls[base_w], v)] for w, v in walls.items()},
        "speedup_predicted_dedicated_cores": {str(w): v for w, v in dedicated.items()},
        "overheads": overheads,
        "images": images,
        "simulation": simulate_corpus(scaling, overheads, images, logs=corpus_logs, workers=SIM_WORKERS, storage_gb_s=storage_gb_s),
        "bench_wall_s": time.perf_counter() - started,
        "load_average": os.getloadavg(),
        "cpus": os.cpu_count(),
    }


def markdown(doc: dict[str, Any]) -> str:
    """The tables of ``bench fleet``."""
    from lcv_replay.fleet.table import fmt

    probe = doc["session_parallelism"]
    lines = ["## Scaling (batch wall time, fresh embedded cluster each, start-up excluded)", "",
             f"This session's parallelism before the runs: {probe['parallelism']:.2f} (the same busy loop in 2 processes "
             f"against 1: {probe['two_processes_s']:.1f} s against {probe['one_process_s']:.1f} s; 2.0 on two free cores).", "",
             "| workers | round | logs ok | wall s | start-up s | sum of replay s | cores busy | speedup |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    base = min(doc["workers"])
    base_walls = {r["round"]: r["wall_s"] for r in doc["scaling"] if r["workers"] == base}
    for r in doc["scaling"]:
        replay = sum(x["replay_s"] or 0 for x in r["logs"])
        lines.append(f"| {r['workers']} | {r['round'] + 1} | {r['ok']} | {r['wall_s']:.1f} | {r['startup_s']:.1f} | {replay:.1f} | "
                     f"{r['cores_used']:.2f} | {base_walls[r['round']] / r['wall_s']:.2f} |")
    lines += ["", "measured speedup (median over rounds): " + ", ".join(f"{w} workers {s:.2f}x" for w, s in doc["speedup"].items()),
              "predicted on dedicated cores from the per-log CPU seconds: "
              + ", ".join(f"{w} workers {s:.2f}x" for w, s in doc["speedup_predicted_dedicated_cores"].items()), ""]
    first = [r for r in doc["scaling"] if r["workers"] == base][0]
    lines += ["## Per-log cost (1 worker, first round)", "", "| log | frames | log s | task s | CPU s | replay s | set-up s | rrd MB | FP | recall |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for x in first["logs"]:
        lines.append(f"| {x['name']} | {x['frames']} | {fmt(x['log_duration_s'], 0)} | {fmt(x['task_s'], 2)} | {fmt(x['cpu_s'], 2)} | "
                     f"{fmt(x['replay_s'], 2)} | {fmt(x['setup_s'], 2)} | {fmt((x['rrd_bytes'] or 0) / 1e6, 2)} | {x['false_positives']} | "
                     f"{fmt(x['recall'], 3)} |")
    o = doc["overheads"]
    lines += ["", "## Ray's overheads", "", "| what | value |", "|---|---:|",
              f"| start the embedded cluster (ray.init) | {o['startup_s']:.2f} s |",
              f"| shut it down | {o['shutdown_s']:.2f} s |",
              f"| first task on a fresh worker (1-frame log) | {o['first_task_s']:.2f} s |",
              f"| worker warm-up (first task minus a warm one) | {o['worker_warmup_s']:.2f} s ({o['worker_warmup_cpu_s']:.2f} s CPU) |",
              f"| 1-frame log, wrapper in this process (median of {o['tasks']}) | {o['one_frame_in_process_s'] * 1e3:.0f} ms |",
              f"| 1-frame log through a Ray task (median of {o['tasks']}) | {o['one_frame_ray_s'] * 1e3:.0f} ms ({o['one_frame_cpu_s'] * 1e3:.0f} ms CPU in the worker) |",
              f"| Ray's per-task cost (difference) | {o['ray_per_task_s'] * 1e3:.0f} ms |",
              f"| no-op task, driver throughput inverse | {o['noop_task_s'] * 1e3:.2f} ms |"]
    im = doc.get("images")
    if im:
        g2o = [x for x in first["logs"] if x["cpu_s"] is not None]
        g2o_frames = sum(x["frames"] or 0 for x in g2o)
        g2o_cpu = sum(x["cpu_s"] for x in g2o)
        lines += ["", "## Images against the verifier (per frame)", "", "| replay | frames | wall s | CPU s | CPU ms/frame |",
                  "|---|---:|---:|---:|---:|",
                  f"| synthetic camera log, cold descriptor cache (CNN) | {im['frames']} | {im['cold_task_s']:.1f} | {im['cold_cpu_s']:.1f} | {1e3 * im['cold_cpu_s'] / im['frames']:.1f} |",
                  f"| same, warm descriptor cache | {im['frames']} | {im['warm_task_s']:.1f} | {im['warm_cpu_s']:.1f} | {1e3 * im['warm_cpu_s'] / im['frames']:.1f} |",
                  f"| KITTI g2o logs, verification only (ilv+, whole task) | {g2o_frames} | {sum(x['task_s'] or 0 for x in g2o):.1f} | {g2o_cpu:.1f} | {1e3 * g2o_cpu / max(g2o_frames, 1):.2f} |"]
    sim = doc["simulation"]
    for key, title in (("g2o", "g2o logs (verification only)"), ("images", "camera logs of the same lengths (cold cache)")):
        if key not in sim:
            continue
        lines += ["", f"## Simulation: {sim['logs']} {title}, dedicated cores, cluster running, shared storage {sim['storage_gb_s']:g} GB/s (assumed)", "",
                  "| workers | wall | speedup | utilisation | bottleneck |", "|---:|---:|---:|---:|---|"]
        for p in sim[key]["predictions"]:
            lines.append(f"| {p['workers']} | {_duration(p['wall_s'])} | {p['speedup']:.0f}x | {p['utilisation']:.0%} | {p['bottleneck']} |")
    lines += ["", f"load average during the bench: {', '.join(f'{x:.1f}' for x in doc['load_average'])} ({doc['cpus']} CPUs)"]
    return "\n".join(lines)


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 120:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.0f} s"
