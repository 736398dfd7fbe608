"""SAC's parts: the squashed Gaussian, the entropy-regularised target, alpha, deterministic evaluation. The algorithm
functions are written for one seed (main runs them through rl_utils.per_seed); so are these tests."""

import gymnasium as gym
import numpy as np
import pytest
import torch

import sac_continuous_action as sac
from conftest import assert_ensemble_is_independent_mlps, small_args
from rl_utils import Batch, make_env, per_seed, stack_seeds

OBS_DIM = 3
SPACE = gym.spaces.Box(np.array([-1.0, 0.0], np.float32), np.array([1.0, 4.0], np.float32))


def actor_with(mean, log_std_raw):
    """An actor whose mean and (pre-squash) log-std heads output constants."""
    actor = sac.Actor(OBS_DIM, SPACE)
    with torch.no_grad():
        for layer, value in [(actor.fc_mean, mean), (actor.fc_logstd, log_std_raw)]:
            layer.weight.zero_()
            layer.bias.copy_(torch.tensor(value))
    return actor


def test_log_prob_matches_the_density_of_the_sampled_actions():
    """Histogram the actions the actor samples (in narrow bins) and compare with exp(log_prob)."""
    torch.manual_seed(0)
    space = gym.spaces.Box(np.array([0.0], np.float32), np.array([4.0], np.float32))
    actor = sac.Actor(OBS_DIM, space)
    with torch.no_grad():
        for layer, value in [(actor.fc_mean, 0.3), (actor.fc_logstd, 0.1)]:
            layer.weight.zero_()
            layer.bias.fill_(value)
        actions, log_prob, _ = actor.get_action(torch.zeros(1_000_000, OBS_DIM))
    edges = torch.linspace(0, 4, 201)
    hist = torch.histogram(actions[:, 0], bins=edges, density=True).hist
    bin_of = torch.bucketize(actions[:, 0].contiguous(), edges[1:-1])
    count = torch.bincount(bin_of, minlength=200)
    mean_density = torch.zeros(200).index_add_(0, bin_of, log_prob.exp()) / count.clamp(min=1)
    populated = count > 2000
    assert populated.sum() > 100
    torch.testing.assert_close(mean_density[populated], hist[populated], rtol=0.05, atol=0.0)
    assert hist.sum() * 0.02 == pytest.approx(1.0)


def test_actions_stay_in_bounds_and_the_deterministic_action_is_the_squashed_mean():
    actor = actor_with([0.3, -0.5], [0.0, 0.0])
    actions, _, deterministic = actor.get_action(torch.zeros(1000, OBS_DIM))
    assert (actions[:, 0].abs() <= 1).all() and (actions[:, 1] >= 0).all() and (actions[:, 1] <= 4).all()
    torch.testing.assert_close(deterministic[0], torch.tensor([np.tanh(0.3), 2 + 2 * np.tanh(-0.5)], dtype=torch.float32))


def test_log_std_is_kept_in_cleanrls_range():
    for raw, expected in [(-100.0, sac.LOG_STD_MIN), (100.0, sac.LOG_STD_MAX)]:
        _, log_std = actor_with([0.0, 0.0], [raw, raw])(torch.zeros(1, OBS_DIM))
        torch.testing.assert_close(log_std, torch.full_like(log_std, float(expected)))


class FixedPolicy:
    """A fake actor: a fixed next action and log-probability."""

    def __init__(self, log_prob):
        self.log_prob = log_prob

    def get_action(self, obs):
        return torch.zeros(len(obs), 2), self.log_prob, None


def test_target_subtracts_alpha_log_pi_from_the_min_and_bootstraps_unless_terminated():
    q = torch.tensor([[1.0, 5.0, -2.0], [3.0, 4.0, -3.0]])
    qf_target = lambda obs, actions: q  # noqa: E731
    log_pi = torch.tensor([-1.0, 2.0, 0.5])
    batch = Batch(
        torch.zeros(3, OBS_DIM),
        torch.zeros(3, 2),
        torch.zeros(3, OBS_DIM),
        torch.tensor([1.0, 0.0, 2.0]),
        torch.tensor([0.0, 0.0, 1.0]),
    )
    y = sac.td_target(batch, FixedPolicy(log_pi), qf_target, torch.tensor(0.5), sac.Args(gamma=0.9))
    expected = batch.rewards + 0.9 * (1 - batch.terminations) * (torch.tensor([1.0, 4.0, -3.0]) - 0.5 * log_pi)
    torch.testing.assert_close(y, expected)


