"""PPO's defining parts: GAE, the clipped objective, CleanRL's normalisation, deterministic evaluation."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

import ppo_continuous_action as ppo
from conftest import small_args


def test_gae_against_a_hand_computed_rollout():
    rewards, values = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.5, 1.0, 1.5])
    episode_ends = torch.tensor([0.0, 1.0, 0.0])  # the episode ends at step 1; step 2 starts a new one
    advantages, returns = ppo.compute_gae(rewards, values, episode_ends, torch.tensor(2.0), gamma=0.9, gae_lambda=0.8)
    # t=2: 3 + .9*2 - 1.5 = 3.3; t=1: 2 - 1 = 1 (nothing flows back across the end); t=0: 1 + .9*1 - .5 + .9*.8*1 = 2.12
    torch.testing.assert_close(advantages, torch.tensor([2.12, 1.0, 3.3]))
    torch.testing.assert_close(returns, torch.tensor([2.62, 2.0, 4.8]))


def test_clipped_objective_and_clipped_value_loss_by_hand():
    torch.manual_seed(0)
    agent = ppo.Agent(3, 1)
    obs, actions = torch.randn(4, 3), torch.randn(4, 1)
    with torch.no_grad():
        _, logprob, _, value = agent.get_action_and_value(obs, actions)
    ratios = torch.tensor([1.5, 0.5, 1.1, 1.5])
    advantages = torch.tensor([2.0, -2.0, 1.0, -1.0])
    old_values = value + torch.tensor([0.5, -0.5, 0.0, 0.1])
    returns = value + torch.tensor([1.0, 1.0, -1.0, 0.0])
    args = ppo.Args(norm_adv=False, clip_coef=0.2, ent_coef=0.0, vf_coef=0.5)
    loss, stats = ppo.ppo_loss(agent, obs, actions, logprob - ratios.log(), advantages, returns, old_values, args)
    # pessimistic surrogate: max(-A r, -A clip(r, .8, 1.2)): -2.4, 1.6, -1.1, 1.5
    assert stats["policy_loss"].item() == pytest.approx(np.mean([-2.4, 1.6, -1.1, 1.5]), rel=1e-5)
    # value: new - return = -1, -1, 1, 0; old + clip(new - old, +-.2) - return = -.7, -1.3, 1, 0; the larger square
    assert stats["value_loss"].item() == pytest.approx(0.5 * np.mean([1.0, 1.69, 1.0, 0.0]), rel=1e-5)
    assert stats["clipfrac"].item() == pytest.approx(0.75)
    assert loss.item() == pytest.approx(stats["policy_loss"].item() + 0.5 * stats["value_loss"].item(), rel=1e-5)


def test_normalizer_matches_gymnasiums_wrappers():
    env = gym.make("Pendulum-v1")
    wrapped = gym.wrappers.NormalizeReward(gym.wrappers.NormalizeObservation(gym.make("Pendulum-v1")), gamma=0.99)
    normalizer = ppo.Normalizer(3, gamma=0.99)
    obs, _ = env.reset(seed=0)
    wrapped_obs, _ = wrapped.reset(seed=0)
    np.testing.assert_allclose(normalizer.observation(obs), wrapped_obs, rtol=1e-5, atol=1e-6)
    rng = np.random.default_rng(0)
    for _ in range(300):
        action = rng.uniform(-2, 2, 1).astype(np.float32)
        obs, reward, terminated, truncated, _ = env.step(action)
        wrapped_obs, wrapped_reward, *_ = wrapped.step(action)
        np.testing.assert_allclose(normalizer.observation(obs), np.clip(wrapped_obs, -10, 10), rtol=1e-5, atol=1e-5)
        assert normalizer.reward(reward, terminated) == pytest.approx(float(np.clip(wrapped_reward, -10, 10)), rel=1e-5)
        if terminated or truncated:
            obs, _ = env.reset()
            wrapped.reset()
            normalizer.observation(obs)


def test_running_mean_std_matches_numpy():
    stats, data = ppo.RunningMeanStd((2,)), np.random.default_rng(1).normal(3.0, 2.0, (500, 2))
    for x in data:
        stats.update(x)
    np.testing.assert_allclose(stats.mean, data.mean(0), rtol=1e-4)
    np.testing.assert_allclose(stats.var, data.var(0), rtol=1e-3)


def test_evaluation_is_deterministic_and_leaves_the_statistics_alone(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = ppo.main(
        small_args(ppo, env_id="Pendulum-v1", total_timesteps=600, eval_frequency=600, eval_episodes=2, run_name="run")
    )
    agent, normalizer, env = result["agent"], result["normalizer"], ppo.make_env("Pendulum-v1", seed=101)
    mean_before, count_before = normalizer.obs_rms.mean.copy(), normalizer.obs_rms.count
    first = ppo.evaluate(agent, normalizer, env, 2, seed=101)
    second = ppo.evaluate(agent, normalizer, env, 2, seed=101)
    np.testing.assert_array_equal(first, second)
    assert first.mean() == pytest.approx(result["eval_returns"][-1][1])
    np.testing.assert_array_equal(normalizer.obs_rms.mean, mean_before)
    assert normalizer.obs_rms.count == count_before


def test_learning_rate_anneals_to_zero_over_the_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = ppo.main(small_args(ppo, env_id="Pendulum-v1", total_timesteps=1024, eval_frequency=1024, run_name="run"))
    # 4 rollouts of 256: the last is trained at lr * (1 - 3/4)
    assert result["optimizer"].param_groups[0]["lr"] == pytest.approx(3e-4 / 4)
    assert math.isclose(ppo.Args().learning_rate, 3e-4)


def test_a_collapsed_std_reaches_the_nan_guard_as_a_non_finite_loss():
    # after a huge step the std can be exactly 0; that must become a non-finite loss (reported in one line
    # by the guard), not an exception from the distribution's argument checks
    torch.manual_seed(0)
    agent = ppo.Agent(3, 1)
    with torch.no_grad():
        agent.actor_logstd.fill_(-1e30)
    obs, actions = torch.randn(8, 3), torch.randn(8, 1)
    loss, _ = ppo.ppo_loss(agent, obs, actions, torch.zeros(8), torch.randn(8), torch.randn(8), torch.randn(8), ppo.Args())
    assert not torch.isfinite(loss)
