"""The environment layer every script imports from rl_utils: MuJoCo and DeepMind Control, dtypes, episode ends,
one env per seed side by side (SeedEnvs), and the evaluation loop."""

import gymnasium as gym
import numpy as np
import pytest

from conftest import OFF_POLICY, load, small_args
from rl_utils import SeedEnvs, evaluate, fail, make_env


def test_dmc_dict_observation_is_flattened_to_float32():
    env = make_env("dm_control/walker-walk-v0", seed=0)
    raw = env.unwrapped.observation_space  # a Dict, with the scalar 'height' among its entries
    expected_dim = sum(int(np.prod(space.shape)) for space in raw.spaces.values())
    assert isinstance(raw, gym.spaces.Dict) and expected_dim == 24
    assert env.observation_space.shape == (expected_dim,) and env.observation_space.dtype == np.float32
    obs, _ = env.reset(seed=0)
    assert obs.shape == (expected_dim,) and obs.dtype == np.float32
    obs, *_ = env.step(env.action_space.sample())
    assert obs.dtype == np.float32


def test_dmc_float64_actions_are_exposed_as_float32_box():
    env = make_env("dm_control/cheetah-run-v0", seed=0)
    assert env.unwrapped.action_space.dtype == np.float64
    assert env.action_space.dtype == np.float32 and env.action_space.shape == (6,)
    np.testing.assert_array_equal(env.action_space.low, -1.0)
    np.testing.assert_array_equal(env.action_space.high, 1.0)
    env.reset(seed=0)
    env.step(np.ones(6, dtype=np.float32))  # a float32 action reaches dm_control as float64


def test_mujoco_observation_and_bounds():
    env = make_env("Hopper-v4", seed=0)
    assert env.observation_space.shape == (11,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (3,)
    obs, _ = env.reset(seed=0)
    assert obs.dtype == np.float32


def test_dmc_episode_ends_by_truncation_at_1000_steps():
    env = make_env("dm_control/cartpole-balance-v0", seed=0)
    env.reset(seed=0)
    ends = []
    for t in range(1000):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            ends.append((t, terminated, truncated))
    assert ends == [(999, False, True)]


def test_mujoco_fall_is_a_termination():
    env = make_env("Hopper-v4", seed=0)
    env.reset(seed=0)
    for t in range(1000):
        _, _, terminated, truncated, _ = env.step(np.ones(3, dtype=np.float32))  # full torque: it falls
        if terminated or truncated:
            break
    assert terminated and not truncated and t < 999


def test_action_space_sampling_is_seeded():
    a = make_env("Hopper-v4", seed=3).action_space.sample()
    b = make_env("Hopper-v4", seed=3).action_space.sample()
    c = make_env("Hopper-v4", seed=4).action_space.sample()
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize(
    "env_id, message",
    [
        ("Hoper-v4", "did you mean Hopper-v4"),
        ("dm_control/cartpole-swingupp-v0", "did you mean dm_control/cartpole-swingup-v0"),
        ("NoSuchThing-v0", "unknown --env-id 'NoSuchThing-v0'"),
        ("CartPole-v1", "Discrete action space"),
    ],
)
def test_bad_env_ids_are_rejected_with_a_hint(env_id, message):
    with pytest.raises(SystemExit, match=message):
        make_env(env_id, seed=0)


class UnboundedActions(gym.Env):
    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)

    def __init__(self, render_mode=None):
        self.render_mode = render_mode


def test_unbounded_actions_are_refused():
    if "UnboundedActions-v0" not in gym.registry:
        gym.register("UnboundedActions-v0", entry_point=UnboundedActions)
    with pytest.raises(SystemExit, match="has unbounded actions"):
        make_env("UnboundedActions-v0", seed=0)


def test_error_messages_are_one_line():
    with pytest.raises(SystemExit) as exit_info:
        fail("first line\nsecond   line")
    assert str(exit_info.value) == "error: first line second line"


# ---- one env per seed, side by side ------------------------------------------------------------------


