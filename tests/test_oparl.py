"""OPARL's mechanisms, each pinned so that changing it fails a test."""

import gymnasium as gym
import numpy as np
import pytest
import torch

import oparl_continuous_action as oparl
from conftest import assert_ensemble_is_independent_mlps, scalars, small_args

OBS_DIM, ACTION_DIM = 3, 2
SPACE = gym.spaces.Box(-2.0, 2.0, (ACTION_DIM,), np.float32)


def batch_of(n, rewards, terminations):
    return oparl.Batch(torch.randn(n, OBS_DIM), torch.rand(n, ACTION_DIM), torch.randn(n, OBS_DIM), rewards, terminations)


def test_td_target_takes_the_min_over_all_members():
    torch.manual_seed(0)
    qf_target, target_actor = oparl.QEnsemble(OBS_DIM, ACTION_DIM, num_q=5), oparl.Actor(OBS_DIM, SPACE)
    batch = batch_of(64, torch.randn(64), (torch.rand(64) < 0.3).float())
    args = oparl.Args(policy_noise=0.0)
    y = oparl.td_target(batch, target_actor, qf_target, args)
    with torch.no_grad():
        q = qf_target(batch.next_observations, target_actor(batch.next_observations))  # [5, 64]
    assert q.argmin(0).unique().numel() > 2  # the min is spread over several members
    torch.testing.assert_close(y, batch.rewards + 0.99 * (1 - batch.terminations) * q.min(0).values)


def test_td_target_noise_is_clipped_scaled_and_kept_in_bounds():
    """The target policy smoothing of TD3 in OPARL's own target: noise ~ N(0, policy_noise), clipped to
    +-noise_clip, times the action scale, added to the target actor's action and clamped to the bounds."""
    torch.manual_seed(0)
    actor = oparl.Actor(OBS_DIM, SPACE)  # bounds +-2: action scale 2
    with torch.no_grad():
        actor.fc_mu.weight.zero_()
        actor.fc_mu.bias.copy_(torch.tensor([0.0, 100.0]))  # acts [0, 2]: the middle, and the upper bound
    seen = {}

    def ensemble(obs, actions):
        seen["actions"] = actions
        return torch.zeros(5, len(actions))

    args = oparl.Args(policy_noise=10.0, noise_clip=0.5)
    oparl.td_target(batch_of(4096, torch.zeros(4096), torch.zeros(4096)), actor, ensemble, args)
    first, second = seen["actions"][:, 0], seen["actions"][:, 1]
    assert first.abs().max() == pytest.approx(1.0)  # clip 0.5 times scale 2
    assert first.std() > 0.5  # noisy, not constant
    assert second.max() == 2.0 and second.min() == pytest.approx(1.0)  # clamped at the bound, noise below it


def test_q_ensemble_members_are_independent_mlps_with_the_styles_activation():
    torch.manual_seed(0)
    for style, activation in (("release", torch.nn.functional.silu), ("td3", torch.nn.functional.relu)):
        qf = oparl.QEnsemble(OBS_DIM, ACTION_DIM, num_q=3, style=style)
        assert_ensemble_is_independent_mlps(qf, OBS_DIM, ACTION_DIM, activation)


def make_actors():
    torch.manual_seed(1)
    pessimistic, optimistic = oparl.Actor(OBS_DIM, SPACE), oparl.Actor(OBS_DIM, SPACE)
    qf = oparl.QEnsemble(OBS_DIM, ACTION_DIM, num_q=5)
    optimizers = [torch.optim.Adam(a.parameters(), lr=1e-3) for a in (pessimistic, optimistic)]
    return pessimistic, optimistic, qf, optimizers


def params(net):
    return [p.detach().clone() for p in net.parameters()]


