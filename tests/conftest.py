import dataclasses
import importlib
import os
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
os.environ.setdefault("OMP_NUM_THREADS", "1")

# the algorithm scripts, by short name; every script-level test runs on each of them
SCRIPTS = ["td3", "oparl", "sac"]


def load(short_name: str):
    return importlib.import_module(f"{short_name}_continuous_action")


@pytest.fixture(params=SCRIPTS)
def algo(request):
    return load(request.param)


def small_args(module, **overrides):
    """Args for a short run: few steps, small evaluations."""
    fields = {f.name for f in dataclasses.fields(module.Args)}
    defaults = dict(total_timesteps=600, learning_starts=300, batch_size=64, eval_frequency=300, eval_episodes=1)
    defaults = {k: v for k, v in defaults.items() if k in fields}
    return module.Args(**{**defaults, **overrides})


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
