"""PPO's defining parts: GAE, the clipped objective under each of its switches, the update's early stop and
gradient clipping, CleanRL's normalisation, deterministic evaluation. The loss and update tests run on RND's and
EBD's copies too (their PPO part is PPO's; test_exploration.py tests what they add)."""

import math

import numpy as np
import pytest
import torch

import ebd_continuous_action as ebd
import ppo_continuous_action as ppo
import rl_utils
import rnd_continuous_action as rnd
from conftest import small_args

FAMILY = [ppo, rnd, ebd]  # the scripts with PPO's ppo_loss and update_policy
FAMILY_IDS = ["ppo", "rnd", "ebd"]


# ---- ppo_loss, switch by switch ---------------------------------------------------------------------


def minibatch(module, ratios, action_dim=1, logstd=None):
    """An agent and a minibatch of len(ratios) whose old log-probabilities put the new/old probability ratios at
    `ratios`; returns (agent, obs, actions, old_logprobs, values)."""
    torch.manual_seed(0)
    agent = module.Agent(3, action_dim)
    if logstd is not None:
        with torch.no_grad():
            agent.actor_logstd.copy_(torch.tensor(logstd))
    obs, actions = torch.randn(len(ratios), 3), torch.randn(len(ratios), action_dim)
    with torch.no_grad():
        _, logprob, _, value = agent.get_action_and_value(obs, actions)[:4]
    return agent, obs, actions, logprob - ratios.log(), value


def loss_of(module, agent, obs, actions, old_logprobs, advantages, returns, old_values, args):
    """module's ppo_loss; RND's and EBD's intrinsic head is given its own value as its return, so that it adds
    nothing and the hand computations are PPO's."""
    if module is ppo:
        return ppo.ppo_loss(agent, obs, actions, old_logprobs, advantages, returns, old_values, args)
    with torch.no_grad():
        int_values = agent.get_value(obs)[1]
    return module.ppo_loss(agent, obs, actions, old_logprobs, advantages, returns, old_values, int_values, args)


RATIOS = torch.tensor([1.5, 0.5, 1.1, 1.5])


@pytest.mark.parametrize("module", FAMILY, ids=FAMILY_IDS)
def test_clipped_objective_and_clipped_value_loss_by_hand(module):
    agent, obs, actions, old_logprobs, value = minibatch(module, RATIOS)
    advantages = torch.tensor([2.0, -2.0, 1.0, -1.0])
    old_values = value + torch.tensor([0.5, -0.5, 0.0, 0.1])
    returns = value + torch.tensor([1.0, 1.0, -1.0, 0.0])
    args = module.Args(norm_adv=False, clip_coef=0.2, ent_coef=0.0, vf_coef=0.7)
    loss, stats = loss_of(module, agent, obs, actions, old_logprobs, advantages, returns, old_values, args)
    # pessimistic surrogate: max(-A r, -A clip(r, .8, 1.2)): -2.4, 1.6, -1.1, 1.5
    assert stats["policy_loss"].item() == pytest.approx(np.mean([-2.4, 1.6, -1.1, 1.5]), rel=1e-5)
    # value: new - return = -1, -1, 1, 0; old + clip(new - old, +-.2) - return = -.7, -1.3, 1, 0; the larger square
    assert stats["value_loss"].item() == pytest.approx(0.5 * np.mean([1.0, 1.69, 1.0, 0.0]), rel=1e-5)
    assert stats["clipfrac"].item() == pytest.approx(0.75)
    # log r = .405, -.693, .095, .405: old_approx_kl = mean(-log r), approx_kl = mean(r - 1 - log r)
    assert stats["old_approx_kl"].item() == pytest.approx(-np.log(RATIOS.numpy()).mean(), rel=1e-5)
    assert stats["approx_kl"].item() == pytest.approx(np.mean(RATIOS.numpy() - 1 - np.log(RATIOS.numpy())), rel=1e-5)
    assert loss.item() == pytest.approx(stats["policy_loss"].item() + 0.7 * stats["value_loss"].item(), rel=1e-5)