def test_seed_envs_step_each_seeds_env_with_its_action_and_reset_where_an_episode_ends():
    """As SyncVectorEnv's same-step autoreset: an env whose episode ends returns the next episode's first observation,
    its true last one in infos["real_next_obs"], and its episode's statistics in infos["episode"]."""
    envs = SeedEnvs("Pendulum-v1", [1, 2])
    singles = [make_env("Pendulum-v1", seed) for seed in (1, 2)]  # the same envs, stepped one by one
    obs = envs.reset()
    np.testing.assert_array_equal(obs, np.stack([env.reset(seed=seed)[0] for env, seed in zip(singles, (1, 2))]))
    assert envs.obs_dim == 3 and envs.action_dim == 1
    rng = np.random.default_rng(0)
    for t in range(201):  # Pendulum's episodes are cut at 200 steps
        actions = rng.uniform(-2, 2, (2, 1)).astype(np.float32)
        next_obs, rewards, terminations, truncations, infos = envs.step(actions)
        expected = [env.step(action) for env, action in zip(singles, actions)]  # env k gets action k
        np.testing.assert_array_equal(infos["real_next_obs"], np.stack([e[0] for e in expected]))
        np.testing.assert_array_equal(rewards, [e[1] for e in expected])
        assert not terminations.any() and list(truncations) == [t == 199] * 2
        if t == 199:
            for k, env in enumerate(singles):
                assert infos["episode"][k]["l"] == 200 and infos["episode"][k]["r"] == pytest.approx(
                    expected[k][4]["episode"]["r"]
                )
                np.testing.assert_array_equal(next_obs[k], env.reset()[0])  # the next episode's first observation
        else:
            assert infos["episode"] == [None, None]
            np.testing.assert_array_equal(next_obs, infos["real_next_obs"])
    envs.close()


@pytest.mark.parametrize(
    "env_id, seeds, shape",
    [
        ("dm_control/walker-run-v0", [1], (6,)),  # one env's action (envs.action_space.sample()): DMC broadcast its first
        ("dm_control/walker-run-v0", [1, 2], (3,)),  # number to every actuator of each env zip reached
        ("dm_control/walker-run-v0", [1, 2], (2, 1, 6)),
        ("Pendulum-v1", [1, 2], (2, 2)),  # each env took its row's first number
        ("Pendulum-v1", [1, 2, 3], (2, 1)),  # zip left the third env out
    ],
)
def test_seed_envs_refuse_actions_that_are_not_one_row_per_seed_in_one_line(env_id, seeds, shape):
    envs = SeedEnvs(env_id, seeds)
    envs.reset()
    with pytest.raises(ValueError) as error:
        envs.step(np.zeros(shape, dtype=np.float32))
    expected = [len(seeds), envs.action_dim]
    assert str(error.value) == (
        f"SeedEnvs.step: actions have shape {list(shape)}, not [num_seeds, action_dim] = {expected}: one row per seed's "
        "env (random ones: envs.sample_actions(); envs.action_space is one env's)"
    )
    assert error.value.one_line
    envs.step(envs.sample_actions())  # the right shape still steps
    envs.close()


