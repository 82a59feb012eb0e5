"""The recorder registry: every entry imports, and its signature matches what the registry says."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from lcv_replay.errors import RecorderError
from recorders import RECORDERS, get_recorder


@pytest.mark.parametrize("name", sorted(RECORDERS))
def test_registry_entries_load(name: str) -> None:
    info = get_recorder(name)
    record = info.load()
    params = inspect.signature(record).parameters.values()
    positional = [p.name for p in params if p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD]
    keyword = {p.name for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY}
    assert positional[-2:] == ["out_path", "options"] and len(positional) == (3 if info.takes_source else 2)
    assert {"force", "progress", "live"} <= keyword
    options = info.load_options()
    assert dataclasses.is_dataclass(options) and options.__dataclass_params__.frozen
    options()  # the defaults are valid


def test_unknown_recorder_lists_known_names() -> None:
    with pytest.raises(RecorderError, match="unknown recorder 'bagfile'.*euroc, folder, g2o, kitti, ros2, rosbag, synthetic"):
        get_recorder("bagfile")
