"""Learning checks: each algorithm solves a small task on a fixed seed within a small budget.

Thresholds come from measured runs (see the README's Tests section); Pendulum-v1's returns go
from about -1300 (random) to about -150 (solved)."""
import pytest

from conftest import load, small_args

# script: (total steps, learning starts, return the final evaluation must beat)
BUDGETS = {"td3": (8000, 1000, -400.0), "oparl": (8000, 1000, -400.0), "sac": (5000, 1000, -400.0)}


@pytest.mark.parametrize("script", sorted(BUDGETS))
def test_learns_pendulum(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    module = load(script)
    total, learning_starts, threshold = BUDGETS[script]
    args = small_args(
        module, env_id="Pendulum-v1", seed=1, total_timesteps=total, learning_starts=learning_starts,
        batch_size=256, eval_frequency=total, eval_episodes=10, run_name="run",
    )
    final_return = module.main(args)["eval_returns"][-1][1]
    assert final_return > threshold