class Countdown(gym.Env):
    """Episodes of `length` steps whose reward is the action; records the seeds it is reset with and counts steps."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)
    action_space = gym.spaces.Box(-100.0, 100.0, (1,), np.float32)

    def __init__(self, length: int):
        self.length, self.reset_seeds, self.steps = length, [], 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.reset_seeds.append(seed)
        self.t = 0
        return np.array([self.length], dtype=np.float32), {}

    def step(self, action):
        self.t += 1
        self.steps += 1
        return np.array([self.length], dtype=np.float32), float(action[0]), False, self.t == self.length, {}


def test_evaluate_runs_each_seeds_episodes_to_their_end_and_reseeds_every_time():
    envs = [Countdown(2), Countdown(5)]
    seen = []

    def policy(obs):  # a batch of every env's observation; env 0 is given 1, env 1 is given 10
        seen.append(obs.shape)
        return np.where(obs == 2, 1.0, 10.0)

    for _ in range(2):
        returns = evaluate(policy, envs, [7, 8], num_episodes=3)
        np.testing.assert_array_equal(returns, [[2.0, 2.0, 2.0], [50.0, 50.0, 50.0]])
    assert set(seen) == {(2, 1)}
    # the short episodes' env waits for the long ones' (it is not stepped past its 3 episodes), and each
    # evaluation starts from the seeds: the same start states every time
    assert [env.steps for env in envs] == [2 * 6, 2 * 15]
    assert envs[0].reset_seeds == [7, None, None, 7, None, None]
    assert envs[1].reset_seeds == [8, None, None, 8, None, None]


@pytest.mark.parametrize("script", OFF_POLICY)
def test_buffer_holds_every_transition_with_its_true_final_observation(script, tmp_path, monkeypatch):
    """Pendulum's episodes are cut at 200 steps: the buffer must hold the real last observation of
    each episode (no reset observation in its place) and mark the cut as not terminated."""
    monkeypatch.chdir(tmp_path)
    algo = load(script)
    args = small_args(algo, env_id="Pendulum-v1", total_timesteps=450, learning_starts=1000, eval_frequency=450)
    rb = algo.main(args)["rb"]
    assert rb.size == 450
    batch = rb.storage[0, :450].split(rb.widths, dim=1)  # the one seed's rows, on the run's device (a GPU where there is one)
    obs, actions, next_obs, _, terminations = (field.cpu().numpy() for field in batch)
    assert not terminations.any()
    # replaying the stored actions from the same start reproduces every stored next observation
    env = make_env("Pendulum-v1", seed=args.seed)
    replay_obs, _ = env.reset(seed=args.seed)
    for t in range(450):
        np.testing.assert_allclose(obs[t], replay_obs, atol=1e-6)
        replay_obs, _, terminated, truncated, _ = env.step(actions[t])
        np.testing.assert_allclose(next_obs[t], replay_obs, atol=1e-6)
        if terminated or truncated:
            assert (t + 1) % 200 == 0
            replay_obs, _ = env.reset()
            assert not np.allclose(next_obs[t], obs[t + 1])
        elif t + 1 < 450:
            np.testing.assert_array_equal(next_obs[t], obs[t + 1])


def test_evaluate_refuses_a_policy_whose_actions_are_not_one_row_per_env():
    """A policy that squeezes the batch away ([action_dim] for one env) would hand the env a number."""
    with pytest.raises(ValueError) as error:
        evaluate(lambda obs: obs[0], [Countdown(2)], [7], num_episodes=1)
    assert str(error.value) == (
        "evaluate: the policy's actions have shape [1], not [num_seeds, action_dim] = [1, 1]: a policy maps observations "
        "[num_envs, obs_dim] to actions [num_envs, action_dim]; keep the batch dimension"
    )
    assert error.value.one_line


def test_seed_envs_refuse_ragged_actions_in_one_line():
    envs = SeedEnvs("Pendulum-v1", [1, 2])
    envs.reset()
    with pytest.raises(ValueError, match=r"^SeedEnvs.step: actions have shape ragged, not \[num_seeds, action_dim\]") as error:
        envs.step([np.zeros(1), np.zeros(2)])
    assert error.value.one_line


@pytest.mark.parametrize("action", [np.float32(0.3), np.zeros(5), np.zeros((1, 6))])
def test_every_env_refuses_an_action_without_its_shape_in_one_line(action):
    """The env make_env builds (PPO's, RND's, EBD's, each of SeedEnvs'): a DeepMind Control env took a number, or the
    first numbers of a longer action, for every actuator without a word."""
    env = make_env("dm_control/walker-run-v0", 1)
    env.reset(seed=1)
    with pytest.raises(ValueError) as error:
        env.step(action)
    assert str(error.value) == (
        f"env.step: an action of shape {list(np.shape(action))} for an env whose actions are [6]: one action a step"
    )
    assert error.value.one_line
    env.step(np.zeros(6, dtype=np.float32))  # its own shape still steps
