"""TD3's parts: replay buffer, critic ensemble, target value, losses and their optimizer steps, target networks.
The algorithm functions are written for one seed (main runs them through rl_utils.per_seed); so are these tests."""

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn.functional as F

import td3_continuous_action as td3
from conftest import assert_ensemble_is_independent_mlps, small_args
from rl_utils import Batch, ReplayBuffer

OBS_DIM, ACTION_DIM = 4, 2
SPACE = gym.spaces.Box(np.array([-1.0, 0.0], np.float32), np.array([1.0, 4.0], np.float32))


def filled_buffer(capacity=10, rows=7, num_seeds=1):
    rb = ReplayBuffer(capacity, OBS_DIM, ACTION_DIM, num_seeds, torch.device("cpu"))
    seed = np.arange(num_seeds)[:, None]  # seed k's rows are offset by 100 k
    for i in range(rows):  # row i is recognisable from every field
        j = i + 100 * seed
        rb.add(
            np.broadcast_to(j, (num_seeds, OBS_DIM)),
            np.broadcast_to(j + 0.5, (num_seeds, OBS_DIM)),
            np.broadcast_to(-j, (num_seeds, ACTION_DIM)),
            10.0 * j[:, 0],
            j[:, 0] % 2,
        )
    return rb


def test_replay_buffer_samples_whole_transitions():
    torch.manual_seed(0)
    rb = filled_buffer()
    batch = Batch(*(field[0] for field in rb.sample(500)))  # the one seed's batch
    i = batch.observations[:, 0]
    assert set(i.tolist()) == set(range(7))
    torch.testing.assert_close(batch.observations, i[:, None].expand(-1, OBS_DIM))
    torch.testing.assert_close(batch.actions, -i[:, None].expand(-1, ACTION_DIM))
    torch.testing.assert_close(batch.next_observations, i[:, None].expand(-1, OBS_DIM) + 0.5)
    torch.testing.assert_close(batch.rewards, 10.0 * i)
    torch.testing.assert_close(batch.terminations, i % 2)
    assert batch.rewards.shape == batch.terminations.shape == (500,)


def test_replay_buffer_add_takes_cleanrls_order_and_names_a_field_of_the_wrong_shape():
    """add(obs, next_obs, actions, rewards, terminations), as CleanRL's rb.add; the earlier order (actions second), a
    missing seeds dimension or a field of another width stops at the call, naming the field and the order."""
    rb = ReplayBuffer(10, OBS_DIM, ACTION_DIM, 1, torch.device("cpu"))
    obs, next_obs, actions = np.zeros((1, OBS_DIM)), np.ones((1, OBS_DIM)), np.full((1, ACTION_DIM), 2.0)
    rb.add(obs, next_obs, actions, np.array([3.0]), np.array([0.0]))
    batch = rb.sample(1)
    assert batch.next_observations.tolist() == [[[1.0] * OBS_DIM]] and batch.actions.tolist() == [[[2.0] * ACTION_DIM]]
    order = r"the order is add\(obs, next_obs, actions, rewards, terminations\)"
    with pytest.raises(ValueError, match=rf"^ReplayBuffer.add: next_obs has shape \[1, 2\], not \[1, 4\]; {order}"):
        rb.add(obs, actions, next_obs, np.array([3.0]), np.array([0.0]))  # actions where next_obs goes
    with pytest.raises(ValueError, match=r"^ReplayBuffer.add: obs has shape \[4\], not \[1, 4\]"):
        rb.add(obs[0], next_obs[0], actions[0], 3.0, 0.0)  # one seed's transition without the seeds dimension
    assert rb.size == 1


def test_replay_buffer_overwrites_the_oldest_rows_when_full():
    torch.manual_seed(0)
    rb = filled_buffer(capacity=5, rows=7)
    assert rb.size == 5 and rb.pos == 2
    assert set(rb.sample(500).observations[0, :, 0].tolist()) == {2, 3, 4, 5, 6}


