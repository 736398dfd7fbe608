"""A function or class that several scripts define (each script keeps its own copy: a fork copies its base) is
tested in every script that defines it, a new fork's copy included: a slip in one copy (a `1 - tau`, a GAE that
flows across an episode's end) fails here, in the fast tier, not only in a learning check."""

import inspect
import re

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn as nn

from conftest import SCRIPTS, load, source
from rl_utils.numerics import NonFiniteError


def copies(name: str, *, like=None) -> list:
    """The scripts that define `name` at the top level; with `like`, only those whose copy takes the parameters of
    script `like`'s copy (a copy with other parameters is another function: its script's own tests cover it)."""
    found = [s for s in SCRIPTS if re.search(rf"^(def|class) {name}\b", source(s), re.M)]
    if like is not None:
        parameters = list(inspect.signature(getattr(load(like), name)).parameters)
        found = [s for s in found if list(inspect.signature(getattr(load(s), name)).parameters) == parameters]
    return found


def test_the_shared_parts_are_found_in_the_scripts_that_share_them():
    """The lists the tests below run over (a regex that found nothing would test nothing)."""
    assert {"td3", "oparl", "sac", "redq"} <= set(copies("soft_update")) and set(copies("optimize")) == set(
        copies("soft_update")
    )
    assert {"ppo", "rnd", "ebd"} <= set(copies("compute_gae")) <= set(copies("RunningMeanStd", like="ppo"))
    assert {"ppo", "rnd", "ebd"} <= set(copies("Normalizer", like="ppo"))
    assert {"td3", "oparl"} <= set(copies("noisy_action", like="td3"))
    assert "sac" not in copies("noisy_action", like="td3")  # SAC's samples its policy: its own test


@pytest.mark.parametrize("script", copies("soft_update"))
def test_soft_update_is_polyak_averaging(script):
    source_nets, target_nets = [nn.Linear(3, 2), nn.Linear(2, 1)], [nn.Linear(3, 2), nn.Linear(2, 1)]
    with torch.no_grad():
        for p in (p for net in source_nets for p in net.parameters()):
            p.fill_(1.0)
        for p in (p for net in target_nets for p in net.parameters()):
            p.fill_(0.0)
    for _ in range(3):
        load(script).soft_update(target_nets, source_nets, tau=0.1)
    for p in (p for net in target_nets for p in net.parameters()):
        torch.testing.assert_close(p, torch.full_like(p, 1 - 0.9**3))
    for p in (p for net in source_nets for p in net.parameters()):
        torch.testing.assert_close(p, torch.ones_like(p))


@pytest.mark.parametrize("script", copies("optimize"))
def test_optimize_steps_on_this_losss_gradient_alone_and_refuses_a_non_finite_loss(script):
    """One step on the gradient of this loss only (the previous step's gradient left in .grad is cleared first), of
    every optimizer given; a NaN or infinite loss stops it before any weight changes."""
    optimize = load(script).optimize
    torch.manual_seed(0)
    first, second, x = nn.Linear(3, 2), nn.Linear(2, 1), torch.randn(16, 3)
    nets = [first, second]
    optimizers = [torch.optim.SGD(net.parameters(), lr=0.1) for net in nets]

    def loss_fn():
        return (second(torch.tanh(first(x))) ** 2).mean()

    optimize(loss_fn(), "a_loss", *optimizers)  # leaves its gradient in .grad
    before = [p.detach().clone() for net in nets for p in net.parameters()]
    loss = loss_fn()
    grads = torch.autograd.grad(loss, [p for net in nets for p in net.parameters()], retain_graph=True)
    optimize(loss, "a_loss", *optimizers)
    for a, g, b in zip(before, grads, (p for net in nets for p in net.parameters())):
        torch.testing.assert_close(b, a - 0.1 * g)
    after = [p.detach().clone() for net in nets for p in net.parameters()]
    for bad in (float("nan"), float("inf")):
        with pytest.raises(NonFiniteError, match="a_loss"):
            optimize(loss_fn() * bad, "a_loss", *optimizers)
        assert all(torch.equal(a, b) for a, b in zip(after, (p for net in nets for p in net.parameters())))


