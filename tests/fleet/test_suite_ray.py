"""`bench suite` on Ray: the same rows as serial apart from the time fields, in the same order."""

from __future__ import annotations

from lcv_replay.bench.suite import run_suite, summarise
from lcv_replay.bench.suites import load_suite_file
from lcv_replay.config import load_config
from lcv_replay.fleet.suite import TIME_FIELDS, on_cluster
from tests.replay.helpers import square_route_g2o


def _without_time(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in TIME_FIELDS}


def test_suite_on_ray_equals_serial(ray_cluster, fleet_logs, tmp_path):
    cases = []
    for seed in (0, 1):
        route = square_route_g2o(tmp_path / f"src{seed}", laps=2, side_poses=25, seed=seed)
        cases.append(f'[[case]]\nname = "square{seed}"\ngraph = "{route.graph}"\nground_truth = "{route.ground_truth}"\n'
                     f'true_loops = "{route.true_loops}"\n')
    suite_file = tmp_path / "mini.toml"
    suite_file.write_text('methods = ["ilv+", "gnc", "oracle"]\n' + "\n".join(cases), encoding="utf-8")
    suite = load_suite_file(suite_file)
    config = load_config(fleet_logs.config).verification
    kwargs = dict(data_dir=tmp_path, workdir=tmp_path / "work", config=config)
    serial = run_suite(suite, **kwargs)
    on_ray = run_suite(suite, distribute=on_cluster(ray_cluster), **kwargs)
    assert [(r.case, r.method) for r in on_ray.rows] == [(r.case, r.method) for r in serial.rows]
    assert len(serial.rows) == 6 and all(r.row is not None for r in on_ray.rows)
    assert [_without_time(r.as_dict()) for r in on_ray.rows] == [_without_time(r.as_dict()) for r in serial.rows]
    times = ("total_time_s", "median_time_s")
    strip = lambda s: {k: v for k, v in vars(s).items() if k not in times}  # noqa: E731
    assert [strip(s) for s in summarise(on_ray.rows, on_ray.methods)] == [strip(s) for s in summarise(serial.rows, serial.methods)]