def test_replay_buffer_draws_each_seeds_batch_from_its_own_transitions():
    torch.manual_seed(0)
    batch = filled_buffer(rows=7, num_seeds=3).sample(4, 500)  # 4 batches of 500 per seed
    assert batch.observations.shape == (3, 4, 500, OBS_DIM) and batch.rewards.shape == (3, 4, 500)
    for k in range(3):
        i = batch.observations[k, ..., 0]
        assert set(i.flatten().tolist()) == {100 * k + row for row in range(7)}  # its own rows, all of them
        torch.testing.assert_close(batch.rewards[k], 10.0 * i)  # whole transitions
    assert not torch.equal(batch.observations[0] % 100, batch.observations[1] % 100)  # indices drawn per seed


@pytest.mark.parametrize("style, activation", [("td3", F.relu), ("release", F.silu)])
def test_q_ensemble_members_are_independent_mlps(style, activation):
    qf = td3.QEnsemble(OBS_DIM, ACTION_DIM, num_q=3, style=style)
    obs, actions, q = assert_ensemble_is_independent_mlps(qf, OBS_DIM, ACTION_DIM, activation)
    torch.testing.assert_close(qf[0](obs, actions), q[0])  # a critic alone, as TD3's actor loss uses the first


def test_critic_style_release_trains_oparls_critics_and_the_default_draws_as_before(tmp_path, monkeypatch):
    """--critic-style release: OPARL's critics in TD3 (the same draws and function as oparl's QEnsemble), so that
    OPARL's method can be told from its critics; the default draws CleanRL's critics as plain nn.Linear layers do."""
    torch.manual_seed(0)
    plain = [[torch.nn.Linear(320, 256), torch.nn.Linear(256, 256), torch.nn.Linear(256, 1)] for _ in range(2)]
    torch.manual_seed(0)
    default = td3.QEnsemble(300, 20)
    for layers, critic in zip(plain, default):
        for layer, fc in zip(layers, (critic.fc1, critic.fc2, critic.fc3)):
            assert torch.equal(layer.weight, fc.weight) and torch.equal(layer.bias, fc.bias)
    import oparl_continuous_action as oparl

    torch.manual_seed(1)
    release = td3.QEnsemble(300, 20, style="release")
    torch.manual_seed(1)
    oparls = oparl.QEnsemble(300, 20, num_q=2, style="release")
    assert all(torch.equal(a, b) for a, b in zip(release.parameters(), oparls.parameters()))
    obs, actions = torch.randn(16, 300), torch.randn(16, 20)
    assert torch.equal(release(obs, actions), oparls(obs, actions))
    assert torch.stack([c.fc2.weight for c in release]).std().item() == pytest.approx(0.5 / 256**0.5, rel=0.05)
    monkeypatch.chdir(tmp_path)  # and the flag reaches a run's critics, online and target
    flags = dict(env_id="Pendulum-v1", total_timesteps=300, learning_starts=200, batch_size=32, eval_frequency=300)
    result = td3.main(small_args(td3, critic_style="release", **flags))
    assert all(critic.activation is F.silu for critic in [*result["qf"], *result["qf_target"]])


def test_actor_respects_asymmetric_bounds():
    actor = td3.Actor(OBS_DIM, SPACE)
    with torch.no_grad():
        actor.fc_mu.bias.fill_(100.0)
        high = actor(torch.randn(5, OBS_DIM))
        actor.fc_mu.bias.fill_(-100.0)
        low = actor(torch.randn(5, OBS_DIM))
    torch.testing.assert_close(high, torch.tensor([[1.0, 4.0]]).expand(5, -1))
    torch.testing.assert_close(low, torch.tensor([[-1.0, 0.0]]).expand(5, -1))


class RecordingEnsemble:
    """A fake target ensemble: member k returns (k + 1) * offsets; remembers the actions it saw."""

    def __init__(self, offsets):
        self.offsets = offsets

    def __call__(self, obs, actions):
        self.actions = actions
        return torch.stack([self.offsets * (k + 1) for k in range(3)])


def zero_actor():
    actor = td3.Actor(OBS_DIM, SPACE)
    with torch.no_grad():
        for p in actor.parameters():
            p.zero_()
    return actor  # always outputs the middle of the box: [0, 2]


