"""The wall-time model of docs/fleet.md: list scheduling, warm-up, driver and storage bounds."""

from __future__ import annotations

import numpy as np
import pytest

from lcv_replay.fleet.simulate import ClusterModel, corpus, makespan, predict, sweep

FREE = ClusterModel(startup_s=0.0, worker_warmup_s=0.0, driver_per_task_s=0.0)


def test_makespan_of_list_scheduling():
    assert makespan([3, 3, 2, 2, 2], 2, FREE) == (pytest.approx(7.0), pytest.approx(12.0))
    assert makespan([5, 1, 1, 1], 4, FREE)[0] == pytest.approx(5.0)  # the longest log alone at the end
    assert makespan([1.0] * 10, 1, FREE)[0] == pytest.approx(10.0)


def test_warmup_once_per_worker_and_driver_pacing():
    model = ClusterModel(startup_s=0.0, worker_warmup_s=2.0, driver_per_task_s=0.0)
    assert makespan([1.0] * 4, 2, model)[0] == pytest.approx(2.0 + 2 * 1.0)
    paced = ClusterModel(startup_s=0.0, worker_warmup_s=0.0, driver_per_task_s=1.0)
    assert makespan([0.1] * 5, 100, paced)[0] == pytest.approx(4.1)  # the 5th task is submitted at 4 s


def test_predictions_name_their_bottleneck():
    tasks = np.full(1000, 10.0)
    tasks[0] = 400.0
    model = ClusterModel(startup_s=5.0, worker_warmup_s=1.0, driver_per_task_s=0.001, storage_bytes_per_s=1e9)
    few, many = sweep(tasks, [10, 1000], model, longest_first=True)
    assert few.bottleneck.startswith("compute") and few.utilisation > 0.95
    assert "longest log" in many.bottleneck and many.wall_s == pytest.approx(5.0 + 1.0 + 400.0)
    assert few.speedup == pytest.approx((5.0 + 1.0 + tasks.sum()) / few.wall_s)
    io = predict(tasks, 1000, model, bytes_per_log=2e9)  # 2 TB through 1 GB/s
    assert io.bottleneck.startswith("shared storage") and io.wall_s == pytest.approx(5.0 + 2000.0)


def test_corpus_draws_from_the_measured_times():
    drawn = corpus([1.0, 2.0, 3.0], 500, seed=1)
    assert len(drawn) == 500 and set(np.unique(drawn)) == {1.0, 2.0, 3.0}
    assert np.array_equal(drawn, corpus([1.0, 2.0, 3.0], 500, seed=1))