def test_pessimistic_loss_is_the_min_and_optimistic_loss_the_max():
    pessimistic, optimistic, qf, optimizers = make_actors()
    batch = batch_of(128, torch.zeros(128), torch.zeros(128))
    obs = batch.observations
    with torch.no_grad():
        q_pes, q_opt = qf(obs, pessimistic(obs)), qf(obs, optimistic(obs))
    pes_loss, opt_loss = oparl.update_actors(batch, pessimistic, optimistic, *optimizers, qf)
    assert pes_loss.item() == pytest.approx(-q_pes.min(0).values.mean().item(), rel=1e-5)
    assert opt_loss.item() == pytest.approx(-q_opt.max(0).values.mean().item(), rel=1e-5)
    assert abs(pes_loss.item() + q_pes.mean().item()) > 1e-3  # distinguishable from the mean


def test_each_actor_gets_only_its_own_loss_gradient():
    pessimistic, optimistic, qf, optimizers = make_actors()
    batch = batch_of(128, torch.zeros(128), torch.zeros(128))
    obs = batch.observations
    expected = {}
    for name, actor, reduce in [
        ("pes", pessimistic, lambda q: q.min(0).values),
        ("opt", optimistic, lambda q: q.max(0).values),
    ]:
        (-reduce(qf(obs, actor(obs))).mean()).backward()  # this actor's loss alone
        expected.update({(name, n): p.grad.clone() for n, p in actor.named_parameters()})
        actor.zero_grad(set_to_none=True)
    qf.zero_grad(set_to_none=True)
    seen = {}
    for name, actor in [("pes", pessimistic), ("opt", optimistic)]:
        for n, p in actor.named_parameters():
            p.register_hook(lambda g, key=(name, n): seen.__setitem__(key, g.clone()))
    oparl.update_actors(batch, pessimistic, optimistic, *optimizers, qf)
    assert seen.keys() == expected.keys()
    for key in expected:
        torch.testing.assert_close(seen[key], expected[key])


def test_actor_losses_never_touch_the_critic():
    pessimistic, optimistic, qf, optimizers = make_actors()
    before = params(qf)
    batch = batch_of(64, torch.zeros(64), torch.zeros(64))
    for _ in range(5):
        oparl.update_actors(batch, pessimistic, optimistic, *optimizers, qf)
    assert all(p.grad is None for p in qf.parameters())
    for a, b in zip(before, qf.parameters()):
        assert torch.equal(a, b)


def test_actors_climb_their_own_objective():
    pessimistic, optimistic, qf, optimizers = make_actors()
    batch = batch_of(256, torch.zeros(256), torch.zeros(256))
    obs = batch.observations

    def objectives():
        with torch.no_grad():
            return qf(obs, pessimistic(obs)).min(0).values.mean(), qf(obs, optimistic(obs)).max(0).values.mean()

    pes_before, opt_before = objectives()
    for _ in range(50):
        oparl.update_actors(batch, pessimistic, optimistic, *optimizers, qf)
    pes_after, opt_after = objectives()
    assert pes_after > pes_before and opt_after > opt_before


@pytest.mark.parametrize("ratio", [0.0, 0.25, 0.3, 0.5, 0.7, 1.0])
def test_optimistic_steps_are_spread_evenly_at_the_requested_share(ratio):
    for start in (0, 25000, 12345):
        flags = [oparl.is_optimistic_step(t, ratio) for t in range(start, start + 1000)]
        for n in (1, 7, 100, 1000):
            assert abs(sum(flags[:n]) / n - ratio) <= 1 / n + 1e-9
        # never two optimistic steps in a row below 0.5, never two pessimistic ones above it
        pairs = list(zip(flags, flags[1:]))
        if ratio <= 0.5:
            assert (True, True) not in pairs
        if ratio >= 0.5:
            assert (False, False) not in pairs


def test_half_ratio_alternates_as_the_release_pessimistic_on_even_steps():
    assert [oparl.is_optimistic_step(t, 0.5) for t in range(25000, 25006)] == [False, True, False, True, False, True]


class SpreadByFirstAction:
    """A fake ensemble whose members disagree in proportion to |action[0]|."""

    def __call__(self, obs, actions):
        return torch.stack([actions[..., 0] * k for k in range(5)], -2)  # [seeds, critics, candidates]