@pytest.mark.parametrize("log_std_raw, direction", [(-1.0, +1), (0.458, -1)])
def test_alpha_rises_when_entropy_is_below_target_and_falls_above(log_std_raw, direction):
    """Raw -1 gives std ~ e^-3.3, an entropy far below the target -|A| = -2; raw 0.458 gives std ~ 1,
    a squashed distribution spread over the box, entropy far above."""
    torch.manual_seed(0)
    actor = actor_with([0.0, 0.0], [log_std_raw, log_std_raw])
    log_alpha = torch.zeros(1, requires_grad=True)
    optimizer = torch.optim.Adam([log_alpha], lr=0.01)
    batch = Batch(torch.zeros(256, OBS_DIM), None, None, None, None)
    for _ in range(10):  # main's alpha step: the loss, then optimize
        sac.optimize(sac.alpha_loss_fn(batch, actor, log_alpha, target_entropy=-2.0), "alpha_loss", optimizer)
    assert np.sign(log_alpha.item()) == direction and abs(log_alpha.item()) > 0.05


def test_actor_update_leaves_the_critic_alone_and_lowers_its_loss():
    torch.manual_seed(0)
    actor, qf = sac.Actor(OBS_DIM, SPACE), sac.QEnsemble(OBS_DIM, 2)
    optimizer = torch.optim.Adam(actor.parameters(), lr=1e-3)
    batch = Batch(torch.randn(128, OBS_DIM), None, None, None, None)
    before = [p.detach().clone() for p in qf.parameters()]
    losses = []
    qf.requires_grad_(False)  # main's actor step: the critics frozen, the loss, then optimize
    for _ in range(100):
        loss = sac.policy_loss(batch, actor, qf, torch.tensor(0.2))
        sac.optimize(loss, "actor_loss", optimizer)
        losses.append(loss.item())
    assert np.mean(losses[-10:]) < np.mean(losses[:10])
    assert all(p.grad is None for p in qf.parameters())
    assert all(torch.equal(a, b) for a, b in zip(before, qf.parameters()))


