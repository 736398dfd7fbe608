"""One self-contained file per algorithm means the helpers the scripts share are copies. These tests keep
every copy identical, keep each script in the same order (the algorithm first; below one banner, the
machinery that does not change what is learned) and the repository formatted."""

import ast
import difflib
import importlib.util
import os
import re
import subprocess
import sys

import pytest

from conftest import OFF_POLICY, ON_POLICY, REPO, SCRIPTS, ancestry, base_of

BANNER = "# Machinery. Nothing below changes what the algorithm computes"
# what every script keeps below the banner, where it has it
MACHINERY = {
    "fail", "parse_args", "check_args", "float32_box", "make_env", "start_logging", "bf16_autocast", "NonFiniteError",
    "check_finite", "log_scalars", "stop_non_finite", "CudaGraph", "CHECKPOINT", "RESUMABLE_FLAGS", "snapshot", "restore",
    "rng_state", "set_rng_state", "write_checkpoint", "load_checkpoint", "EpisodeRecord", "log_evaluation", "run_folders",
    "results", "seed_share", "PER_SEED", "split_seeds", "join_seeds", "write_checkpoints", "load_checkpoints", "save_models",
    "restore_generators", "to_device",
}  # fmt: skip
# Definitions that differ between scripts by design, with the groups of scripts whose copies must still agree.
# A script in no group joins the group of its nearest base that is in one (a fork of TD3 keeps TD3's Actor); one
# whose copy differs from its base's by design gets a group of its own here, e.g. {"ddpg"}. An empty list: every
# script has its own (nothing compared). Every definition not named here must be one copy in all scripts.
BY_DESIGN = {
    "Args": [],
    "main": [],
    "check_args": [],
    # TD3's actor is deterministic, SAC's a squashed Gaussian; REDQ is SAC's copy, OPARL TD3's
    "Actor": [{"td3", "oparl"}, {"sac", "redq"}],
    "noisy_action": [{"td3", "oparl"}, {"sac", "redq"}],
    "evaluate": [{"td3", "oparl"}, {"sac", "redq"}, set(ON_POLICY)],
    "update_critic": [{"td3", "oparl"}, {"sac", "redq"}],
    "td_target": [],
    "update_actor": [],
    # `members` exists where an update picks critics (TD3's actor: the first; REDQ's target: a random subset);
    # OPARL's critics are the authors' release's (SiLU, truncated-normal init)
    "QEnsemble": [{"td3", "redq"}, {"sac"}, {"oparl"}],
    # --cudagraphs exists in the off-policy scripts only
    "check_finite": [set(OFF_POLICY), set(ON_POLICY)],
    "stop_non_finite": [set(OFF_POLICY), set(ON_POLICY)],
    "RESUMABLE_FLAGS": [set(OFF_POLICY), set(ON_POLICY)],
    # RND and EBD add a second value head, batch statistics and intrinsic fields to PPO's
    "Agent": [{"rnd", "ebd"}, {"ppo"}],
    "RunningMeanStd": [{"rnd", "ebd"}],
    "ppo_loss": [{"rnd", "ebd"}, {"ppo"}],
    "Rollout": [],
    "update_policy": [],
}


def top_level(script: str) -> dict:
    """{name: source} of the script's top-level classes, functions and assignments, in file order."""
    source = open(os.path.join(REPO, f"{script}_continuous_action.py")).read()
    found = {}
    for node in ast.parse(source).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names = [node.name]
        elif isinstance(node, (ast.Assign, ast.AugAssign)):
            names = [
                t.id for t in (node.targets if isinstance(node, ast.Assign) else [node.target]) if isinstance(t, ast.Name)
            ]
        else:
            continue
        for name in names:
            found[name] = found.get(name, "") + ast.get_source_segment(source, node) + "\n"
    return found


DEFINITIONS = {script: top_level(script) for script in SCRIPTS}
SHARED = sorted({name for defs in DEFINITIONS.values() for name in defs if sum(name in d for d in DEFINITIONS.values()) > 1})


