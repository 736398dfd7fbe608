"""Every *_continuous_action.py on disk is covered by the suite. The scripts are found on disk (conftest.SCRIPTS) and
every script-level test runs on each; the few per-script settings that cannot be read from a script are tables
in which a script without an entry is held to its base's entry (docs/forking.md). This test fails, naming the
table, when a script has neither."""

from conftest import OFF_POLICY, SCRIPTS, ancestry
from test_end_to_end import EXTRA_TAGS
from test_learning import BUDGETS
from test_reliability import KILL_CASES
from test_wiring import WIRING


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
        if not any(s in table for s in ancestry(script))  # its own entry or its nearest base's
    ]
    assert not uncovered, "; ".join(uncovered) + " (docs/forking.md)"
    for script in SCRIPTS:  # a kill-and-resume case once learning has started; for a replay buffer, one in the random phase
        phases = {kill for s, _, phase in KILL_CASES if s == script for kill in phase.split("+")}
        assert phases & {"learning", "trained"} and ("random" in phases) == (script in OFF_POLICY), (script, phases)
