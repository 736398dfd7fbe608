import dataclasses
import importlib
import os
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
os.environ.setdefault("OMP_NUM_THREADS", "1")
import torch  # noqa: E402  (after the thread setting it reads)

# the algorithm scripts, by short name; every script-level test runs on each of them
SCRIPTS = ["td3", "oparl", "sac", "redq", "ppo", "rnd", "ebd"]
OFF_POLICY = ["td3", "oparl", "sac", "redq"]  # the scripts with a replay buffer
ON_POLICY = ["ppo", "rnd", "ebd"]  # PPO and the exploration methods built on it
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
    return "--q-lr" if script in ("sac", "redq") else "--learning-rate"


def load(short_name: str):
    return importlib.import_module(f"{short_name}_continuous_action")


@pytest.fixture(params=SCRIPTS)
def algo(request):
    return load(request.param)


def settings(script: str, values: dict) -> dict:
    """`values` plus the script's QUICK settings, without the off-policy ones a script lacks."""
    fields = {f.name for f in dataclasses.fields(load(script).Args)}
    merged = {**QUICK.get(script, {}), **values}
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
