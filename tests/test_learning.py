"""Learning checks: each algorithm solves a small task on a fixed seed within a small budget.

Thresholds come from measured runs (see docs/tests.md); Pendulum-v1's returns go
from about -1300 (random) to about -150 (solved)."""

import pytest

from conftest import SCRIPTS, declared, load, small_args

pytestmark = pytest.mark.slow  # every test here trains or sweeps

# script: (env, total steps, learning starts, batch size, return the final evaluation must beat). A script without
# an entry is held to its base's budget (a fork of TD3 to TD3's) until it declares its own here. The off-policy
# batches are below the default 256 to keep the checks short; TD3 at 64 missed the threshold on seed 2 over 7000 steps.
# TD3's 8000 steps leave its seed 1 three evaluations past the crossing on both kernel paths measured (docs/tests.md).
BUDGETS = {
    "td3": ("Pendulum-v1", 8000, 1000, 128, -400.0),
    "oparl": ("Pendulum-v1", 7000, 1000, 64, -400.0),
    "sac": ("Pendulum-v1", 5000, 1000, 128, -400.0),
    "ppo": ("InvertedPendulum-v4", 30000, None, None, 500.0),  # PPO's default rollouts of 2048 steps; 1000 is solved
    "rnd": ("InvertedPendulum-v4", 30000, None, None, 500.0),  # the bonus must not keep PPO from a task it solves
    "ebd": ("InvertedPendulum-v4", 30000, None, None, 500.0),
    # at 20 critic updates per step REDQ's check would take many minutes (see docs/tests.md)
    "redq": None,
}
LEARNING_CHECKED = [s for s in SCRIPTS if declared(BUDGETS, s)]


@pytest.mark.parametrize("script", LEARNING_CHECKED)
def test_learns_a_small_task(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    module = load(script)
    env_id, total, learning_starts, batch_size, threshold = declared(BUDGETS, script)
    quick = (
        {"learning_starts": learning_starts, "batch_size": batch_size}
        if learning_starts
        else {"num_steps": 2048, "num_minibatches": 32, "update_epochs": 10}
    )
    args = small_args(
        module, env_id=env_id, seed=1, total_timesteps=total, eval_frequency=total, eval_episodes=10, run_name="run", **quick
    )
    final_return = module.main(args)["eval_returns"][-1][1]
    assert final_return > threshold
