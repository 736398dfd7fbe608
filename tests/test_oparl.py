"""OPARL's mechanisms, each pinned so that changing it fails a test. The algorithm functions are written for one
seed (main runs them through rl_utils.per_seed); so are these tests, but for the candidate choice with several seeds."""

import gymnasium as gym
import numpy as np
import pytest
import torch

import oparl_continuous_action as oparl
from conftest import assert_ensemble_is_independent_mlps, scalars, small_args
from rl_utils import Batch, evaluate, make_env, per_seed, stack_seeds

OBS_DIM, ACTION_DIM = 3, 2
SPACE = gym.spaces.Box(-2.0, 2.0, (ACTION_DIM,), np.float32)


def batch_of(n, rewards, terminations):
    return Batch(torch.randn(n, OBS_DIM), torch.rand(n, ACTION_DIM), torch.randn(n, OBS_DIM), rewards, terminations)


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


def actor_step(batch, pessimistic, optimistic, optimizers, qf):
    """main's actor step: the critics frozen, both losses from one ensemble pass, one backward pass of their sum, both
    optimizers."""
    qf.requires_grad_(False)
    pessimistic_loss, optimistic_loss = oparl.policy_losses(batch, pessimistic, optimistic, qf)
    oparl.optimize(pessimistic_loss + optimistic_loss, "actor_loss", *optimizers)
    qf.requires_grad_(True)
    return pessimistic_loss.detach(), optimistic_loss.detach()


def test_pessimistic_loss_is_the_min_and_optimistic_loss_the_max():
    pessimistic, optimistic, qf, optimizers = make_actors()
    batch = batch_of(128, torch.zeros(128), torch.zeros(128))
    obs = batch.observations
    with torch.no_grad():
        q_pes, q_opt = qf(obs, pessimistic(obs)), qf(obs, optimistic(obs))
    pes_loss, opt_loss = oparl.policy_losses(batch, pessimistic, optimistic, qf)
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
    actor_step(batch, pessimistic, optimistic, optimizers, qf)
    assert seen.keys() == expected.keys()
    for key in expected:
        torch.testing.assert_close(seen[key], expected[key])


def test_actor_losses_never_touch_the_critic():
    pessimistic, optimistic, qf, optimizers = make_actors()
    before = params(qf)
    batch = batch_of(64, torch.zeros(64), torch.zeros(64))
    for _ in range(5):
        actor_step(batch, pessimistic, optimistic, optimizers, qf)
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
        actor_step(batch, pessimistic, optimistic, optimizers, qf)
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
        return torch.stack([actions[..., 0] * k for k in range(5)])  # [critics, candidates]


def test_candidate_with_the_largest_ensemble_std_is_taken():
    torch.manual_seed(0)
    actor = oparl.Actor(OBS_DIM, SPACE)
    obs = torch.randn(OBS_DIM)  # one observation
    args = oparl.Args(num_candidates=8, exploration_noise=0.5)
    with torch.no_grad():
        mean = actor(obs)  # the noiseless optimistic action
    for _ in range(20):
        rng_state = torch.get_rng_state()
        chosen = oparl.optimistic_action(obs, actor, SpreadByFirstAction(), args)
        torch.set_rng_state(rng_state)  # replay the same 8 candidates
        candidates = (mean + torch.randn(8, ACTION_DIM) * actor.action_scale * 0.5).clamp(-2, 2)
        assert torch.equal(chosen, candidates[candidates[:, 0].abs().argmax()])
        assert candidates[:, 0].abs().unique().numel() == 8  # a real choice among distinct candidates


def seed_networks(stacked: list, k: int, *fresh) -> list:
    """Seed k's networks out of stack_seeds' stacked ones, as plain single-seed networks (`fresh`, overwritten)."""
    for net, single in zip(stacked, fresh):
        single.load_state_dict({n: t[k] for n, t in net.state_dict().items()})  # parameters and buffers, stacked
    return list(fresh)