@pytest.mark.parametrize("module", FAMILY, ids=FAMILY_IDS)
def test_norm_adv_standardises_the_minibatchs_advantages_with_the_sample_std(module):
    agent, obs, actions, old_logprobs, value = minibatch(module, RATIOS)
    advantages = torch.tensor([3.0, -1.0, 1.0, 1.0])
    policy_loss = {}
    for norm_adv in (True, False):
        args = module.Args(norm_adv=norm_adv, clip_coef=0.2)
        policy_loss[norm_adv] = loss_of(module, agent, obs, actions, old_logprobs, advantages, value, value, args)[1]
    # on: mean 1, sample std sqrt(8/3), so A = sqrt(1.5), -sqrt(1.5), 0, 0 and the surrogate is
    # max(-1.5 A, -1.2 A) = -1.2 sqrt(1.5), max(-.5 A, -.8 A) = .8 sqrt(1.5), 0, 0: mean -.1 sqrt(1.5)
    # (the population std, sqrt(2), would give -.1 sqrt(2); centring alone -.2)
    assert policy_loss[True]["policy_loss"].item() == pytest.approx(-0.1 * math.sqrt(1.5), rel=1e-5)
    # off, the raw advantages: -3.6, .8, -1.1, -1.2
    assert policy_loss[False]["policy_loss"].item() == pytest.approx(np.mean([-3.6, 0.8, -1.1, -1.2]), rel=1e-5)


@pytest.mark.parametrize("module", FAMILY, ids=FAMILY_IDS)
def test_clip_vloss_off_is_the_plain_half_squared_error(module):
    agent, obs, actions, old_logprobs, value = minibatch(module, RATIOS)
    old_values = value + torch.tensor([0.5, -0.5, 0.0, 0.1])
    returns = value + torch.tensor([1.0, 1.0, -1.0, 0.0])
    value_loss = {}
    for clip_vloss in (True, False):
        args = module.Args(norm_adv=False, clip_coef=0.2, clip_vloss=clip_vloss)
        _, stats = loss_of(module, agent, obs, actions, old_logprobs, torch.ones(4), returns, old_values, args)
        value_loss[clip_vloss] = stats["value_loss"].item()
    # off: new - return = -1, -1, 1, 0 whatever the old values; on: the larger of that and the clipped error
    # (-.7, -1.3, 1, 0), squared: 1, 1.69, 1, 0
    assert value_loss[False] == pytest.approx(0.5 * np.mean([1.0, 1.0, 1.0, 0.0]), rel=1e-5)
    assert value_loss[True] == pytest.approx(0.5 * np.mean([1.0, 1.69, 1.0, 0.0]), rel=1e-5)


@pytest.mark.parametrize("module", FAMILY, ids=FAMILY_IDS)
def test_ent_coef_subtracts_the_gaussians_entropy_and_raises_the_std(module):
    """Each action dimension's entropy is 1/2 log(2 pi e) + log std; their sum, averaged over the minibatch, enters
    the loss times -ent_coef, and its gradient pushes every log-std up by ent_coef."""
    logstd = [0.3, -0.5]
    agent, obs, actions, old_logprobs, value = minibatch(module, RATIOS, action_dim=2, logstd=logstd)
    entropy = 2 * 0.5 * math.log(2 * math.pi * math.e) + sum(logstd)  # 2.6379, the same for every sample
    advantages, losses, grads = torch.randn(4), {}, {}
    for ent_coef in (0.0, 0.05):
        args = module.Args(norm_adv=False, ent_coef=ent_coef, vf_coef=0.5)
        loss, stats = loss_of(module, agent, obs, actions, old_logprobs, advantages, value + 1, value, args)
        assert stats["entropy"].item() == pytest.approx(entropy, rel=1e-6)
        agent.zero_grad()
        loss.backward()
        losses[ent_coef], grads[ent_coef] = loss.item(), agent.actor_logstd.grad.clone()
    assert losses[0.05] - losses[0.0] == pytest.approx(-0.05 * entropy, rel=1e-4)
    torch.testing.assert_close(grads[0.05] - grads[0.0], torch.full((2,), -0.05))


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