def test_candidate_with_the_largest_ensemble_std_is_taken():
    torch.manual_seed(0)
    actor = oparl.Actor(OBS_DIM, SPACE)
    obs = torch.randn(1, OBS_DIM)  # one seed
    for _ in range(20):
        rng_state = torch.get_rng_state()
        chosen = oparl.optimistic_action(obs, actor, SpreadByFirstAction(), 8, 0.5, None)
        torch.set_rng_state(rng_state)  # replay the same 8 candidates
        with torch.no_grad():
            candidates = (actor(obs).expand(8, -1) + torch.normal(0, actor.action_scale.expand(8, -1) * 0.5)).clamp(-2, 2)
        assert torch.equal(chosen[0], candidates[candidates[:, 0].abs().argmax()])
        assert candidates[:, 0].abs().unique().numel() == 8  # a real choice among distinct candidates


class SpreadPerSeed:
    """A fake 3-seed ensemble whose members disagree by another function of the action in each seed."""

    @staticmethod
    def key(k, actions):  # seed k's spread of actions [..., ACTION_DIM], up to a constant factor
        return [actions[..., 0], actions[..., 1], actions[..., 0] - actions[..., 1]][k]

    def __call__(self, obs, actions):
        keys = torch.stack([self.key(k, actions[k]) for k in range(3)])  # [seeds, candidates]
        return torch.stack([keys * m for m in range(5)], -2)  # [seeds, critics, candidates]


def test_each_seed_of_a_process_takes_its_own_best_candidate():
    """With 3 seeds, each seed draws its candidates from its own generator and takes the one its own critics spread
    most on: the choice is made per seed, never one index for every seed or one seed's spread for all."""
    actor = oparl.Actor(OBS_DIM, SPACE, [torch.Generator().manual_seed(s) for s in (1, 2, 3)])
    obs = torch.randn(3, OBS_DIM, generator=torch.Generator().manual_seed(0))
    generators = [torch.Generator().manual_seed(s) for s in (11, 12, 13)]
    with torch.no_grad():
        means = actor(obs)  # each seed's noiseless optimistic action
    indices = []
    for _ in range(20):
        states = [g.get_state() for g in generators]
        chosen = oparl.optimistic_action(obs, actor, SpreadPerSeed(), 8, 0.5, generators)
        for k, state in enumerate(states):  # seed k's 8 candidates, replayed from its generator
            noise = torch.randn(8, ACTION_DIM, generator=torch.Generator().set_state(state))
            candidates = (means[k] + noise * actor.action_scale * 0.5).clamp(-2, 2)
            best = SpreadPerSeed.key(k, candidates).abs().argmax()
            assert torch.equal(chosen[k], candidates[best])
            indices.append(best.item())
    assert len(set(indices[0::3])) > 1 and indices[0::3] != indices[1::3]  # the seeds' choices differ


def test_one_candidate_is_the_noisy_optimistic_action():
    torch.manual_seed(0)
    actor = oparl.Actor(OBS_DIM, SPACE)
    obs = torch.randn(1, OBS_DIM)  # one seed
    actions = torch.stack([oparl.optimistic_action(obs, actor, None, 1, 0.1, None)[0] for _ in range(2000)])
    with torch.no_grad():
        torch.testing.assert_close(actions.mean(0), actor(obs)[0], atol=0.02, rtol=0)
    torch.testing.assert_close(actions.std(0), torch.full((ACTION_DIM,), 0.2), atol=0.02, rtol=0)  # 0.1 * action scale 2


def test_release_critic_style():
    torch.manual_seed(0)
    qf = oparl.QEnsemble(300, 20, num_q=5, hidden=256, style="release")
    assert qf.activation is torch.nn.functional.silu
    assert qf.w1.std().item() == pytest.approx(0.5 / 320**0.5, rel=0.02)
    assert qf.w2.std().item() == pytest.approx(0.5 / 256**0.5, rel=0.02)
    assert all(torch.equal(b, torch.zeros_like(b)) for b in (qf.b1, qf.b2, qf.b3))
    td3_style = oparl.QEnsemble(300, 20, num_q=5, hidden=256, style="td3")
    assert td3_style.activation is torch.nn.functional.relu
    assert td3_style.b1.abs().max() > 0 and td3_style.w2.abs().max() <= 1 / 16


