"""A single-seed run computes the same numbers as at the reference commit (tests/data/same_numbers_reference.txt):
every logged scalar of a short run of each script, bit for bit, both commits' scripts run here and now
(tools/same_numbers.py). Values recorded on another CPU would differ in their last bits, so none are kept."""

import os
import sys
import types

import pytest

from conftest import REPO
import forkserver

sys.path.insert(0, os.path.join(REPO, "tools"))
import same_numbers  # noqa: E402


@pytest.fixture(scope="module")
def reference_dir(tmp_path_factory):
    """The reference commit's Python files, from this clone's history; the tests skip, saying why, without it."""
    commit = same_numbers.reference_commit()
    try:
        return same_numbers.checkout(commit, str(tmp_path_factory.mktemp("reference")))
    except same_numbers.NoReference as e:
        pytest.skip(f"the reference commit's scripts are not here: {e}")


@pytest.mark.slow
@pytest.mark.parametrize("script", list(same_numbers.RUNS))
def test_a_short_run_logs_what_the_reference_commit_logs(script, reference_dir, monkeypatch):
    # both commits' runs forked from the tests' fork server (tests/forkserver.py): the same interpreter state for both
    monkeypatch.setattr(same_numbers, "subprocess", types.SimpleNamespace(run=forkserver.run))
    assert same_numbers.compare(script, reference_dir) == []


def test_the_comparison_finds_a_changed_value_a_missing_tag_and_a_shorter_series():
    reference = {"losses/qf_loss": [[0, 1.0], [100, 2.0]], "eval/episodic_return": [[0, -1.0]]}
    assert same_numbers.differences(reference, reference) == []
    changed = {**reference, "losses/qf_loss": [[0, 1.0], [100, 2.0000002]]}
    assert same_numbers.differences(reference, changed) == ["losses/qf_loss: step 100: 2.0, now step 100: 2.0000002"]
    assert same_numbers.differences(reference, {"losses/qf_loss": reference["losses/qf_loss"]}) == [
        "eval/episodic_return: only in the reference run"
    ]
    shorter = {**reference, "losses/qf_loss": [[0, 1.0]]}
    assert same_numbers.differences(reference, shorter) == ["losses/qf_loss: 2 values, now 1"]


def test_the_reference_is_a_commit_of_this_clone_and_a_missing_one_is_said_in_one_line(tmp_path):
    """The reference file names a commit (the tests skip, not pass, where the clone lacks it); a commit that is not
    in the clone is refused with the way to fetch it, and a folder is taken as it is."""
    commit = same_numbers.reference_commit()
    assert len(commit) == 40 and int(commit, 16) >= 0
    with pytest.raises(same_numbers.NoReference, match="no such commit in this clone .*git fetch --unshallow"):
        same_numbers.checkout("0" * 40, str(tmp_path))
    assert same_numbers.checkout(str(tmp_path), "unused") == str(tmp_path)
    result = same_numbers.subprocess.run(
        [sys.executable, os.path.join(REPO, "tools", "same_numbers.py"), "--against", "0" * 40, "--scripts", "td3"],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 1 and result.stderr.strip().count("\n") == 0
    assert result.stderr.startswith(f"error: {'0' * 40}: no such commit in this clone")
