"""How long a corpus takes on N workers: a list-scheduling model fed with measured costs.

The model of one batch on a cluster with ``W`` task slots:

* the cluster is up after ``startup_s`` (0 for a cluster that is already running);
* the driver submits tasks one after another (the largest logs first, as ``batch`` does), ``driver_per_task_s`` each (Ray's measured per-task
  cost at the driver: submission, scheduling, result), so task ``k`` starts no earlier than
  ``k * driver_per_task_s``;
* a task starts on the slot that frees first; its first task on a fresh worker process pays
  ``worker_warmup_s`` (Python imports); then it takes its measured seconds;
* all logs are read from and all outputs written to shared storage, which moves at most
  ``storage_bytes_per_s`` in all; transfers overlap computation, so storage bounds the run from
  below by ``total bytes / bandwidth``.

The predicted wall time is ``startup_s + max(schedule's makespan, storage bound)``. The bottleneck
is the largest of four lower bounds: compute (sum of task seconds over W), the straggler (the
longest log), the driver (tasks times its per-task cost) and storage. Pure numpy; no Ray.
"""

from __future__ import annotations

import heapq
from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np


@dataclass(frozen=True)
class ClusterModel:
    """Costs of a run (seconds, bytes); the first four are measured by ``bench fleet``.

    Attributes:
        startup_s: starting the cluster (the embedded one; a joined cluster: 0).
        worker_warmup_s: a fresh worker's first task minus a warm one's (imports).
        driver_per_task_s: Ray's cost per task at the driver (no-op tasks, throughput inverse).
        task_overhead_s: Ray's cost per task beyond the replay (a 1-frame log through Ray minus
            in the process); already inside the measured per-log seconds, kept for the record.
        storage_bytes_per_s: aggregate bandwidth of the shared storage (an assumption: a NAS or a
            parallel file system moves 0.5 to 10 GB/s; stated with every prediction).
    """

    startup_s: float
    worker_warmup_s: float
    driver_per_task_s: float
    task_overhead_s: float = 0.0
    storage_bytes_per_s: float = 1e9


@dataclass(frozen=True)
class Prediction:
    """One corpus on one cluster size."""

    workers: int
    logs: int
    wall_s: float
    speedup: float  # over the same model with one worker
    utilisation: float  # busy slot-seconds over workers x makespan
    compute_bound_s: float
    straggler_bound_s: float
    driver_bound_s: float
    storage_bound_s: float
    bottleneck: str

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def makespan(task_s: Sequence[float], workers: int, model: ClusterModel) -> tuple[float, float]:
    """``(makespan_s, busy_s)`` of list scheduling in the given order (see the module docstring)."""
    if workers < 1:
        raise ValueError("workers must be >= 1")
    free: list[tuple[float, int, bool]] = [(0.0, slot, False) for slot in range(workers)]  # (free at, slot, warm)
    heapq.heapify(free)
    end = busy = 0.0
    for k, seconds in enumerate(task_s):
        at, slot, warm = heapq.heappop(free)
        start = max(at, k * model.driver_per_task_s)
        duration = float(seconds) + (0.0 if warm else model.worker_warmup_s)
        busy += duration
        end = max(end, start + duration)
        heapq.heappush(free, (start + duration, slot, True))
    return end, busy


def predict(task_s: Sequence[float], workers: int, model: ClusterModel, *, bytes_per_log: float = 0.0) -> Prediction:
    """Predicted wall time of the corpus ``task_s`` (seconds per log, in submission order)."""
    task_s = np.asarray(task_s, dtype=float)
    span, busy = makespan(task_s, workers, model)
    single, _ = makespan(task_s, 1, model)
    storage = len(task_s) * bytes_per_log / model.storage_bytes_per_s
    bounds = {
        "compute": float(task_s.sum()) / workers,
        "straggler": float(task_s.max()) + model.worker_warmup_s if len(task_s) else 0.0,
        "driver": len(task_s) * model.driver_per_task_s,
        "storage": storage,
    }
    labels = {
        "compute": "compute: every worker busy",
        "straggler": f"the longest log ({task_s.max():.0f} s) runs alone at the end",
        "driver": f"the driver: {len(task_s)} tasks x {model.driver_per_task_s * 1e3:.1f} ms",
        "storage": f"shared storage: {len(task_s) * bytes_per_log / 1e9:.1f} GB at {model.storage_bytes_per_s / 1e9:g} GB/s",
    }
    wall = model.startup_s + max(span, storage)
    return Prediction(
        workers=workers, logs=len(task_s), wall_s=wall,
        speedup=(model.startup_s + max(single, storage)) / wall,
        utilisation=busy / (workers * span) if span > 0 else 0.0,
        compute_bound_s=bounds["compute"], straggler_bound_s=bounds["straggler"],
        driver_bound_s=bounds["driver"], storage_bound_s=bounds["storage"],
        bottleneck=labels[max(bounds, key=bounds.get)],
    )


def corpus(measured_s: Sequence[float], logs: int, *, seed: int = 0) -> np.ndarray:
    """A corpus of ``logs`` per-log seconds drawn with replacement from the measured ones (seeded)."""
    measured = np.asarray(measured_s, dtype=float)
    if measured.size == 0:
        raise ValueError("no measured per-log times")
    return np.random.default_rng(seed).choice(measured, size=logs, replace=True)


def sweep(task_s: Sequence[float], workers: Sequence[int], model: ClusterModel, *, bytes_per_log: float = 0.0,
          longest_first: bool = False) -> list[Prediction]:
    """:func:`predict` for each cluster size; ``longest_first`` submits the longest logs first (LPT)."""
    order = np.sort(np.asarray(task_s, dtype=float))[::-1] if longest_first else np.asarray(task_s, dtype=float)
    return [predict(order, w, model, bytes_per_log=bytes_per_log) for w in workers]