def test_evaluation_is_deterministic_and_leaves_the_statistics_alone(tmp_path, monkeypatch):
    """The policy main evaluates (handed to rl_utils.evaluate, spied on here) is the clipped mean action on the
    training statistics: it draws nothing, updates no statistics, and repeats the run's last evaluation."""
    monkeypatch.chdir(tmp_path)
    policies = []

    def spy(policy, envs, seeds, num_episodes):
        policies.append(policy)
        return rl_utils.evaluate(policy, envs, seeds, num_episodes)

    monkeypatch.setattr(ppo, "evaluate", spy)
    result = ppo.main(
        small_args(ppo, env_id="Pendulum-v1", total_timesteps=600, eval_frequency=600, eval_episodes=2, run_name="run")
    )
    assert len(policies) == 2  # steps 0 and 600
    policy, agent, normalizer = policies[-1], result["agent"], result["normalizer"]
    env = rl_utils.make_env("Pendulum-v1", seed=101)
    mean_before, var_before, count_before = (
        normalizer.obs_rms.mean.copy(),
        normalizer.obs_rms.var.copy(),
        normalizer.obs_rms.count,
    )
    rng_before = torch.get_rng_state()
    first = rl_utils.evaluate(policy, [env], [101], 2)
    second = rl_utils.evaluate(policy, [env], [101], 2)
    np.testing.assert_array_equal(first, second)
    assert first.mean() == pytest.approx(result["eval_returns"][-1][1])
    assert torch.equal(torch.get_rng_state(), rng_before)
    np.testing.assert_array_equal(normalizer.obs_rms.mean, mean_before)
    np.testing.assert_array_equal(normalizer.obs_rms.var, var_before)
    assert normalizer.obs_rms.count == count_before
    # the mean action of the normalised observation, clipped to Pendulum's bounds (+-2)
    obs = np.array([[0.6, -0.8, 3.0], [-1.0, 0.0, -7.0]], dtype=np.float32)
    normalised = (obs - normalizer.obs_rms.mean) / np.sqrt(normalizer.obs_rms.var + 1e-8)
    with torch.no_grad():
        device = agent.actor_logstd.device  # the run's (a GPU where there is one)
        mean_action = agent.actor_mean(torch.as_tensor(normalised, dtype=torch.float32, device=device)).cpu().numpy()
        np.testing.assert_allclose(policy(obs), mean_action, rtol=1e-5, atol=1e-6)
        agent.actor_mean[-1].bias.copy_(torch.tensor([5.0]))  # far beyond the bounds
        np.testing.assert_array_equal(policy(obs), [[2.0], [2.0]])


def test_learning_rate_anneals_to_zero_over_the_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = ppo.main(small_args(ppo, env_id="Pendulum-v1", total_timesteps=1024, eval_frequency=1024, run_name="run"))
    # 4 rollouts of 256: the last is trained at lr * (1 - 3/4)
    assert result["optimizer"].param_groups[0]["lr"] == pytest.approx(3e-4 / 4)
    assert math.isclose(ppo.Args().learning_rate, 3e-4)


# ---- update_policy: the target_kl early stop, gradient clipping --------------------------------------

NUM_STEPS, OBS_DIM, ACTION_DIM = 8, 3, 1


def update_setup(module, old_ratio: float = 1.0):
    """An agent, a rollout of NUM_STEPS whose old log-probabilities put every ratio at old_ratio, and what RND's and
    EBD's update_policy take besides: (agent, rollout, explorer, explorer's trained parameters, its data)."""
    torch.manual_seed(0)
    agent = module.Agent(OBS_DIM, ACTION_DIM)
    rollout = module.Rollout(NUM_STEPS, OBS_DIM, ACTION_DIM, torch.device("cpu"))
    for tensor in vars(rollout).values():
        tensor.normal_()
    with torch.no_grad():
        rollout.logprobs.copy_(agent.get_action_and_value(rollout.obs, rollout.actions)[1] - math.log(old_ratio))
    if module is rnd:
        explorer = rnd.RNDModel(OBS_DIM, features=8, hidden=16)
        return agent, rollout, explorer, list(explorer.predictor.parameters()), torch.randn(NUM_STEPS, OBS_DIM)
    if module is ebd:
        explorer = ebd.ForwardModels(3, OBS_DIM, ACTION_DIM, hidden=16)
        data = (torch.randn(NUM_STEPS, OBS_DIM + ACTION_DIM), torch.randn(NUM_STEPS, OBS_DIM))
        return agent, rollout, explorer, list(explorer.parameters()), data
    return agent, rollout, None, [], None


def update(module, rollout, advantages, returns, agent, explorer, data, optimizer, args) -> dict:
    if module is ppo:
        return ppo.update_policy(rollout, advantages, returns, agent, optimizer, args)
    int_returns = returns.flip(0)
    return module.update_policy(rollout, advantages, returns, int_returns, data, agent, explorer, optimizer, args)


