"""Our OPARL against the authors' release, number for number: the same weights in the release's TD3
object and in the networks of our main, the same batch and the same target noise, one training iteration
each (the release's `train`, our main's `update`). Needs a checkout of
github.com/yydsok/OPARL (tools/authors_release.py says which commit) named by OPARL_RELEASE_DIR;
skipped without one. Also the adapter that runs the release: its dmc2gym stand-in and its loading."""

import importlib.util
import os
import sys

import numpy as np
import pytest
import torch

import oparl_continuous_action as oparl
from conftest import REPO
from rl_utils import Batch

sys.path.insert(0, os.path.join(REPO, "tools"))
import authors_release  # noqa: E402

RELEASE_DIR = os.environ.get("OPARL_RELEASE_DIR")
needs_release = pytest.mark.skipif(not RELEASE_DIR, reason="OPARL_RELEASE_DIR names no checkout of github.com/yydsok/OPARL")
# a task with several action dimensions in [-1, 1], the release's max_action = 1 (main.py: action_space.high[0])
ENV_ID, OBS_DIM, ACTION_DIM, BATCH, Q_NUM = "Hopper-v4", 11, 3, 32, 5


def release_td3():
    spec = importlib.util.spec_from_file_location("release_TD3", os.path.join(RELEASE_DIR, "TD3.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.device = torch.device("cpu")
    return module


def copy_critic(release_critic, ours: oparl.QEnsemble):
    """The release's EnsembleLinear layers ([N, in, out] weights, [N, 1, out] biases) into our QEnsemble's N critics
    (nn.Linear: [out, in] weights, [out] biases)."""
    (l1, l2), out = release_critic.backbones, release_critic.output_layer
    with torch.no_grad():
        for k, critic in enumerate(ours):
            for mine, theirs in [(critic.fc1, l1), (critic.fc2, l2), (critic.fc3, out)]:
                mine.weight.copy_(theirs.weight[k].T)
                mine.bias.copy_(theirs.bias[k, 0])


def copy_actor(release_actor, ours: oparl.Actor):
    ours.load_state_dict(
        {
            "fc1.weight": release_actor.l1.weight,
            "fc1.bias": release_actor.l1.bias,
            "fc2.weight": release_actor.l2.weight,
            "fc2.bias": release_actor.l2.bias,
            "fc_mu.weight": release_actor.l3.weight,
            "fc_mu.bias": release_actor.l3.bias,
            "action_scale": ours.action_scale,
            "action_bias": ours.action_bias,
            "action_low": ours.action_low,
            "action_high": ours.action_high,
        }
    )


@pytest.fixture
def both(tmp_path, monkeypatch):
    """The release's TD3 (its noise as main.py scales it) and the networks of our main (a run that has not trained
    yet, with its default flags), holding the same weights, and a batch."""
    module = release_td3()
    torch.manual_seed(0)
    policy = module.TD3(
        OBS_DIM, ACTION_DIM, max_action=1.0, policy_noise=0.2, noise_clip=0.5, policy_freq=2, reset_freq=20000, Q_num=Q_NUM
    )
    monkeypatch.chdir(tmp_path)
    args = oparl.Args(env_id=ENV_ID, total_timesteps=1, learning_starts=1, batch_size=BATCH, eval_episodes=1, cuda=False)
    result = oparl.main(args)
    ours = {
        "qf": result["qf"],
        "qf_target": result["qf_target"],
        "pessimistic": result["actor"],
        "pessimistic_target": result["target_actor"],
        "optimistic": result["optimistic_actor"],
    }
    assert len(ours["qf"]) == Q_NUM and ours["qf"][0].fc1.weight.shape == (256, OBS_DIM + ACTION_DIM)
    assert ours["pessimistic"].action_scale.tolist() == [1.0] * 3
    with torch.no_grad():  # targets apart from their sources, so that the target networks are really the ones used
        for p in [*policy.critic_target.parameters(), *policy.actor_target.parameters()]:
            p.add_(0.01 * torch.randn_like(p))
    copy_critic(policy.critic, ours["qf"])  # in place: main's update uses these very networks
    copy_critic(policy.critic_target, ours["qf_target"])
    copy_actor(policy.actor, ours["pessimistic"])
    copy_actor(policy.actor_target, ours["pessimistic_target"])
    copy_actor(policy.exit_actor, ours["optimistic"])
    g = torch.Generator().manual_seed(1)
    batch = Batch(
        torch.randn(BATCH, OBS_DIM, generator=g),
        torch.rand(BATCH, ACTION_DIM, generator=g) * 2 - 1,
        torch.randn(BATCH, OBS_DIM, generator=g),
        torch.randn(BATCH, generator=g),
        (torch.rand(BATCH, generator=g) < 0.2).float(),
    )
    return module, policy, ours, batch, result


class OneBatch:
    """The release's replay buffer, answering with our batch in its layout (rewards and not_done as columns)."""

    def __init__(self, batch):
        self.batch = batch

    def sample(self, batch_size):
        b = self.batch
        return b.observations, b.actions, b.next_observations, b.rewards[:, None], (1 - b.terminations)[:, None]


def release_actor_as_ours(release_actor) -> oparl.Actor:
    ours = oparl.Actor(OBS_DIM, oparl.gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32))
    copy_actor(release_actor, ours)
    return ours


@needs_release
def test_one_training_iteration_matches_the_release(both, monkeypatch):
    module, policy, ours, batch, result = both
    args = oparl.Args()  # main's defaults: the release's discount, tau, learning rate, target noise and its clip
    seen = {}
    real_mse = module.F.mse_loss

    def recording_mse(current, target):
        seen["current"], seen["target"] = current.detach().clone(), target.detach().clone()
        return real_mse(current, target)

    monkeypatch.setattr(module.F, "mse_loss", recording_mse)
    policy.total_it = 1  # this iteration (2) updates the actors, as every second one does
    # Adam's eps, 1e-8 in both, set negligible on both sides: our critic loss is Q_NUM times the release's,
    # and with eps the two steps differ where a gradient is itself ~1e-8 (30 of 10240 critic weights, by up
    # to 1.2e-4, in one draw); without it a constant factor cannot change an Adam step
    for optimizer in (policy.critic_optimizer, policy.actor_optimizer, policy.exit_actor_optimizer):
        optimizer.param_groups[0]["eps"] = 1e-30
    for name in ("q_optimizer", "actor_optimizer", "optimistic_optimizer"):  # main's, fused as it builds them
        assert result[name].param_groups[0]["lr"] == policy.critic_optimizer.param_groups[0]["lr"]
        result[name].param_groups[0]["eps"] = 1e-30
    torch.manual_seed(7)  # the target noise: the release's first draw, as ours is, of the actions' shape
    released = policy.train(OneBatch(batch), BATCH)

    torch.manual_seed(7)
    target = oparl.td_target(batch, ours["pessimistic_target"], ours["qf_target"], args)
    assert not torch.equal(target, oparl.td_target(batch, ours["pessimistic_target"], ours["qf_target"], args))  # noisy
    torch.testing.assert_close(target, seen["target"][0, :, 0], rtol=1e-5, atol=1e-5)  # the TD target, noise and all
    for member in range(1, Q_NUM):  # every member learns toward the same target
        torch.testing.assert_close(seen["target"][member], seen["target"][0])

    torch.manual_seed(7)  # main's training iteration (an actor step: policy_step), on the same batch and noise
    logs = result["update"](Batch(*(field[None] for field in batch)), True)
    # main logs the members' mean MSE, as the release computes it (the loss it steps on sums them: a factor of
    # Q_NUM, which Adam's step does not see)
    assert logs["losses/qf_loss"].item() == pytest.approx(released["critic_loss"], rel=1e-5)
    # both actor losses come after the critic's step, in the release as here
    assert logs["losses/pessimistic_actor_loss"].item() == pytest.approx(released["actor_loss"], rel=1e-4, abs=1e-6)
    assert logs["losses/optimistic_actor_loss"].item() == pytest.approx(released["exit_actor_loss"], rel=1e-4, abs=1e-6)

    expected = {"qf": oparl.QEnsemble(OBS_DIM, ACTION_DIM, Q_NUM), "qf_target": oparl.QEnsemble(OBS_DIM, ACTION_DIM, Q_NUM)}
    copy_critic(policy.critic, expected["qf"])
    copy_critic(policy.critic_target, expected["qf_target"])
    expected["pessimistic"] = release_actor_as_ours(policy.actor)
    expected["optimistic"] = release_actor_as_ours(policy.exit_actor)
    expected["pessimistic_target"] = release_actor_as_ours(policy.actor_target)
    # the critic after its Adam step, both actors after theirs, and the Polyak-averaged targets
    for name, net in expected.items():
        for (param, mine), theirs in zip(ours[name].named_parameters(), net.parameters()):
            torch.testing.assert_close(mine, theirs, rtol=1e-4, atol=1e-6, msg=lambda m, n=f"{name}.{param}": f"{n}: {m}")


@needs_release
def test_the_release_resets_by_copying_the_pessimistic_actor_into_the_optimistic_one(both):
    # the direction this repository follows (pi_opt <- pi_pes, Section 4.3), against Algorithm 1's reverse
    _, policy, _, batch, _ = both
    policy.total_it, policy.policy_freq = 20000 - 1, 10**9  # the next iteration resets; no actor step in it
    pessimistic_before = policy.actor.l1.weight.detach().clone()
    assert not torch.equal(policy.exit_actor.l1.weight, pessimistic_before)
    policy.train(OneBatch(batch), BATCH)
    torch.testing.assert_close(policy.exit_actor.l1.weight, pessimistic_before)
    torch.testing.assert_close(policy.actor.l1.weight, pessimistic_before)


@needs_release
def test_the_optimistic_candidate_choice_matches_the_release(both):
    _, policy, ours, _, _ = both
    obs = torch.randn(OBS_DIM)
    args = oparl.Args(num_candidates=10, exploration_noise=0.5)
    with torch.no_grad():
        mean = ours["optimistic"](obs)
    chosen_indices = set()
    for seed in range(20):
        torch.manual_seed(seed)
        chosen = oparl.optimistic_action(obs, ours["optimistic"], ours["qf"], args)
        torch.manual_seed(seed)  # the same ten candidates, as optimistic_action draws them (action scale 1)
        candidates = (mean.expand(10, -1) + torch.randn(10, ACTION_DIM) * 0.5).clamp(-1, 1)
        # the release's rule (main.py): the population std of each candidate's N Q-values, the first strictly largest wins
        with torch.no_grad():
            q = policy.critic(obs.expand(10, -1), candidates)[:, :, 0].T.tolist()
        best, best_std = 0, 0.0
        for index, values in enumerate(q):
            if np.std(values) > best_std:
                best, best_std = index, np.std(values)
        torch.testing.assert_close(chosen, candidates[best])
        chosen_indices.add(best)
    assert len(chosen_indices) > 1  # a real choice, not always the same candidate


def test_the_dmc2gym_stand_in_behaves_as_dmc2gym():
    env = authors_release.dmc2gym_module().make(
        domain_name="cartpole", task_name="swingup", seed=3, from_pixels=False, visualize_reward=False
    )
    again = authors_release.DMCEnv("cartpole", "swingup", seed=3)
    obs = env.reset()
    assert obs.dtype == np.float64 and obs.shape == env.observation_space.shape == (5,)
    np.testing.assert_array_equal(obs, again.reset())  # the physics generator comes from the seed at load
    assert env.action_space.low.tolist() == [-1.0] and env.action_space.high.tolist() == [1.0]
    env.seed(7)
    first = env.action_space.sample()
    env.seed(7)  # seed() re-seeds the spaces, and leaves the physics alone
    assert np.array_equal(first, env.action_space.sample())
    with pytest.raises(AssertionError):
        env.step(np.array([1.5]))
    steps, done = 0, False
    while not done:
        obs, reward, done, info = env.step(np.array([0.3]))
        steps += 1
        assert 0.0 <= reward <= 1.0 and info["discount"] == 1.0
    assert steps == env._max_episode_steps == 1000


def test_actions_are_rescaled_from_minus_one_one_to_the_tasks_bounds():
    env = authors_release.DMCEnv("cartpole", "swingup", seed=0)
    env._low, env._high = np.array([-2.0]), np.array([6.0])  # a task with other bounds
    sent = []
    env._env.step = lambda action: sent.append(action) or env._env.reset()
    env.reset()
    env.step(np.array([-1.0]))
    env.step(np.array([0.5]))
    assert [a.tolist() for a in sent] == [[-2.0], [4.0]]


def test_main_is_loaded_with_its_cuda_calls_on_td3s_device(tmp_path):
    source = "import TD3\nx.to('cuda')\ny.to('cuda')\n"
    (tmp_path / "main.py").write_text(source)
    loaded = authors_release.release_main_source(str(tmp_path))
    assert ".to('cuda')" not in loaded and loaded.count(".to(TD3.device)") == 2
    (tmp_path / "main.py").write_text("x.to('cuda')\n")  # another version of the file: refused, not half-adapted
    with pytest.raises(SystemExit, match="expected 2 calls"):
        authors_release.release_main_source(str(tmp_path))


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--release-dir", "nowhere"], "--release-dir nowhere: no main.py"),
        (["--env-id", "Hopper-v4"], "the release runs DeepMind Control tasks only"),
        (["--env-id", "dm_control/walker-fly-v0"], "dm_control has no task walker-fly"),
    ],
)
def test_bad_input_is_refused_in_one_line(flags, message, tmp_path):
    release = tmp_path / "release"
    release.mkdir()
    for name in ("main.py", "TD3.py", "utils.py"):
        (release / name).write_text("")
    argv = ["--release-dir", str(release), *flags] if flags[0] != "--release-dir" else flags
    with pytest.raises(SystemExit) as exit_info:
        authors_release.main(argv)
    assert str(exit_info.value).startswith("error: ") and message in str(exit_info.value)


def test_the_releases_evaluations_are_read_from_its_log_step_zero_included(tmp_path):
    (tmp_path / "seed=2_result.txt").write_text(
        "policy:TD3 Domain: walker Task: walk seed:2 policy_utd:1 policy_interval:1 reset_freq:20000 qnum:5 N:1 bili:2\n"
        "Timesteps 0 Evaluation over 10 episodes: 4.968\nTimesteps 5000 Evaluation over 10 episodes: -12.500\n"
    )
    evaluated = authors_release.evaluations(str(tmp_path), seed=2)
    assert evaluated == [(0, 4.968), (5000, -12.5)]
    authors_release.write_eval_series(str(tmp_path / "eval_series.csv"), "dm_control/walker-walk-v0", 2, evaluated)
    assert (tmp_path / "eval_series.csv").read_text().splitlines() == [
        "algo,env_id,seed,step,episodic_return",
        "oparl_release,dm_control/walker-walk-v0,2,0,4.9680",
        "oparl_release,dm_control/walker-walk-v0,2,5000,-12.5000",
    ]
    with pytest.raises(SystemExit, match="holds no evaluation"):
        authors_release.evaluations(str(tmp_path), seed=3)
