"""REDQ's defining parts: the random-subset min target, G critic updates per step, the mean-Q actor. The algorithm
functions are written for one seed (main runs them through rl_utils.per_seed); so are these tests."""

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch

import redq_continuous_action as redq
from conftest import small_args
from rl_utils import Batch

OBS_DIM, ACTION_DIM = 3, 2
SPACE = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)


def batch_of(n):
    return Batch(
        torch.randn(n, OBS_DIM),
        torch.rand(n, ACTION_DIM),
        torch.randn(n, OBS_DIM),
        torch.randn(n),
        (torch.rand(n) < 0.2).float(),
    )


def test_target_takes_the_min_over_a_fresh_random_subset_of_members():
    torch.manual_seed(0)
    actor, qf_target = redq.Actor(OBS_DIM, SPACE), redq.QEnsemble(OBS_DIM, ACTION_DIM, num_q=10)
    batch, alpha, args = batch_of(64), torch.tensor(0.1), redq.Args()
    subsets = set()
    for _ in range(60):
        rng = torch.get_rng_state()
        y = redq.td_target(batch, actor, qf_target, alpha, args)
        torch.set_rng_state(rng)  # replay the same draws by hand
        with torch.no_grad():
            next_actions, next_log_pi, _ = actor.get_action(batch.next_observations)
            subset = torch.randperm(10)[:2]
            q = qf_target(batch.next_observations, next_actions)  # all 10 members
        subsets.add(tuple(sorted(subset.tolist())))
        expected = batch.rewards + 0.99 * (1 - batch.terminations) * (q[subset].min(0).values - alpha * next_log_pi)
        torch.testing.assert_close(y, expected)
        assert not torch.allclose(y, batch.rewards + 0.99 * (1 - batch.terminations) * (q.min(0).values - alpha * next_log_pi))
    assert len(subsets) > 25  # many of the 45 pairs appear: the subset is drawn anew each time


def test_each_seed_draws_its_own_subsets_with_several_seeds():
    """Three seeds side by side (--num-seeds 3): critic i of each target ensemble answers i, so a target is the
    smallest index in that update's subset. Each seed's subsets are drawn anew at every update and are its own."""
    from rl_utils import per_seed, stack_seeds

    def networks():
        qf_target = redq.QEnsemble(OBS_DIM, ACTION_DIM, num_q=10)
        with torch.no_grad():
            for i, critic in enumerate(qf_target):
                critic.fc3.weight.zero_(), critic.fc3.bias.fill_(i)
        return redq.Actor(OBS_DIM, SPACE), qf_target

    actor, qf_target = stack_seeds(networks, [1, 2, 3], torch.device("cpu"))
    one = batch_of(64)
    batch = Batch(
        *(
            field.expand(3, *field.shape).clone()
            for field in one._replace(rewards=0 * one.rewards, terminations=0 * one.terminations)
        )
    )
    args, alpha = redq.Args(gamma=1.0), torch.zeros(3)
    smallest = torch.stack([per_seed(redq.td_target)(batch, actor, qf_target, alpha, args) for _ in range(30)])
    assert smallest.shape == (30, 3, 64) and torch.equal(smallest, smallest[..., :1].expand_as(smallest))
    per_seed_draws = smallest[..., 0].T  # [seed, update]
    assert all(len(set(draws.tolist())) > 3 for draws in per_seed_draws)  # anew at every update
    assert not torch.equal(per_seed_draws[0], per_seed_draws[1]) and not torch.equal(per_seed_draws[1], per_seed_draws[2])


def test_actor_ascends_the_mean_of_all_critics():
    torch.manual_seed(0)
    actor, qf = redq.Actor(OBS_DIM, SPACE), redq.QEnsemble(OBS_DIM, ACTION_DIM, num_q=10)
    before = copy.deepcopy(actor)
    optimizer = torch.optim.Adam(actor.parameters(), lr=1e-3)
    batch, alpha = batch_of(128), torch.tensor(0.2)
    rng = torch.get_rng_state()
    qf.requires_grad_(False)  # main's actor step: the critics frozen, the loss, then optimize
    loss = redq.policy_loss(batch, actor, qf, alpha)
    redq.optimize(loss, "actor_loss", optimizer)
    torch.set_rng_state(rng)  # the same sample, from the weights the loss was computed with
    with torch.no_grad():
        pi, log_pi, _ = before.get_action(batch.observations)
        q = qf(batch.observations, pi)
    assert loss.item() == pytest.approx((alpha * log_pi - q.mean(0)).mean().item(), rel=1e-5)
    assert loss.item() != pytest.approx((alpha * log_pi - q.min(0).values).mean().item(), rel=1e-3)
    assert all(p.grad is None for p in qf.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(before.parameters(), actor.parameters()))  # the actor stepped


def test_utd_ratio_critic_updates_and_one_actor_update_per_step(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = redq.main(
        small_args(
            redq,
            env_id="Pendulum-v1",
            total_timesteps=330,
            learning_starts=300,
            utd_ratio=3,
            num_q=4,
            eval_frequency=330,
            run_name="run",
        )
    )
    critic_steps = {int(s["step"]) for s in result["q_optimizer"].state.values()}
    actor_steps = {int(s["step"]) for s in result["actor_optimizer"].state.values()}
    assert critic_steps == {30 * 3} and actor_steps == {30}
    assert len(result["qf"]) == 4


@pytest.mark.parametrize(
    "env_id, flags, expected",
    [
        ("Hopper-v4", {}, -1.0),  # REDQ's release (from MBPO)
        ("Ant-v4", {}, -4.0),
        ("Pendulum-v1", {}, -1.0),  # -|A|, as SAC, where the release has no value
        ("dm_control/cartpole-swingup-v0", {}, -1.0),
        ("Hopper-v4", {"target_entropy": -3.0}, -3.0),  # the flag wins
    ],
)
def test_default_target_entropy_is_the_releases_per_task_value(env_id, flags, expected, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    seen = []
    real_loss = redq.alpha_loss_fn
    monkeypatch.setattr(redq, "alpha_loss_fn", lambda *a: seen.append(a[3]) or real_loss(*a))  # its target_entropy
    redq.main(small_args(redq, env_id=env_id, total_timesteps=70, learning_starts=64, eval_frequency=70, **flags))
    assert seen and set(seen) == {expected}
