"""``retrieval.mode = "paper"`` gives exactly the candidates the paper pipeline gave before issue 15.

The golden (tests/data/retrieval_paper_golden.json) was written by tests/data/make_retrieval_golden.py
on the code before the improved prefilter existed; its inputs make every float exact (see there).
"""

from __future__ import annotations

import json

import pytest

from tests.data import make_retrieval_golden as golden

GOLDEN = json.loads(golden.GOLDEN.read_text())


@pytest.mark.parametrize("case", sorted(GOLDEN))
def test_paper_mode_is_bit_identical_to_the_golden(case):
    config = golden.case_config(case)
    assert config.mode == "paper"
    got = golden.run_case(config, golden.golden_descriptors())
    expected = GOLDEN[case]["queries"]
    assert len(got) == len(expected)
    for g, e in zip(got, expected):
        assert g == e, f"{case}: query {e['query']} differs"