def run(tmp_path, monkeypatch, name, **overrides):
    monkeypatch.chdir(tmp_path)
    defaults = dict(
        env_id="Pendulum-v1", total_timesteps=600, learning_starts=300, batch_size=32, eval_frequency=600, run_name=name
    )
    return oparl.main(small_args(oparl, **{**defaults, **overrides}))


def same(net_a, net_b):
    return all(torch.equal(a, b) for a, b in zip(net_a.parameters(), net_b.parameters()))


def test_reset_copies_the_pessimistic_actor_into_the_optimistic_one_every_period(tmp_path, monkeypatch):
    # 300 training iterations; the last one (global step 599) has no actor update after its reset
    never = run(tmp_path, monkeypatch, "never", reset_frequency=0)
    at_300 = run(tmp_path, monkeypatch, "at_300", reset_frequency=300)
    at_301 = run(tmp_path, monkeypatch, "at_301", reset_frequency=301)
    assert not same(never["optimistic_actor"], never["actor"])
    # the reset at iteration 300 copied pessimistic -> optimistic and left the pessimistic actor alone
    assert same(at_300["actor"], never["actor"])
    assert same(at_300["optimistic_actor"], never["actor"])
    # no reset before iteration 300, and none at all with a longer period
    assert same(at_301["optimistic_actor"], never["optimistic_actor"]) and same(at_301["actor"], never["actor"])
    run(tmp_path, monkeypatch, "at_100", reset_frequency=100)
    assert dict(scalars("runs/at_100")["charts/resets"])[500] == 2  # iteration 201 at global step 500


@pytest.mark.parametrize("ratio", [0.0, 0.5, 1.0])
def test_realised_optimistic_share(ratio, tmp_path, monkeypatch):
    run(tmp_path, monkeypatch, "share", optimistic_ratio=ratio, total_timesteps=800)
    step, share = scalars("runs/share")["charts/optimistic_share"][-1]
    assert step == 700 and share == pytest.approx(ratio, abs=1 / (step + 1 - 300))


def test_evaluation_uses_the_pessimistic_actor_without_noise(tmp_path, monkeypatch):
    result = run(tmp_path, monkeypatch, "eval", exploration_noise=0.5, eval_episodes=2)
    env = oparl.make_env("Pendulum-v1", seed=101)
    logged = result["eval_returns"][-1][1]
    for _ in range(2):  # noiseless: the same returns every time
        assert oparl.evaluate(result["actor"], [env], 2, [101]).mean() == pytest.approx(logged, abs=1e-9)
    assert oparl.evaluate(result["optimistic_actor"], [env], 2, [101]).mean() != pytest.approx(logged, abs=1e-3)


def test_ablation_flags_change_what_they_say(tmp_path, monkeypatch):
    default = run(tmp_path, monkeypatch, "default")
    assert default["qf"].w1.shape[0] == 5 and default["qf"].activation is torch.nn.functional.silu
    two = run(tmp_path, monkeypatch, "two", q_num=2)
    assert two["qf"].w1.shape[0] == 2 and two["qf"].w2.shape[1:] == default["qf"].w2.shape[1:]
    relu = run(tmp_path, monkeypatch, "relu", critic_style="td3")
    assert relu["qf"].activation is torch.nn.functional.relu and relu["qf"].w1.shape[0] == 5
    # optimistic only / pessimistic only are the ratio's ends, checked by test_realised_optimistic_share


def test_learning_starts_random_phase_ignores_both_actors(tmp_path, monkeypatch):
    a = run(tmp_path, monkeypatch, "a", total_timesteps=300, learning_starts=300, optimistic_ratio=1.0)
    b = run(tmp_path, monkeypatch, "b", total_timesteps=300, learning_starts=300, optimistic_ratio=0.0)
    assert torch.equal(a["rb"].storage, b["rb"].storage)
