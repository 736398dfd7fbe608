"""A single-seed run computes the same numbers as at the commit before the machinery moved into a package
(c7560a2): every logged scalar of a short run of each script, bit for bit (tools/same_numbers.py)."""

import json
import os
import sys

import pytest

from conftest import REPO

sys.path.insert(0, os.path.join(REPO, "tools"))
import same_numbers  # noqa: E402

RECORDED = os.path.join(REPO, "tests", "data", "same_numbers.json")


@pytest.mark.slow
@pytest.mark.parametrize("script", list(same_numbers.RUNS))
def test_a_short_run_logs_the_recorded_numbers(script):
    with open(RECORDED) as f:
        expected = json.load(f)[script]
    assert expected["flags"] == same_numbers.RUNS[script], "the run's flags changed: record the values anew at the old commit"
    assert same_numbers.differences(expected["scalars"], same_numbers.run(script)) == []


def test_the_comparison_finds_a_changed_value_a_missing_tag_and_a_shorter_series():
    recorded = {"losses/qf_loss": [[0, 1.0], [100, 2.0]], "eval/episodic_return": [[0, -1.0]]}
    assert same_numbers.differences(recorded, recorded) == []
    changed = {**recorded, "losses/qf_loss": [[0, 1.0], [100, 2.0000002]]}
    assert same_numbers.differences(recorded, changed) == ["losses/qf_loss: step 100: 2.0, now step 100: 2.0000002"]
    assert same_numbers.differences(recorded, {"losses/qf_loss": recorded["losses/qf_loss"]}) == [
        "eval/episodic_return: only in the recorded run"
    ]
    shorter = {**recorded, "losses/qf_loss": [[0, 1.0]]}
    assert same_numbers.differences(recorded, shorter) == ["losses/qf_loss: 2 values, now 1"]