def test_evaluation_acts_with_the_squashed_mean(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = sac.main(
        small_args(
            sac,
            env_id="Pendulum-v1",
            total_timesteps=400,
            learning_starts=200,
            eval_frequency=400,
            eval_episodes=2,
            run_name="run",
        )
    )
    actor, env = result["actor"], make_env("Pendulum-v1", seed=101)
    by_hand = []
    for episode in range(2):
        obs, _ = env.reset(seed=101) if episode == 0 else env.reset()
        total, done = 0.0, False
        while not done:
            with torch.no_grad():  # the actor stays on the run's device (a GPU where there is one)
                mean, _ = actor(torch.as_tensor(obs, device=actor.action_scale.device))
            obs, reward, terminated, truncated, _ = env.step(
                (torch.tanh(mean) * actor.action_scale + actor.action_bias).cpu().numpy()
            )
            total, done = total + reward, terminated or truncated
        by_hand.append(total)
    assert result["eval_returns"][-1][1] == pytest.approx(np.mean(by_hand), abs=1e-6)


def test_autotune_off_keeps_alpha_fixed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = small_args(
        sac,
        env_id="Pendulum-v1",
        total_timesteps=400,
        learning_starts=200,
        eval_frequency=400,
        autotune=False,
        alpha=0.05,
        run_name="fixed",
    )
    assert sac.main(args)["alpha"] == pytest.approx(0.05)
    args = small_args(
        sac, env_id="Pendulum-v1", total_timesteps=400, learning_starts=200, eval_frequency=400, run_name="tuned"
    )
    assert sac.main(args)["alpha"] != pytest.approx(1.0)  # moved from its start value


def test_q_ensemble_members_are_independent_relu_mlps():
    assert_ensemble_is_independent_mlps(sac.QEnsemble(OBS_DIM, 2, num_q=3), OBS_DIM, 2, torch.relu)


def test_actor_loss_is_alpha_log_pi_minus_the_min_over_critics():
    torch.manual_seed(0)
    actor, qf = sac.Actor(OBS_DIM, SPACE), sac.QEnsemble(OBS_DIM, 2)
    batch = Batch(torch.randn(64, OBS_DIM), None, None, None, None)
    rng = torch.get_rng_state()
    loss = sac.policy_loss(batch, actor, qf, torch.tensor(0.2))
    torch.set_rng_state(rng)  # the same reparameterised samples
    with torch.no_grad():
        pi, log_pi, _ = actor.get_action(batch.observations)
        q = qf(batch.observations, pi)
    assert loss.item() == pytest.approx((0.2 * log_pi - q.min(0).values).mean().item(), rel=1e-5)
    assert abs(loss.item() - (0.2 * log_pi - q.mean(0)).mean().item()) > 1e-4  # not REDQ's mean


def test_critic_update_fits_both_critics_to_the_entropy_target_and_leaves_the_actor_alone():
    torch.manual_seed(0)
    actor, qf, qf_target = sac.Actor(OBS_DIM, SPACE), sac.QEnsemble(OBS_DIM, 2), sac.QEnsemble(OBS_DIM, 2)
    batch = Batch(torch.randn(32, OBS_DIM), torch.rand(32, 2), torch.randn(32, OBS_DIM), torch.randn(32), torch.zeros(32))
    optimizer, args, alpha = torch.optim.Adam(qf.parameters(), lr=1e-3), sac.Args(), torch.tensor(0.2)
    rng = torch.get_rng_state()
    loss, q_values = sac.critic_loss(batch, qf, actor, qf_target, alpha, args)
    torch.set_rng_state(rng)  # the same next actions
    target = sac.td_target(batch, actor, qf_target, alpha, args)
    assert loss.item() == pytest.approx(((q_values - target) ** 2).mean(1).sum().item(), rel=1e-5)  # both critics' MSE
    actor_before, target_before = [p.clone() for p in actor.parameters()], [p.clone() for p in qf_target.parameters()]
    losses = []
    for _ in range(50):  # main's critic step: the loss, then optimize
        loss, _ = sac.critic_loss(batch, qf, actor, qf_target, alpha, args)
        sac.optimize(loss, "qf_loss", optimizer)
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    for before, net in [(actor_before, actor), (target_before, qf_target)]:
        assert all(torch.equal(a, b) for a, b in zip(before, net.parameters()))


def test_acting_samples_from_the_policy():
    torch.manual_seed(0)
    actor = actor_with([0.0, 0.0], [0.0, 0.0])  # pre-squash mean 0: by symmetry the actions centre on the squashed mean
    obs = torch.randn(OBS_DIM)
    actions = torch.stack([sac.noisy_action(obs, actor) for _ in range(2000)])
    _, _, mean = actor.get_action(obs[None])
    torch.testing.assert_close(actions.mean(0), mean[0].detach(), atol=0.1, rtol=0)
    assert (actions.std(0) > 0.1 * actor.action_scale).all()  # spread: the policy's own noise, not its mean


@pytest.mark.parametrize("num_seeds", [1, 3])
def test_sampled_action_is_get_actions_bit_for_bit(num_seeds):
    """Acting skips the log-probability and deterministic action (sampled_action), yet acts and draws as get_action:
    the same actions bit for bit and the generator left in the same state, so training is unchanged by it; with
    several seeds too, where main acts through per_seed."""
    (actor,) = stack_seeds(lambda: [sac.Actor(OBS_DIM, SPACE)], list(range(num_seeds)), torch.device("cpu"))
    obs = torch.as_tensor(3 * np.random.default_rng(0).standard_normal((num_seeds, OBS_DIM), dtype=np.float32))
    torch.manual_seed(0)
    acted = torch.stack([per_seed(sac.noisy_action)(obs, actor) for _ in range(20)])
    state = torch.get_rng_state()
    torch.manual_seed(0)
    with torch.no_grad():
        sampled = torch.stack([per_seed(actor.get_action)(obs)[0] for _ in range(20)])
    assert acted.shape == (20, num_seeds, 2)
    assert torch.equal(acted, sampled) and acted.std(0).min() > 0  # every draw new, every one get_action's
    assert torch.equal(torch.get_rng_state(), state)
