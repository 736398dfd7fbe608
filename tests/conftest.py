import dataclasses
import functools
import glob
import importlib
import os
import re
import sys
from typing import Optional

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")  # as tools/same_numbers.py runs its scripts: one fork server serves both
# Tests run scripts side by side (and pytest-xdist one test per core). With more threads than cores, OpenMP's default
# spin at every barrier, waiting for a thread that is not running, made two 2-thread TD3 runs side by side on 2 cores
# take 18 to 118 s where one took 10; waiting passively, 10 s (results/test_suite/side_by_side.sh). The numbers are the
# same either way: this is for OMP_NUM_THREADS > 1.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
import torch  # noqa: E402  (after the thread settings it reads)


def source(script: str) -> str:
    return open(os.path.join(REPO, f"{script}_continuous_action.py")).read()


# the algorithm scripts, by short name, as found on disk: every script-level test runs on each of them, a new
# {name}_continuous_action.py included, with nothing to register (docs/forking.md)
SCRIPTS = sorted(
    os.path.basename(p).removesuffix("_continuous_action.py") for p in glob.glob(f"{REPO}/*_continuous_action.py")
)
OFF_POLICY = [s for s in SCRIPTS if "ReplayBuffer(" in source(s)]  # the scripts with a replay buffer
ON_POLICY = [s for s in SCRIPTS if s not in OFF_POLICY]  # PPO and the exploration methods built on it


@functools.lru_cache(maxsize=None)
def base_of(script: str) -> Optional[str]:
    """The script a script was copied from, as its header (the comment lines it starts with) names it:
    `diff td3_continuous_action.py oparl_continuous_action.py`; None for a script copied from CleanRL (td3, ppo)."""
    lines = source(script).splitlines()
    header = " ".join(
        line.lstrip("# ") for line in lines[: next(i for i, line in enumerate(lines) if not line.startswith("#"))]
    )
    found = re.search(rf"`diff\s+(\w+)_continuous_action\.py\s+{script}_continuous_action\.py`", header)
    return found.group(1) if found and found.group(1) != script else None


def ancestry(script: str) -> list:
    """The script, its base, its base's base, ... (a chain that loops back stops there)."""
    chain = []
    while script is not None and script not in chain:
        chain.append(script)
        script = base_of(script) if script in SCRIPTS else None  # a header may name a script that is not there
    return chain


def declared(table: dict, script: str):
    """A per-script test setting: the script's own entry, else its nearest base's (a fork is tested as its base
    until it declares otherwise), else None."""
    return next((table[s] for s in ancestry(script) if s in table), None)


# what keeps each script's test runs short, beyond fewer steps
SHORT_ROLLOUTS = {"num_steps": 256, "num_minibatches": 4, "update_epochs": 2}
# REDQ: 2 critic updates per step and 4 critics (a random 2 of them in each target) instead of 20 and 10
QUICK = {"redq": {"utd_ratio": 2, "num_q": 4}, **{script: SHORT_ROLLOUTS for script in ON_POLICY}}
# settings that only the off-policy scripts have; dropped for the others
OFF_POLICY_ONLY = {"learning_starts", "batch_size"}


# the tests that need a GPU skip elsewhere (CI has none), saying why
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def script_command(script: str, *flags) -> list:
    return [sys.executable, os.path.join(REPO, f"{script}_continuous_action.py"), *flags]


def critic_lr_flag(script: str) -> str:
    """The flag that sets a script's critic learning rate (e.g. to 1e30, to make a loss non-finite)."""
    fields = {f.name for f in dataclasses.fields(load(script).Args)}
    return "--q-lr" if "q_lr" in fields else "--learning-rate"


def load(short_name: str):
    return importlib.import_module(f"{short_name}_continuous_action")


def parse(module, argv: list):
    """A script's command line as its __main__ parses it: rl_utils' checks and the script's own `check_args`."""
    from rl_utils import parse_args

    return parse_args(module.Args, getattr(module, "check_args", None), argv)


@pytest.fixture(params=SCRIPTS)
def algo(request):
    return load(request.param)


def settings(script: str, values: dict) -> dict:
    """`values` plus the script's QUICK settings, without the off-policy ones a script lacks."""
    fields = {f.name for f in dataclasses.fields(load(script).Args)}
    merged = {**(declared(QUICK, script) or {}), **values}
    return {k: v for k, v in merged.items() if k in fields or k not in OFF_POLICY_ONLY}


def small_args(module, **overrides):
    """Args for a short run: few steps, small evaluations."""
    script = module.__name__.removesuffix("_continuous_action")
    defaults = dict(total_timesteps=600, learning_starts=300, batch_size=64, eval_frequency=300, eval_episodes=1)
    return module.Args(**settings(script, {**defaults, **overrides}))


def cli_flags(script: str, **values) -> list:
    """The same as command-line flags: cli_flags("td3", total_timesteps=10) -> ["--total-timesteps", "10", ...]."""
    flags = []
    for name, value in settings(script, values).items():
        flags += [f"--{name.replace('_', '-')}", str(value)]
    return flags


def assert_ensemble_is_independent_mlps(qf, obs_dim: int, action_dim: int, activation) -> tuple:
    """A QEnsemble of 3 critics against each critic's MLP computed by hand (concat -> fc1 -> fc2 -> fc3); returns (obs,
    actions, Q-values). An edit to one critic's layer changes that critic's values alone."""
    torch.manual_seed(0)
    obs, actions = torch.randn(8, obs_dim), torch.randn(8, action_dim)
    q = qf(obs, actions)
    assert q.shape == (3, 8) and len(qf) == 3
    for k, critic in enumerate(qf):
        x = activation(torch.cat([obs, actions], 1) @ critic.fc1.weight.T + critic.fc1.bias)
        x = activation(x @ critic.fc2.weight.T + critic.fc2.bias)
        torch.testing.assert_close(q[k], (x @ critic.fc3.weight.T + critic.fc3.bias).squeeze(-1))
    assert not torch.equal(qf[0].fc1.weight, qf[1].fc1.weight)  # drawn independently
    with torch.no_grad():
        qf[1].fc2.weight.mul_(2.0)
        changed = qf(obs, actions)
    assert torch.equal(changed[0], q[0]) and torch.equal(changed[2], q[2]) and not torch.equal(changed[1], q[1])
    with torch.no_grad():
        qf[1].fc2.weight.div_(2.0)
    return obs, actions, q


def refusal(script, argv, cwd, monkeypatch):
    """The one-line error with which parsing `argv` in `cwd` stops (what the command line prints on stderr)."""
    monkeypatch.chdir(cwd)
    module = load(script)
    with pytest.raises(SystemExit) as exit_info:
        module.main(parse(module, argv))
    message = str(exit_info.value)
    assert message.startswith("error: ") and "\n" not in message, message
    return message


def scalars(run_dir: str) -> dict:
    """{tag: [(step, value), ...]} of every scalar in a TensorBoard run folder."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def pytest_sessionfinish(session, exitstatus):
    # a checkout with no tests collected is not a failure of the suite
    if exitstatus == pytest.ExitCode.NO_TESTS_COLLECTED:
        session.exitstatus = pytest.ExitCode.OK