def test_each_seed_takes_the_candidate_its_own_critics_spread_most_on(monkeypatch):
    """With 3 seeds (networks stacked, optimistic_action run through per_seed, as main acts), each seed's action is
    the single-seed function's on that seed's own actor and critics, given the same candidates: the choice is made
    per seed, never one index for every seed or one seed's critics for all. (That the seeds draw different
    candidates is rl_utils.per_seed's, tests/test_many_seeds.py.)"""
    torch.manual_seed(0)
    networks = lambda: [oparl.Actor(OBS_DIM, SPACE), oparl.QEnsemble(OBS_DIM, ACTION_DIM, num_q=5)]  # noqa: E731
    stacked = stack_seeds(networks, [1, 2, 3], torch.device("cpu"))
    assert len(stacked[1]) == 5 and stacked[1][4].fc1.weight.shape[0] == 3  # 5 critics, each of 3 seeds
    singles = [seed_networks(stacked, k, *networks()) for k in range(3)]
    obs = torch.randn(3, OBS_DIM)
    args = oparl.Args(num_candidates=8, exploration_noise=0.5)
    choices, own_critics_matter = {0: [], 1: [], 2: []}, False
    for draw in range(20):
        torch.manual_seed(draw)
        chosen = per_seed(oparl.optimistic_action)(obs, *stacked, args)
        torch.manual_seed(draw)
        noise = torch.randn(3, 8, ACTION_DIM)  # the seeds' candidate noise, as vmap draws it: seed after seed
        for k, (actor, qf) in enumerate(singles):
            with monkeypatch.context() as patch, torch.no_grad():
                patch.setattr(torch, "randn_like", lambda x, seeds_noise=noise[k]: seeds_noise)  # the same candidates
                single_seed = oparl.optimistic_action(obs[k], actor, qf, args)
                candidates = (actor(obs[k]) + noise[k] * actor.action_scale * 0.5).clamp(-2, 2)
                # the candidate each seed's critics spread most on, among seed k's candidates
                best = [int(critics(obs[k].expand(8, -1), candidates).std(0).argmax()) for _, critics in singles]
            torch.testing.assert_close(chosen[k], single_seed, rtol=0, atol=1e-6)
            torch.testing.assert_close(chosen[k], candidates[best[k]], rtol=0, atol=1e-6)
            choices[k].append(best[k])
            own_critics_matter |= best != [best[k]] * 3
    assert own_critics_matter  # another seed's critics would have chosen otherwise: the test tells them apart
    assert len(set(choices[0])) > 1 and choices[0] != choices[1]  # not one index every time, nor for every seed


def test_one_candidate_is_the_noisy_optimistic_action():
    torch.manual_seed(0)
    actor = oparl.Actor(OBS_DIM, SPACE)
    obs = torch.randn(OBS_DIM)  # one observation
    args = oparl.Args(num_candidates=1, exploration_noise=0.1)
    actions = torch.stack([oparl.optimistic_action(obs, actor, None, args) for _ in range(2000)])  # no critic pass
    with torch.no_grad():
        torch.testing.assert_close(actions.mean(0), actor(obs), atol=0.02, rtol=0)
    torch.testing.assert_close(actions.std(0), torch.full((ACTION_DIM,), 0.2), atol=0.02, rtol=0)  # 0.1 * action scale 2


def test_release_critic_style():
    """The release's critics: SiLU, weights normal with std 1/(2 sqrt(fan_in)), zero biases; TD3's: ReLU and
    nn.Linear's init (uniform within 1/sqrt(fan_in), biases too)."""
    torch.manual_seed(0)
    qf = oparl.QEnsemble(300, 20, num_q=5, style="release")
    assert all(critic.activation is torch.nn.functional.silu for critic in qf)
    assert torch.stack([c.fc1.weight for c in qf]).std().item() == pytest.approx(0.5 / 320**0.5, rel=0.02)
    assert torch.stack([c.fc2.weight for c in qf]).std().item() == pytest.approx(0.5 / 256**0.5, rel=0.02)
    assert all(torch.equal(layer.bias, torch.zeros_like(layer.bias)) for c in qf for layer in (c.fc1, c.fc2, c.fc3))
    td3_style = oparl.QEnsemble(300, 20, num_q=5, style="td3")
    assert all(critic.activation is torch.nn.functional.relu for critic in td3_style)
    assert td3_style[0].fc1.bias.abs().max() > 0 and td3_style[0].fc2.weight.abs().max() <= 1 / 16


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
    env = make_env("Pendulum-v1", seed=101)
    logged = result["eval_returns"][-1][1]

    def noiseless(actor):  # the actor, as a policy; it stays on the run's device (a GPU where there is one)
        return lambda obs: actor(torch.as_tensor(obs, device=actor.action_scale.device)).detach().cpu().numpy()

    for _ in range(2):  # noiseless: the same returns every time
        assert evaluate(noiseless(result["actor"]), [env], [101], 2).mean() == pytest.approx(logged, abs=1e-9)
    assert evaluate(noiseless(result["optimistic_actor"]), [env], [101], 2).mean() != pytest.approx(logged, abs=1e-3)


def test_ablation_flags_change_what_they_say(tmp_path, monkeypatch):
    default = run(tmp_path, monkeypatch, "default")
    assert len(default["qf"]) == 5 and default["qf"][0].activation is torch.nn.functional.silu
    two = run(tmp_path, monkeypatch, "two", q_num=2)
    assert len(two["qf"]) == 2 and two["qf"][1].fc2.weight.shape == default["qf"][1].fc2.weight.shape
    relu = run(tmp_path, monkeypatch, "relu", critic_style="td3")
    assert relu["qf"][0].activation is torch.nn.functional.relu and len(relu["qf"]) == 5
    # optimistic only / pessimistic only are the ratio's ends, checked by test_realised_optimistic_share


def test_learning_starts_random_phase_ignores_both_actors(tmp_path, monkeypatch):
    a = run(tmp_path, monkeypatch, "a", total_timesteps=300, learning_starts=300, optimistic_ratio=1.0)
    b = run(tmp_path, monkeypatch, "b", total_timesteps=300, learning_starts=300, optimistic_ratio=0.0)
    assert torch.equal(a["rb"].storage, b["rb"].storage)