def groups(name: str, holders: set) -> list:
    """The groups of scripts whose copies of `name` must agree: BY_DESIGN's, each script in none of them joining
    the group of its nearest base that is in one; all holders, for a definition BY_DESIGN does not name."""
    if name not in BY_DESIGN:
        return [holders]
    declared = [set(group) for group in BY_DESIGN[name]]
    for script in sorted(holders):
        nearest = next((group for s in ancestry(script) for group in declared if s in group), None)
        if nearest is not None:
            nearest.add(script)
    return declared


@pytest.mark.parametrize("name", SHARED)
def test_shared_definitions_are_identical_copies(name):
    holders = {script for script in SCRIPTS if name in DEFINITIONS[script]}
    for group in groups(name, holders):
        members = [script for script in SCRIPTS if script in group & holders]
        for script in members[1:]:
            first, other = DEFINITIONS[members[0]][name], DEFINITIONS[script][name]
            diff = "".join(difflib.unified_diff(first.splitlines(True), other.splitlines(True), members[0], script))
            assert first == other, (
                f"{name} differs between {members[0]} and {script}: copy the change to both, or, if one differs by "
                f"design, give it a group of its own under {name!r} in BY_DESIGN, tests/test_copies.py:\n{diff}"
            )


def test_every_script_with_a_base_names_it_and_the_roots_are_cleanrls():
    roots = [script for script in SCRIPTS if base_of(script) is None]
    assert set(roots) <= {"td3", "ppo"}, (
        f"{roots}: a script copied from another names it in its header, as `diff td3_continuous_action.py "
        "ddpg_continuous_action.py` (docs/forking.md)"
    )
    assert all(base_of(script) in SCRIPTS for script in SCRIPTS if base_of(script)), "a header names a missing base"


def test_every_difference_by_design_names_a_shared_definition():
    stale = [name for name in BY_DESIGN if name not in SHARED]
    assert not stale, f"BY_DESIGN lists definitions that no two scripts share: {stale}"


@pytest.mark.parametrize("script", SCRIPTS)
def test_algorithm_first_machinery_after_the_banner(script):
    lines = open(os.path.join(REPO, f"{script}_continuous_action.py")).read().splitlines()
    banner = [i for i, line in enumerate(lines) if line.startswith(BANNER)]
    assert len(banner) == 1, f"one banner line starting {BANNER!r}"
    names = list(DEFINITIONS[script])
    above = names[: names.index("main") + 1]
    assert not MACHINERY & set(above), f"machinery above main: {MACHINERY & set(above)}"
    assert set(names[len(above) :]) <= MACHINERY, f"below main but not machinery: {set(names[len(above) :]) - MACHINERY}"
    main_line = next(i for i, line in enumerate(lines) if line.startswith("def main("))
    assert main_line < banner[0], "main comes before the banner"


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed (it is in requirements.txt)")
def test_repository_is_formatted_with_ruff():
    result = subprocess.run([sys.executable, "-m", "ruff", "format", "--check", "."], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, f"run `ruff format .`:\n{result.stdout}{result.stderr}"


def test_the_diff_sizes_in_the_docs_are_the_scripts():
    """docs/baselines.md gives each script's `diff` against its base, the number a reader checks first."""
    if subprocess.run(["diff", "--version"], capture_output=True).returncode != 0:
        pytest.skip("no diff program here")
    table = open(os.path.join(REPO, "docs", "baselines.md")).read()
    rows = re.findall(r"^\| `(\w+)_continuous_action\.py` \| (\w+) \| (\d+) lines \|", table, re.M)
    with_base = {script: base_of(script) for script in SCRIPTS if base_of(script)}
    assert {script: base.lower() for script, base, _ in rows} == with_base, (
        "docs/baselines.md's table has a row `| `{script}_continuous_action.py` | {BASE} | {N} lines | ...` for every "
        f"script with a base: {with_base}"
    )
    for script, base, documented in rows:
        script_path, base_path = (os.path.join(REPO, f"{name.lower()}_continuous_action.py") for name in (script, base))
        diff = subprocess.run(["diff", base_path, script_path], capture_output=True, text=True).stdout
        changed = sum(line.startswith(("<", ">")) for line in diff.splitlines())
        assert changed == int(documented), (
            f"diff {base.lower()} {script}: {changed} lines, docs/baselines.md says {documented}"
        )