@pytest.mark.parametrize("script", copies("compute_gae"))
def test_gae_against_a_hand_computed_rollout(script):
    rewards, values = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.5, 1.0, 1.5])
    episode_ends = torch.tensor([0.0, 1.0, 0.0])  # the episode ends at step 1; step 2 starts a new one
    advantages, returns = load(script).compute_gae(rewards, values, episode_ends, torch.tensor(2.0), 0.9, 0.8)
    # t=2: 3 + .9*2 - 1.5 = 3.3; t=1: 2 - 1 = 1 (nothing flows back across the end); t=0: 1 + .9*1 - .5 + .9*.8*1 = 2.12
    torch.testing.assert_close(advantages, torch.tensor([2.12, 1.0, 3.3]))
    torch.testing.assert_close(returns, torch.tensor([2.62, 2.0, 4.8]))


@pytest.mark.parametrize("script", copies("RunningMeanStd", like="ppo"))
def test_running_mean_std_matches_numpy(script):
    stats, data = load(script).RunningMeanStd((2,)), np.random.default_rng(1).normal(3.0, 2.0, (500, 2))
    for x in data:
        stats.update(x)
    np.testing.assert_allclose(stats.mean, data.mean(0), rtol=1e-4)
    np.testing.assert_allclose(stats.var, data.var(0), rtol=1e-3)


@pytest.mark.parametrize("script", copies("Normalizer", like="ppo"))
def test_normalizer_matches_gymnasiums_wrappers(script):
    env = gym.make("Pendulum-v1")
    wrapped = gym.wrappers.NormalizeReward(gym.wrappers.NormalizeObservation(gym.make("Pendulum-v1")), gamma=0.99)
    normalizer = load(script).Normalizer(3, gamma=0.99)
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


SPACE = gym.spaces.Box(np.array([-1.0, 0.0], np.float32), np.array([1.0, 4.0], np.float32))


@pytest.mark.parametrize("script", copies("noisy_action", like="td3"))
def test_noisy_action_adds_scaled_gaussian_noise_and_stays_in_bounds(script):
    """TD3's exploration: the deterministic action plus N(0, (exploration_noise * action_scale)^2), clipped to the
    bounds; the actor's action itself is within bounds and centred on them."""
    module = load(script)
    torch.manual_seed(0)
    actor = module.Actor(4, SPACE)
    obs = torch.randn(4)
    with torch.no_grad():
        mean = actor(obs)
        actor.fc_mu.bias.fill_(100.0)  # a saturated actor still acts within the bounds
        assert torch.equal(actor(obs), torch.tensor([1.0, 4.0]))
        actor.fc_mu.bias.fill_(-100.0)
        assert torch.equal(actor(obs), torch.tensor([-1.0, 0.0]))
        actor.fc_mu.weight.zero_(), actor.fc_mu.bias.zero_()  # tanh(0): the middle of the bounds
        mean = actor(obs)
    torch.testing.assert_close(mean, torch.tensor([0.0, 2.0]))
    actions = torch.stack([module.noisy_action(obs, actor, 0.1) for _ in range(4000)])
    torch.testing.assert_close(actions.mean(0), mean, atol=0.02, rtol=0)
    torch.testing.assert_close(actions.std(0), 0.1 * torch.tensor([1.0, 2.0]), atol=0.01, rtol=0)
    wide = torch.stack([module.noisy_action(obs, actor, 5.0) for _ in range(500)])
    assert (wide >= torch.tensor([-1.0, 0.0])).all() and (wide <= torch.tensor([1.0, 4.0])).all()
    assert (wide == torch.tensor([1.0, 4.0])).any()  # clipped, not squashed