def batch_of(n, rewards, terminations):
    return Batch(torch.zeros(n, OBS_DIM), torch.zeros(n, ACTION_DIM), torch.zeros(n, OBS_DIM), rewards, terminations)


def test_td_target_takes_min_over_members_and_bootstraps_unless_terminated():
    offsets = torch.tensor([-1.0, 2.0, 3.0, -4.0])  # negative offsets make the last member the min
    qf_target = RecordingEnsemble(offsets)
    args = td3.Args(gamma=0.9, policy_noise=0.0)
    batch = batch_of(4, torch.tensor([1.0, 1.0, 0.0, 5.0]), torch.tensor([0.0, 1.0, 0.0, 0.0]))
    y = td3.td_target(batch, zero_actor(), qf_target, args)
    min_q = torch.minimum(offsets, 3 * offsets)
    torch.testing.assert_close(y, batch.rewards + 0.9 * (1 - batch.terminations) * min_q)
    assert y[1] == 1.0  # terminated: the reward alone


def test_td_target_noise_is_clipped_scaled_and_kept_in_bounds():
    torch.manual_seed(0)
    qf_target = RecordingEnsemble(torch.zeros(4096))
    args = td3.Args(policy_noise=10.0, noise_clip=0.5)
    td3.td_target(batch_of(4096, torch.zeros(4096), torch.zeros(4096)), zero_actor(), qf_target, args)
    noise = qf_target.actions - torch.tensor([0.0, 2.0])
    # dimension 0: scale 1, clip 0.5 -> [-0.5, 0.5]; dimension 1: scale 2 -> [-1, 1]
    assert noise[:, 0].abs().max() == pytest.approx(0.5) and noise[:, 1].abs().max() == pytest.approx(1.0)
    assert noise.std(0).min() > 0.3  # noisy, not constant


def test_td_target_is_not_differentiable():
    actor, qf = td3.Actor(OBS_DIM, SPACE), td3.QEnsemble(OBS_DIM, ACTION_DIM)
    y = td3.td_target(batch_of(3, torch.ones(3), torch.zeros(3)), actor, qf, td3.Args())
    assert not y.requires_grad


def make_agent():
    torch.manual_seed(0)
    actor, qf = td3.Actor(OBS_DIM, SPACE), td3.QEnsemble(OBS_DIM, ACTION_DIM)
    target_actor, qf_target = td3.Actor(OBS_DIM, SPACE), td3.QEnsemble(OBS_DIM, ACTION_DIM)
    q_optimizer = torch.optim.Adam(qf.parameters(), lr=1e-3)
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=1e-3)
    batch = Batch(
        torch.randn(32, OBS_DIM), torch.rand(32, ACTION_DIM), torch.randn(32, OBS_DIM), torch.randn(32), torch.zeros(32)
    )
    return actor, qf, target_actor, qf_target, q_optimizer, actor_optimizer, batch


def snapshot(net):
    return [p.detach().clone() for p in net.parameters()]


def test_critic_loss_is_the_sum_of_each_critics_mse_against_the_td_target():
    _, qf, target_actor, qf_target, _, _, batch = make_agent()
    args = td3.Args()  # target noise on: the loss and the target below draw the same noise
    torch.manual_seed(1)
    loss, q = td3.critic_loss(batch, qf, target_actor, qf_target, args)
    torch.manual_seed(1)
    y = td3.td_target(batch, target_actor, qf_target, args)
    with torch.no_grad():
        torch.testing.assert_close(q, qf(batch.observations, batch.actions))
    assert q.shape == (2, 32) and not q.requires_grad and loss.shape == ()
    assert loss.item() == pytest.approx(((q - y) ** 2).mean(1).sum().item(), rel=1e-6)