@pytest.mark.parametrize("module", FAMILY, ids=FAMILY_IDS)
@pytest.mark.parametrize("target_kl, minibatches", [(None, 6), (0.35, 6), (0.3, 2)])
def test_target_kl_stops_after_the_epoch_whose_approx_kl_exceeds_it(module, target_kl, minibatches, monkeypatch):
    """Every ratio 2 and a learning rate of 0 (the ratios stay): approx_kl = r - 1 - log r = 1 - log 2 = .307 in
    every minibatch (old_approx_kl = -log 2 = -.693). Above target_kl, the update ends with the epoch: 2 of its
    3 epochs' 2 minibatches each are skipped."""
    calls = []
    real_loss = module.ppo_loss
    monkeypatch.setattr(module, "ppo_loss", lambda *a: calls.append(1) or real_loss(*a))
    agent, rollout, explorer, explorer_params, data = update_setup(module, old_ratio=2.0)
    optimizer = torch.optim.SGD([*agent.parameters(), *explorer_params], lr=0.0)
    args = module.Args(num_steps=NUM_STEPS, num_minibatches=2, update_epochs=3, target_kl=target_kl)
    if module is ebd:
        args.num_models = 3
    stats = update(module, rollout, torch.randn(NUM_STEPS), torch.randn(NUM_STEPS), agent, explorer, data, optimizer, args)
    assert len(calls) == minibatches
    assert stats["approx_kl"].item() == pytest.approx(1 - math.log(2), rel=1e-5)


def clip_groups(module, agent, explorer) -> list:
    """The parameter sets whose gradient norm update_policy clips, each as one: PPO's agent; RND's agent and
    predictor together (its optimizer's one group, as CleanRL); EBD's agent and forward models apart."""
    if module is rnd:
        return [[*agent.parameters(), *explorer.predictor.parameters()]]
    if module is ebd:
        return [list(agent.parameters()), list(explorer.parameters())]
    return [list(agent.parameters())]


@pytest.mark.parametrize("module", FAMILY, ids=FAMILY_IDS)
@pytest.mark.parametrize("max_grad_norm", [0.05, 1e6])
def test_max_grad_norm_scales_each_clipped_gradient_to_that_norm(module, max_grad_norm):
    """One minibatch, one epoch, plain SGD with lr 1: each parameter moves by minus its gradient times
    min(1, max_grad_norm / (norm + 1e-6)), the norm taken over its whole clip group; the gradient by hand is the
    script's losses' on the whole rollout (RND's predictor on all of it: update_proportion 1)."""
    agent, rollout, explorer, explorer_params, data = update_setup(module)
    advantages, returns = torch.randn(NUM_STEPS), torch.randn(NUM_STEPS)
    args = module.Args(num_steps=NUM_STEPS, num_minibatches=1, update_epochs=1, max_grad_norm=max_grad_norm)
    if module is rnd:
        args.update_proportion = 1.0
    if module is ebd:
        args.num_models = 3
    # by hand: the gradient of the whole loss
    torch.manual_seed(7)
    minibatch_args = (agent, rollout.obs, rollout.actions, rollout.logprobs, advantages, returns, rollout.values)
    if module is ppo:
        loss, _ = ppo.ppo_loss(*minibatch_args, args)
    else:
        loss, _ = module.ppo_loss(*minibatch_args, returns.flip(0), args)  # update()'s intrinsic returns
    if module is rnd:
        loss = loss + explorer.loss(data, 1.0)
    if module is ebd:  # the members' bootstrap samples, drawn first, as update_policy draws them
        loss = loss + ebd.forward_model_loss(explorer, *data, torch.randint(NUM_STEPS, (3, NUM_STEPS)))
    groups = clip_groups(module, agent, explorer)
    grads = torch.autograd.grad(loss, [p for group in groups for p in group])
    expected, norms, i = [], [], 0
    for group in groups:
        group_grads = grads[i : i + len(group)]
        norm = torch.sqrt(sum((g.double() ** 2).sum() for g in group_grads)).item()
        scale = min(1.0, max_grad_norm / (norm + 1e-6))
        expected += [p.detach() - scale * g for p, g in zip(group, group_grads)]
        norms.append(norm)
        i += len(group)
    clipping = max_grad_norm < 1
    assert all(norm > 2 * max_grad_norm if clipping else norm < max_grad_norm for norm in norms), norms

    before = [p.detach().clone() for group in groups for p in group]
    optimizer = torch.optim.SGD([*agent.parameters(), *explorer_params], lr=1.0)
    torch.manual_seed(7)  # the same bootstrap samples
    update(module, rollout, advantages, returns, agent, explorer, data, optimizer, args)
    after = [p.detach() for group in groups for p in group]
    for p, e in zip(after, expected):
        torch.testing.assert_close(p, e, rtol=1e-4, atol=1e-6)
    if clipping:  # each clip group's step is max_grad_norm long
        i = 0
        for group in groups:
            step = sum(((a - b).double() ** 2).sum() for a, b in zip(after[i : i + len(group)], before[i : i + len(group)]))
            assert math.sqrt(step) == pytest.approx(max_grad_norm, rel=1e-3)
            i += len(group)
