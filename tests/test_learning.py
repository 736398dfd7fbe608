"""Learning checks: each algorithm solves a small task on a fixed seed within a small budget.

Thresholds come from measured runs (see docs/tests.md); Pendulum-v1's returns go
from about -1300 (random) to about -150 (solved). Another CPU trains another run from the same seed (its kernels
round differently and the last bits grow), so a check reads what holds across seeds rather than one run's final
number: the best median episode of the last EVALUATIONS evaluations (one episode that fails to swing up, or one
evaluation caught in a dip, does not fail it; a policy that has not learned fails every one)."""

import numpy as np
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
    "rnd": ("InvertedPendulum-v4", 40000, None, None, 500.0),  # the bonus must not keep PPO from a task it solves
    "ebd": ("InvertedPendulum-v4", 30000, None, None, 500.0),
    # at 20 critic updates per step REDQ's check would take many minutes (see docs/tests.md)
    "redq": None,
}
LEARNING_CHECKED = [s for s in SCRIPTS if declared(BUDGETS, s)]
EVALUATIONS = 3  # the last three: 500 steps apart (the off-policy scripts), a rollout of 2048 apart (the PPO family)


def learning_run(script: str, seed: int, total_timesteps=None, last=None) -> list:
    """A learning check's run (its budget, or total_timesteps), evaluated every 500 steps (a rollout for the PPO
    family): [(step, the 10 episode returns), ...], of the `last` evaluations only if given (the ones before are not
    run: an evaluation re-seeds its envs, so the ones kept are those of a run that made them all). Evaluations draw
    nothing: the training is the same at any frequency. Run from a scratch folder (its runs/ is written there)."""
    module = load(script)
    env_id, total, learning_starts, batch_size, _ = declared(BUDGETS, script)
    total = total_timesteps or total
    quick = (
        {"learning_starts": learning_starts, "batch_size": batch_size, "eval_frequency": 500}
        if learning_starts
        else {"num_steps": 2048, "num_minibatches": 32, "update_epochs": 10, "eval_frequency": 2048}
    )
    args = small_args(
        module, env_id=env_id, seed=seed, total_timesteps=total, eval_episodes=10, run_name=f"run{seed}", **quick
    )
    skipped = len(range(0, total, args.eval_frequency)) + 1 - last if last else 0  # the loop's, then the final one
    evaluations = []
    evaluate = module.evaluate

    def recorded(*a, **k):  # the script's own evaluation, its episodes kept
        if len(evaluations) < skipped:
            evaluations.append(None)
            return np.full((1, args.eval_episodes), np.nan)
        returns = evaluate(*a, **k)
        evaluations.append(returns[0].copy())
        return returns

    module.evaluate = recorded
    try:
        logged = module.main(args)["eval_returns"]
    finally:
        module.evaluate = evaluate
    kept = [(step, returns) for (step, _), returns in zip(logged, evaluations) if returns is not None]
    assert len(logged) == len(evaluations) and len(kept) == len(logged) - skipped
    assert [mean for (_, mean), r in zip(logged, evaluations) if r is not None] == pytest.approx([r.mean() for _, r in kept])
    return kept


def passes(evaluations: list, threshold: float) -> bool:
    return max(float(np.median(returns)) for _, returns in evaluations[-EVALUATIONS:]) > threshold


@pytest.mark.parametrize("script", LEARNING_CHECKED)
def test_learns_a_small_task(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    evaluations = learning_run(script, seed=1, last=EVALUATIONS)
    threshold = declared(BUDGETS, script)[-1]
    medians = [round(float(np.median(returns)), 1) for _, returns in evaluations[-EVALUATIONS:]]
    assert passes(evaluations, threshold), f"the last {EVALUATIONS} evaluations' median episodes {medians} <= {threshold}"


def test_the_check_reads_the_best_median_of_the_last_evaluations():
    learned, dip, episodes_failed = np.full(10, -150.0), np.full(10, -700.0), np.array([-1400.0] * 3 + [-150.0] * 7)
    assert passes([(0, dip), (500, learned), (1000, dip), (1500, dip)], -400.0)
    assert passes([(0, dip), (500, dip), (1000, episodes_failed)], -400.0)  # its mean is -525: three episodes' -1400
    assert not passes([(0, learned), (500, dip), (1000, dip), (1500, dip)], -400.0)  # learned, then lost it
    assert not passes([(0, np.full(10, -1200.0))] * 5, -400.0)
