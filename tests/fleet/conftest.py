"""Fleet fixtures: one local Ray (2 CPUs) for the whole session, small g2o logs, a corrupt one.

Every fleet test that needs Ray takes ``ray_cluster``; the batch and suite code see that Ray is
already connected and use it (and leave it running), so the start-up (~5-10 s) is paid once.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.replay.helpers import FAST_CONFIG_TOML, record_square_route, write_config


@pytest.fixture(scope="session")
def ray_cluster():
    """A local Ray with 2 CPUs, shut down at the end of the session."""
    pytest.importorskip("ray")
    from lcv_replay.fleet.engine import Cluster, ClusterSpec

    cluster = Cluster(ClusterSpec(workers=2))
    cluster.connect()
    try:
        yield cluster
    finally:
        cluster.close()


@dataclass(frozen=True)
class FleetLogs:
    folder: Path  # holds the logs (in sub-folders) and corrupt.mcap
    logs: tuple[Path, ...]  # the three good logs
    corrupt: Path
    config: Path  # a fast verifier config


@pytest.fixture(scope="session")
def fleet_logs(tmp_path_factory) -> FleetLogs:
    """Three small square-route logs (200 frames, labels and ground truth) and one corrupt file."""
    folder = tmp_path_factory.mktemp("fleet_logs")
    logs = []
    for seed in range(3):
        log, _ = record_square_route(folder / f"route{seed}", laps=2, side_poses=25, seed=seed, name=f"route{seed}.mcap")
        logs.append(log)
    corrupt = folder / "corrupt.mcap"
    corrupt.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 8)  # the magic, then garbage
    return FleetLogs(folder, tuple(logs), corrupt, write_config(folder / "fast.toml", FAST_CONFIG_TOML))
