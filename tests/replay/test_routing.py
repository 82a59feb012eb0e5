"""Routing rules of the replay: constraint source, truth source, time range, replay-local indices."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcv_replay.errors import ConfigError, ReplayError
from lcv_replay.evaluation.truth import TruthSource, choose_truth_source
from lcv_replay.records import Frame, FrameWindow, LoopCandidate, Pose2D
from lcv_replay.replay import DEFAULT_METHOD, ReplayOptions, resolve_constraint_source
from lcv_replay.verification.config import VerificationConfig

LOG = Path("x.mcap")


@pytest.mark.parametrize(
    "requested, images, candidates, expected",
    [
        (None, True, True, "log"),
        (None, True, False, "images"),
        (None, False, True, "log"),
        ("images", True, True, "images"),
        ("both", True, True, "both"),
        ("log", False, True, "log"),
    ],
)
def test_constraint_source(requested, images, candidates, expected):
    assert resolve_constraint_source(requested, has_images=images, has_candidates=candidates, path=LOG) == expected


@pytest.mark.parametrize(
    "requested, images, candidates, message",
    [
        (None, False, False, "neither images nor /loop_candidates"),
        ("images", False, True, "needs images"),
        ("both", True, False, "needs /loop_candidates"),
        ("log", True, False, "use --constraints images"),
    ],
)
def test_constraint_source_refusals(requested, images, candidates, message):
    with pytest.raises(ReplayError, match=message):
        resolve_constraint_source(requested, has_images=images, has_candidates=candidates, path=LOG)


def test_truth_source_rules():
    assert choose_truth_source("log", has_labels=True, has_ground_truth=True) is TruthSource.LABELS
    assert choose_truth_source("images", has_labels=True, has_ground_truth=True) is TruthSource.GROUND_TRUTH
    assert choose_truth_source("both", has_labels=True, has_ground_truth=False) is TruthSource.LABELS
    assert choose_truth_source("images", has_labels=False, has_ground_truth=False) is TruthSource.NONE


def test_rebase_keeps_only_candidates_inside_the_replay():
    window = FrameWindow(100, 200)
    cands = [LoopCandidate(150, 120, 0.5), LoopCandidate(150, 80, 0.9), LoopCandidate(130, 100, 0.1)]
    assert [c.pair for c in window.candidates(cands)] == [(50, 20), (30, 0)]
    assert window.pairs([(150, 120), (150, 50), (130, 100)]) == ((50, 20), (30, 0))
    frame = Frame(index=150, stamp_ns=7, odom=Pose2D(1, 2, 0), candidates=tuple(cands[:2]), true_loops=((150, 120), (150, 50)))
    local = window.frame(frame)
    assert local.index == 50 and [c.pair for c in local.candidates] == [(50, 20)] and local.true_loops == ((50, 20),)
    assert FrameWindow(0, 200).frame(frame) is frame
    np.testing.assert_array_equal(window.rows(np.arange(300)), np.arange(100, 200))
    assert window.frames == 100 and FrameWindow(5, 5).frames == 0


def test_options_resolve_method_and_seed():
    options = ReplayOptions(log_path=LOG, method="gnc", seed=9)
    config = options.resolved_config()
    assert config.verification.method == "gnc" and config.verification.seed == 9 and config.retrieval.seed == 9
    assert ReplayOptions(log_path=LOG).resolved_config().verification.method == DEFAULT_METHOD
    assert DEFAULT_METHOD == VerificationConfig().method  # one constant decides the default


@pytest.mark.parametrize("kwargs, option", [({"rate": 0.0}, "--rate"), ({"start_offset_s": -1.0}, "--start-offset"),
                                            ({"duration_s": 0.0}, "--duration"), ({"constraints": "radar"}, "--constraints")])
def test_options_refuse_bad_values_by_name(kwargs, option):
    with pytest.raises(ConfigError, match=option):
        ReplayOptions(log_path=LOG, **kwargs)