def test_critic_update_fits_the_target_and_leaves_actors_alone():
    actor, qf, target_actor, qf_target, q_optimizer, _, batch = make_agent()
    actor_before, target_before = snapshot(actor), snapshot(target_actor)
    losses = []
    for _ in range(50):  # main's critic step: the loss, then optimize
        loss, _ = td3.critic_loss(batch, qf, target_actor, qf_target, td3.Args(policy_noise=0.0))
        td3.optimize(loss, "qf_loss", q_optimizer)
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    for before, net in [(actor_before, actor), (target_before, target_actor)]:
        for a, b in zip(before, net.parameters()):
            torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_actor_update_uses_q1_and_never_touches_the_critic():
    actor, qf, _, _, _, actor_optimizer, batch = make_agent()
    qf_before, actor_before = snapshot(qf), snapshot(actor)
    q1_before = qf(batch.observations, actor(batch.observations))[0].mean().item()
    qf.requires_grad_(False)  # as main steps the actor
    loss = td3.policy_loss(batch, actor, qf)
    assert loss.item() == pytest.approx(-q1_before, rel=1e-5)
    td3.optimize(loss, "actor_loss", actor_optimizer)
    assert all(p.grad is None for p in qf.parameters())
    for a, b in zip(qf_before, qf.parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert any(not torch.equal(a, b) for a, b in zip(actor_before, actor.parameters()))
    for _ in range(30):
        td3.optimize(td3.policy_loss(batch, actor, qf), "actor_loss", actor_optimizer)
    assert qf(batch.observations, actor(batch.observations))[0].mean().item() > q1_before  # ascends Q1


@pytest.mark.parametrize("script", ["td3", "oparl"])
def test_the_critics_compute_what_the_hand_batched_ensemble_did(script):
    """QEnsemble, a loop over QNetworks, against the hand-batched ensemble the scripts had before (each layer's weights
    stacked into one [num_q, in, out] tensor, one baddbmm a layer), on the same weights: the Q-values, the gradients of
    a critic loss and one fused Adam step agree to float tolerance."""
    import oparl_continuous_action as oparl

    module = {"td3": td3, "oparl": oparl}[script]
    torch.manual_seed(0)
    qf = module.QEnsemble(OBS_DIM, ACTION_DIM, num_q=3)
    activation = qf[0].activation if script == "oparl" else F.relu
    stacked = [
        torch.stack([c.fc1.weight.T for c in qf]),
        torch.stack([c.fc1.bias[None] for c in qf]),
        torch.stack([c.fc2.weight.T for c in qf]),
        torch.stack([c.fc2.bias[None] for c in qf]),
        torch.stack([c.fc3.weight[0] for c in qf]),
        torch.stack([c.fc3.bias for c in qf]),
    ]
    stacked = [tensor.detach().clone().requires_grad_() for tensor in stacked]

    def batched(obs, actions):  # the scripts' QEnsemble.forward before
        w1, b1, w2, b2, w3, b3 = stacked
        x = torch.cat([obs, actions], -1).expand(len(w1), -1, -1).contiguous()
        x = activation(torch.baddbmm(b1, x, w1))
        x = activation(torch.baddbmm(b2, x, w2))
        return (x * w3[:, None]).sum(-1) + b3

    obs, actions, y = torch.randn(64, OBS_DIM), torch.randn(64, ACTION_DIM), torch.randn(64)
    torch.testing.assert_close(qf(obs, actions), batched(obs, actions), rtol=1e-5, atol=1e-6)
    optimizers = [torch.optim.Adam(qf.parameters(), lr=1e-3, fused=True), torch.optim.Adam(stacked, lr=1e-3, fused=True)]
    for optimizer, q in zip(optimizers, (qf(obs, actions), batched(obs, actions))):
        optimizer.zero_grad()
        ((q - y) ** 2).mean(-1).sum().backward()
    torch.testing.assert_close(torch.stack([c.fc2.weight.grad.T for c in qf]), stacked[2].grad, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(torch.stack([c.fc3.bias.grad for c in qf]), stacked[5].grad, rtol=1e-4, atol=1e-6)
    for optimizer in optimizers:
        optimizer.step()
    torch.testing.assert_close(torch.stack([c.fc1.weight.T for c in qf]), stacked[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(torch.stack([c.fc3.weight[0] for c in qf]), stacked[4], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(qf(obs, actions), batched(obs, actions), rtol=1e-5, atol=1e-6)
