"""Every *_continuous_action.py on disk is covered by the suite. The scripts are found on disk (conftest.SCRIPTS) and
every script-level test runs on each; the few per-script settings that cannot be read from a script are tables
in which a script without an entry is held to its base's entry (docs/forking.md). This test fails, naming the
table, when a script has neither."""

import glob
import os

from conftest import OFF_POLICY, ON_POLICY, REPO, SCRIPTS, ancestry
from test_end_to_end import EXTRA_TAGS
from test_learning import BUDGETS
from test_reliability import KILL_CASES
from test_wiring import WIRING


def entry_holder(table: dict, script: str):
    """The script whose entry in `table` applies to `script`: itself or its nearest base; None if neither has one."""
    return next((s for s in ancestry(script) if s in table), None)


def test_the_suite_finds_every_script_on_disk():
    on_disk = sorted(
        os.path.basename(p).removesuffix("_continuous_action.py") for p in glob.glob(f"{REPO}/*_continuous_action.py")
    )
    assert SCRIPTS == on_disk and sorted(OFF_POLICY + ON_POLICY) == on_disk


def test_every_script_is_covered_by_each_per_script_table():
    tables = [
        (WIRING, "what main wires together: WIRING in tests/test_wiring.py"),
        (BUDGETS, "a learning check: BUDGETS in tests/test_learning.py (None, with the reason, for none)"),
        (EXTRA_TAGS, "the tags it logs beyond the common ones: EXTRA_TAGS in tests/test_end_to_end.py"),
    ]
    uncovered = [
        f"{script}_continuous_action.py needs {what}"
        for script in SCRIPTS
        for table, what in tables
        if entry_holder(table, script) is None
    ]
    assert not uncovered, "; ".join(uncovered) + " (docs/forking.md)"
    for script in SCRIPTS:
        phases = {phase for s, _, phase in KILL_CASES if s == script}
        assert phases == ({"learning", "random"} if script in OFF_POLICY else {"learning"}), script
