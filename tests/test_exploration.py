"""RND's and EBD's defining parts: each bonus, the normalisation around it, and how it enters PPO's advantage."""

import copy

import numpy as np
import pytest
import torch

import ebd_continuous_action as ebd
import rnd_continuous_action as rnd
from conftest import small_args

EXPLORERS = [rnd, ebd]


# ---- RND -------------------------------------------------------------------------------------------


def test_rnd_target_never_changes_over_a_run_while_the_predictor_learns(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = rnd.main(small_args(rnd, env_id="Pendulum-v1", total_timesteps=768, eval_frequency=768, run_name="run"))
    torch.manual_seed(1)  # main seeds torch, then builds the agent and the RND model, in this order
    rnd.Agent(3, 1)
    initial = rnd.RNDModel(3)
    trained = result["rnd_model"].cpu()  # from the run's device (a GPU where there is one)
    for name, tensor in initial.target.state_dict().items():
        assert torch.equal(trained.target.state_dict()[name], tensor), name
    assert not torch.equal(trained.predictor[0].weight, initial.predictor[0].weight)


def test_rnd_bonus_falls_where_the_predictor_trained_and_stays_high_elsewhere():
    torch.manual_seed(0)
    model = rnd.RNDModel(4)
    seen = torch.randn(256, 4) * 0.5 + torch.tensor([-2.0, 0.0, 0.0, 0.0])
    unseen = torch.randn(256, 4) * 0.5 + torch.tensor([2.0, 0.0, 0.0, 0.0])
    with torch.no_grad():
        seen_before, unseen_before = model.bonus(seen).mean(), model.bonus(unseen).mean()
    optimizer = torch.optim.Adam(model.predictor.parameters(), lr=1e-3)
    for _ in range(300):
        loss = model.loss(seen, update_proportion=1.0)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        seen_after, unseen_after = model.bonus(seen).mean(), model.bonus(unseen).mean()
    # measured over seeds 0-4: seen falls ~1000x, unseen keeps 70-97% of its start
    assert seen_after < 0.01 * seen_before
    assert unseen_after > 0.5 * unseen_before and unseen_after > 100 * seen_after


def test_rnd_bonus_is_half_the_summed_squared_error_and_the_loss_uses_a_share_of_the_batch():
    torch.manual_seed(0)
    model = rnd.RNDModel(3, features=4)
    obs = torch.randn(1000, 3)
    with torch.no_grad():
        error = model.target(obs) - model.predictor(obs)
        torch.testing.assert_close(model.bonus(obs), (error**2).sum(-1) / 2)
        per_sample = (error**2).mean(-1)
        torch.manual_seed(5)
        loss = model.loss(obs, update_proportion=0.25)
        torch.manual_seed(5)
        mask = torch.rand(1000) < 0.25
    torch.testing.assert_close(loss, per_sample[mask].mean())
    assert 150 < mask.sum() < 350  # about a quarter of the batch


# ---- EBD -------------------------------------------------------------------------------------------


def member_prediction(models, k, x):
    """Member k of the batched ensemble, computed alone from its own weights."""
    for i, (weight, bias) in enumerate(zip(models.weights, models.biases)):
        x = x @ weight[k] + bias[k, 0]
        if i < len(models.weights) - 1:
            x = torch.relu(x)
    return x


def test_ebd_bonus_is_the_variance_across_members_averaged_over_features():
    torch.manual_seed(0)
    models = ebd.ForwardModels(num_models=4, obs_dim=3, action_dim=2, hidden=16)
    inputs = torch.randn(7, 5)
    with torch.no_grad():
        predictions = np.stack([member_prediction(models, k, inputs).numpy() for k in range(4)])  # [4, 7, 3]
        bonus = ebd.disagreement(models, inputs).numpy()
    expected = ((predictions - predictions.mean(0)) ** 2).mean(0).mean(-1)  # population variance over members
    np.testing.assert_allclose(bonus, expected, rtol=1e-5, atol=1e-8)
    assert (bonus > 0).all()


def test_ebd_bonus_is_zero_when_every_member_is_the_same():
    torch.manual_seed(0)
    models = ebd.ForwardModels(num_models=5, obs_dim=3, action_dim=1)
    with torch.no_grad():
        for tensor in [*models.weights, *models.biases]:
            tensor[:] = tensor[0]
        assert torch.all(ebd.disagreement(models, torch.randn(9, 4)) == 0)


def test_ebd_loss_trains_each_member_on_its_own_sample():
    torch.manual_seed(0)
    models = ebd.ForwardModels(num_models=3, obs_dim=2, action_dim=1, hidden=8)
    inputs, targets = torch.randn(10, 3), torch.randn(10, 2)
    samples = torch.tensor([[0, 0, 1, 2], [3, 4, 4, 5], [9, 8, 7, 7]])
    loss = ebd.forward_model_loss(models, inputs, targets, samples)
    by_hand = torch.stack(
        [((member_prediction(models, k, inputs[samples[k]]) - targets[samples[k]]) ** 2).mean() for k in range(3)]
    ).mean()
    torch.testing.assert_close(loss, by_hand)
    # transition 9 is in member 2's sample only: changing its target changes member 2's gradients alone
    loss.backward()
    before = [weight.grad.clone() for weight in models.weights]
    models.zero_grad()
    changed = targets.clone()
    changed[9] += 10.0
    ebd.forward_model_loss(models, inputs, changed, samples).backward()
    for layer, weight in enumerate(models.weights):
        for k in range(3):
            assert torch.equal(before[layer][k], weight.grad[k]) == (k != 2), (layer, k)


def test_ebd_members_see_different_bootstrap_samples_of_each_rollout(monkeypatch):
    seen = []
    real_loss = ebd.forward_model_loss

    def spy(models, inputs, targets, member_samples):
        seen.append(member_samples.clone())
        return real_loss(models, inputs, targets, member_samples)

    monkeypatch.setattr(ebd, "forward_model_loss", spy)
    torch.manual_seed(0)
    args = ebd.Args(num_steps=64, num_minibatches=4, update_epochs=2, num_models=3)
    rollout = ebd.Rollout(64, 2, 1, torch.device("cpu"))
    for tensor in vars(rollout).values():
        tensor.normal_()
    agent, models = ebd.Agent(2, 1), ebd.ForwardModels(3, 2, 1)
    optimizer = torch.optim.Adam([*agent.parameters(), *models.parameters()], lr=1e-3)
    weights_before = models.weights[0].detach().clone()
    inputs, targets = torch.randn(64, 3), torch.randn(64, 2)
    returns = torch.randn(64)
    ebd.update_policy(rollout, torch.randn(64), returns, returns, (inputs, targets), agent, models, optimizer, args)
    assert len(seen) == 8 and all(s.shape == (3, 16) for s in seen)
    first_epoch, second_epoch = torch.cat(seen[:4], 1), torch.cat(seen[4:], 1)
    for k in range(3):
        # one bootstrap sample per member and rollout, reshuffled each epoch, drawn with replacement
        assert torch.equal(first_epoch[k].sort().values, second_epoch[k].sort().values)
        assert len(first_epoch[k].unique()) < 64
    assert not torch.equal(first_epoch[0].sort().values, first_epoch[1].sort().values)
    assert not torch.equal(first_epoch[1].sort().values, first_epoch[2].sort().values)
    assert not torch.equal(models.weights[0], weights_before)


# ---- what RND and EBD share ------------------------------------------------------------------------


@pytest.mark.parametrize("module", EXPLORERS, ids=["rnd", "ebd"])
def test_combined_advantage_and_non_episodic_intrinsic_gae_by_hand(module):
    rollout = module.Rollout(3, 1, 1, torch.device("cpu"))
    rollout.rewards.copy_(torch.tensor([1.0, 2.0, 3.0]))
    rollout.values.copy_(torch.tensor([0.5, 1.0, 1.5]))
    rollout.int_values.copy_(torch.tensor([0.5, 0.5, 0.5]))
    rollout.episode_ends.copy_(torch.tensor([0.0, 1.0, 0.0]))  # an episode ends at step 1
    int_rewards = torch.tensor([1.0, 0.0, 2.0])
    args = module.Args(gamma=0.9, gae_lambda=0.8, int_gamma=0.5, ext_coef=2.0, int_coef=1.0)
    advantages, ext_returns, int_returns = module.advantages_and_returns(
        rollout, int_rewards, (torch.tensor(2.0), torch.tensor(1.0)), args
    )
    # extrinsic, cut at step 1 (as PPO's test): 2.12, 1.0, 3.3
    # intrinsic, not cut: t=2: 2 + .5*1 - .5 = 2; t=1: .5*.5 - .5 + .5*.8*2 = .55; t=0: 1 + .25 - .5 + .4*.55 = .97
    torch.testing.assert_close(advantages, 2.0 * torch.tensor([2.12, 1.0, 3.3]) + torch.tensor([0.97, 0.55, 2.0]))
    torch.testing.assert_close(ext_returns, torch.tensor([2.62, 2.0, 4.8]))
    torch.testing.assert_close(int_returns, torch.tensor([1.47, 1.05, 2.5]))
    rollout.episode_ends.zero_()  # no episode end: the extrinsic part changes, the intrinsic one does not
    advantages_no_end, ext_no_end, int_no_end = module.advantages_and_returns(
        rollout, int_rewards, (torch.tensor(2.0), torch.tensor(1.0)), args
    )
    torch.testing.assert_close(int_no_end, int_returns)
    assert not torch.allclose(ext_no_end, ext_returns)


@pytest.mark.parametrize("module", EXPLORERS, ids=["rnd", "ebd"])
def test_observation_statistics_and_intrinsic_return_std_by_hand(module):
    normalizer = module.IntrinsicNormalizer(3, int_gamma=0.9)
    rng = np.random.default_rng(0)
    first, second = rng.normal(2.0, 3.0, (100, 3)), rng.normal(-1.0, 0.5, (50, 3))
    normalizer.obs_rms.update_batch(first)
    normalizer.obs_rms.update_batch(second)
    both = np.concatenate([first, second])
    # the statistics start from CleanRL's prior (mean 0, var 1, count 1e-4): negligible beside 150 samples
    np.testing.assert_allclose(normalizer.obs_rms.mean, both.mean(0), rtol=1e-5)
    np.testing.assert_allclose(normalizer.obs_rms.var, both.var(0), rtol=1e-5)
    mean, std = both.mean(0), both.std(0)
    obs = torch.tensor(np.stack([mean + 2 * std, mean - 10 * std, mean]), dtype=torch.float32)
    torch.testing.assert_close(
        normalizer.observation(obs), torch.tensor([[2.0] * 3, [-5.0] * 3, [0.0] * 3]), rtol=1e-4, atol=1e-4
    )

    rollouts = [torch.tensor([1.0, 2.0, 0.5, 3.0]), torch.tensor([0.2, 4.0, 1.0])]
    outputs = [normalizer.intrinsic(r) for r in rollouts]
    discounted, running = [], 0.0
    for reward in [1.0, 2.0, 0.5, 3.0, 0.2, 4.0, 1.0]:  # the discounted sum runs on from one rollout to the next
        running = 0.9 * running + reward
        discounted.append(running)
    torch.testing.assert_close(outputs[0], rollouts[0] / float(np.std(discounted[:4])), rtol=1e-4, atol=0)
    torch.testing.assert_close(outputs[1], rollouts[1] / float(np.std(discounted)), rtol=1e-4, atol=0)


@pytest.mark.parametrize("module", EXPLORERS, ids=["rnd", "ebd"])
def test_running_mean_std_batch_update_matches_one_at_a_time(module):
    data = np.random.default_rng(2).normal(1.0, 2.0, (64, 2))
    batched, single = module.RunningMeanStd((2,)), module.RunningMeanStd((2,))
    batched.update_batch(data[:40])
    batched.update_batch(data[40:])
    for x in data:
        single.update(x)
    np.testing.assert_allclose(batched.mean, single.mean, rtol=1e-10)
    np.testing.assert_allclose(batched.var, single.var, rtol=1e-10)
    assert batched.count == pytest.approx(single.count)


@pytest.mark.parametrize("model_scale", [1e4])
def test_ebd_clips_the_agent_apart_from_the_forward_models(monkeypatch, model_scale):
    """However large the models' gradient, the agent takes the step PPO alone would: the two gradient norms are
    clipped apart (as in the EBD release), not as one global norm."""
    real_loss = ebd.forward_model_loss
    args = ebd.Args(num_steps=64, num_minibatches=1, update_epochs=1, num_models=3, max_grad_norm=0.5)
    torch.manual_seed(0)
    rollout = ebd.Rollout(64, 2, 1, torch.device("cpu"))
    for tensor in vars(rollout).values():
        tensor.normal_()
    agent, models = ebd.Agent(2, 1), ebd.ForwardModels(3, 2, 1)
    data = (torch.randn(64, 3), torch.randn(64, 2))
    advantages, returns = torch.randn(64), torch.randn(64)
    agents = {}
    for scale in (1.0, model_scale):
        monkeypatch.setattr(ebd, "forward_model_loss", lambda *a, s=scale: s * real_loss(*a))
        run_agent, run_models = copy.deepcopy(agent), copy.deepcopy(models)
        optimizer = torch.optim.SGD(
            [*run_agent.parameters(), *run_models.parameters()], lr=0.1
        )  # steps as large as the gradients
        torch.manual_seed(1)  # the same minibatch order and bootstrap samples
        ebd.update_policy(rollout, advantages, returns, returns, data, run_agent, run_models, optimizer, args)
        agents[scale] = run_agent
    assert any(not torch.equal(p, q) for p, q in zip(agent.parameters(), agents[1.0].parameters()))  # the agent moved
    for (name, p), q in zip(agents[1.0].named_parameters(), agents[model_scale].parameters()):
        torch.testing.assert_close(q, p, msg=name)


@pytest.mark.parametrize("clip_vloss", [True, False])
@pytest.mark.parametrize("module", EXPLORERS, ids=["rnd", "ebd"])
def test_the_intrinsic_value_head_adds_its_own_unclipped_half_squared_error(module, clip_vloss):
    """PPO's loss with a second value head: value_loss = PPO's (clipped or not) extrinsic value loss + 0.5 * the
    intrinsic head's mean squared error, which is never clipped; the loss takes vf_coef of their sum."""
    torch.manual_seed(0)
    agent, args = module.Agent(3, 2), module.Args(clip_coef=0.2, clip_vloss=clip_vloss, vf_coef=0.7)
    obs, actions = torch.randn(16, 3), torch.randn(16, 2)
    with torch.no_grad():
        _, logprob, _, value, int_value = agent.get_action_and_value(obs, actions)
    # returns 1 above the value, old values .5 below it: the clipped extrinsic error is 1.3 (squared 1.69), the plain 1
    common = (obs, actions, logprob, torch.randn(16), value + 1.0, value - 0.5)
    exact_loss, exact = module.ppo_loss(agent, *common, int_value, args)
    off_loss, off = module.ppo_loss(agent, *common, int_value + 10.0, args)  # 10 away: 0.5 * 100 more, not clipped
    assert exact["value_loss"].item() == pytest.approx(
        0.5 * (1.69 if clip_vloss else 1.0), rel=1e-5
    )  # the extrinsic head alone
    assert off["value_loss"].item() - exact["value_loss"].item() == pytest.approx(50.0, rel=1e-5)
    assert (off_loss - exact_loss).item() == pytest.approx(0.7 * 50.0, rel=1e-5)
    assert off["policy_loss"] == exact["policy_loss"]
