"""The environment layer: Gymnasium MuJoCo tasks and DeepMind Control tasks (`dm_control/<domain>-<task>-v0`,
through shimmy) as plain environments with flat float32 observations and float32 Box actions; one per seed, stepped
side by side (`SeedEnvs`); and the deterministic evaluation every script reports (`evaluate`)."""

import difflib
from typing import NamedTuple, Optional

import gymnasium as gym
import numpy as np
import torch

from rl_utils.checkpoints import EpisodeRecord
from rl_utils.errors import fail, refusal
from rl_utils.seeds import python_draws, same_state


def float32_box(space: gym.spaces.Box) -> gym.spaces.Box:
    return gym.spaces.Box(space.low.astype(np.float32), space.high.astype(np.float32), dtype=np.float32)


def make_env(env_id: str, seed: int, video_folder: Optional[str] = None, video_every: int = 1):
    """One environment with a flat float32 observation and a float32 Box action space.

    A plain (not vectorised) env: the loop sees the true final observation of every episode and
    resets itself, so no autoreset step can end up in the replay buffer."""
    if env_id.startswith("dm_control/"):
        import shimmy  # registers the DeepMind Control tasks as dm_control/<domain>-<task>-v0

        gym.register_envs(shimmy)
    if env_id not in gym.registry:
        close = difflib.get_close_matches(env_id, list(gym.registry), n=3, cutoff=0.6)
        hint = f"did you mean {', '.join(close)}?" if close else "use e.g. Hopper-v4 or dm_control/cartpole-swingup-v0"
        fail(f"unknown --env-id {env_id!r}; {hint}")
    try:
        env = gym.make(env_id, render_mode="rgb_array" if video_folder else None)
    except Exception as e:  # a registered id whose dependencies are missing, e.g. Hopper-v3 (mujoco-py)
        fail(f"could not create --env-id {env_id!r}: {type(e).__name__}: {e}")
    if not isinstance(env.action_space, gym.spaces.Box):
        space = type(env.action_space).__name__
        fail(f"--env-id {env_id!r} has a {space} action space; only continuous (Box) actions are supported")
    if not (np.isfinite(env.action_space.low).all() and np.isfinite(env.action_space.high).all()):
        fail(f"--env-id {env_id!r} has unbounded actions; the policies here act within finite bounds")
    if isinstance(env.observation_space, gym.spaces.Dict):  # DeepMind Control observations are dicts of arrays
        env = gym.wrappers.FlattenObservation(env)
    env = gym.wrappers.TransformObservation(env, lambda obs: obs.astype(np.float32), float32_box(env.observation_space))
    if env.action_space.dtype != np.float32:  # DeepMind Control declares float64 actions
        to_env_dtype = lambda action, dtype=env.action_space.dtype: np.asarray(action, dtype=dtype)  # noqa: E731
        env = gym.wrappers.TransformAction(env, to_env_dtype, float32_box(env.action_space))
    env = gym.wrappers.RecordEpisodeStatistics(env)
    if video_folder:
        env = gym.wrappers.RecordVideo(env, video_folder, episode_trigger=lambda episode: episode % video_every == 0)
    env = EpisodeRecord(env)
    env.action_space.seed(seed)
    return env


SEED_ENVS_HINT = "one row per seed's env (random ones: envs.sample_actions(); envs.action_space is one env's)"
EVALUATE_HINT = "a policy maps observations [num_envs, obs_dim] to actions [num_envs, action_dim]; keep the batch dimension"


class StepObservations(np.ndarray):
    """Observations [num_seeds, obs_dim] as `SeedEnvs.step` returns them, next_obs and infos["real_next_obs"], marked
    with `truncated` (the rows whose episode its time limit cut, not ended: they bootstrap) for `ReplayBuffer.add`'s
    check of terminations. An array of the same shape made from it keeps the mark (`next_obs.copy()`, `.astype`, but
    also `np.zeros_like`); `np.asarray`, `np.array` and what NumPy computes from it give plain arrays without it."""

    truncated = None

    def __array_finalize__(self, source):
        if getattr(source, "shape", None) == self.shape:
            self.truncated = getattr(source, "truncated", None)

    def __repr__(self):
        return repr(self.view(np.ndarray))

    def __array_wrap__(self, array, context=None, return_scalar=False):
        """What NumPy computes from it (a sum, `obs * 2`) is a plain array or number; an in-place update keeps it."""
        if array is self:
            return self
        array = array.view(np.ndarray)
        return array[()] if return_scalar else array


def marked(observations: np.ndarray, truncated: np.ndarray) -> StepObservations:
    observations = observations.view(StepObservations)
    observations.truncated = truncated
    return observations


class EpisodeEnds(NamedTuple):
    """Where the latest `SeedEnvs.step` ended episodes: the shape of its next_obs, the seed indices, the next episode's
    first observations it returned for them in next_obs, and the observations the step led to. `ReplayBuffer.add`
    refuses a next_obs whose rows are the former, whatever array holds them (the one returned, or a copy), where they
    are stored as not terminated."""

    shape: tuple
    rows: np.ndarray
    first_observations: np.ndarray
    real_next_observations: np.ndarray
    step: int  # steps_taken at that step
    rewards: np.ndarray  # every seed's, float32: an add of this step's transition stores them
    cut: np.ndarray  # for each of `rows`, whether its time limit cut the episode (truncated, not terminated)


latest_episode_ends: Optional[EpisodeEnds] = None
steps_taken = 0  # SeedEnvs.step calls in the process: which step a record is of

# with several seeds, the steps of SeedEnvs between two looks at Python's and NumPy's global generators
DRAWS_EVERY = 100


class OneEnvsActionSpace(gym.spaces.Box):
    """SeedEnvs.action_space with several seeds: one env's bounds, as the networks read them. Its draws would all come
    from one generator, not each seed's env's (CleanRL's `envs.action_space.sample()`, one per seed in a list): refused,
    naming envs.sample_actions()."""

    def sample(self, *args, **kwargs):
        raise refusal(
            RuntimeError,
            f"envs.action_space.sample() with {self.num_seeds} seeds: envs.action_space is one env's bounds, and its "
            "draws would come from one generator for every seed, not from each seed's env; draw the seeds' random "
            "actions with envs.sample_actions(), [num_seeds, action_dim]",
        )


class SeedEnvs:
    """One env per seed (--num-seeds), stepped side by side, with arrays [num_seeds, ...] in and out, as Gymnasium's
    SyncVectorEnv with its same-step autoreset: where an episode ends, `step` returns the next episode's first
    observation, and infos["real_next_obs"] holds every env's true next observation (the one to learn from)."""

    def __init__(self, env_id: str, seeds: list, video_folders: Optional[list] = None, video_every: int = 1):
        self.seeds = seeds
        self.envs = [
            make_env(env_id, seed, folder, video_every) for seed, folder in zip(seeds, video_folders or [None] * len(seeds))
        ]
        space = self.envs[0].action_space  # one env's
        self.action_space = space if len(seeds) == 1 else OneEnvsActionSpace(space.low, space.high, dtype=space.dtype)
        if len(seeds) > 1:  # the refusal's count; one seed's space is its env's own, left as it is
            self.action_space.num_seeds = len(seeds)
        self.obs_dim = int(np.prod(self.envs[0].observation_space.shape))
        self.action_dim = int(np.prod(self.action_space.shape))
        self.steps, self.draws = 0, None

    def __iter__(self):
        return iter(self.envs)

    def __len__(self):
        return len(self.envs)

    def reset(self) -> np.ndarray:
        """Every env's first observation of a run: each env reset with its seed."""
        global latest_episode_ends
        latest_episode_ends, self.draws = None, None
        return np.stack([env.reset(seed=seed)[0] for env, seed in zip(self.envs, self.seeds)])

    def sample_actions(self) -> np.ndarray:
        return np.stack([env.action_space.sample() for env in self.envs])

    def step(self, actions: np.ndarray):
        """Each env steps with its seed's action. Returns next_obs, rewards, terminations, truncations (each
        [num_seeds, ...]) and infos: "real_next_obs", and "episode" (each env's episode statistics, or None)."""
        global latest_episode_ends, steps_taken
        check_actions("SeedEnvs.step: actions", actions, len(self.envs), self.action_space, SEED_ENVS_HINT)
        self.watch_draws()
        next_obs, rewards, terminations, truncations, infos = zip(*(env.step(a) for env, a in zip(self.envs, actions)))
        terminations, truncations = np.array(terminations), np.array(truncations)
        ended, cut = terminations | truncations, truncations & ~terminations
        real_next_obs = marked(np.stack(next_obs), cut)
        next_obs = [env.reset()[0] if done else obs for env, obs, done in zip(self.envs, next_obs, ended)]
        next_obs = marked(np.stack(next_obs), cut)
        latest_episode_ends, steps_taken = None, steps_taken + 1
        if ended.any():
            rows = np.flatnonzero(ended)
            first, real = np.array(next_obs[rows]), np.array(real_next_obs[rows])
            rewards_now = np.asarray(rewards, dtype=np.float32)
            latest_episode_ends = EpisodeEnds(next_obs.shape, rows, first, real, steps_taken, rewards_now, cut[rows])
        episodes = [info.get("episode") if done else None for info, done in zip(infos, ended)]
        infos = {"real_next_obs": real_next_obs, "episode": episodes}
        return next_obs, np.array(rewards), terminations, truncations, infos

    def watch_draws(self):
        """With several seeds, Python's and NumPy's global generators are one stream in the process, not any seed's:
        nothing of the loop draws from them (the envs draw from their own). A fork that does (exploration noise
        np.random.normal(0, s, size=envs.action_space.shape), one seed's shape: the same noise for every seed) stops
        within DRAWS_EVERY steps."""
        self.steps += 1
        if len(self.envs) == 1 or (self.draws is not None and self.steps % DRAWS_EVERY):
            return
        draws = python_draws()
        if self.draws is not None and not same_state(self.draws, draws):
            raise refusal(
                RuntimeError,
                f"SeedEnvs.step with {len(self.envs)} seeds: Python's or NumPy's global random generator drew in the "
                f"last {DRAWS_EVERY} steps (in the loop, or code it calls): with several seeds it is the process's stream, "
                "not any seed's, and a draw of one seed's shape (np.random.normal(0, s, size=envs.action_space.shape)) "
                "gives every seed the same numbers; draw with torch inside a per-seed function, as noisy_action does "
                "(per_seed(noisy_action)(obs, actor, ...))",
            )
        self.draws = draws

    def close(self):
        for env in self.envs:
            env.close()


def check_actions(who: str, actions, num_envs: int, space: gym.spaces.Box, hint: str):
    """Actions are [num_envs, action_dim], one row per env. Else an env is handed a part of a row or a number (which
    DeepMind Control broadcasts to every actuator, without a word), or zip leaves envs out: a one-line refusal."""
    expected = (num_envs, *space.shape)
    try:
        shape = list(np.shape(actions))
    except ValueError:  # rows of different lengths
        shape = "ragged"
    if shape != list(expected):
        raise refusal(ValueError, f"{who} have shape {shape}, not [num_seeds, action_dim] = {list(expected)}: {hint}")


PROBE_SCALES = (0.1, 1.0, 10.0, 100.0)  # the probe's observations: 8 normal draws at each scale
PROBE_SIZE = 8 * len(PROBE_SCALES)


def policy_probe(policy, observation_space, num_seeds: int) -> list:
    """--save-model's record of how the evaluated policy acts, one per seed: {"probe": {"observations", "actions"}},
    its actions on PROBE_SIZE fixed observations (normal draws of the task's observation shape at PROBE_SCALES, from
    a generator of their own: small ones where a tanh is not saturated, large ones past a clip or a bounded
    activation). tools/evaluate.py compares them with the actions of the policy it rebuilds."""
    scales = np.repeat(PROBE_SCALES, PROBE_SIZE // len(PROBE_SCALES)).reshape(-1, *[1] * len(observation_space.shape))
    observations = scales * np.random.default_rng(0).standard_normal((PROBE_SIZE, *observation_space.shape))
    observations = observations.astype(observation_space.dtype)
    with torch.no_grad():  # each observation given to every seed: actions [num_seeds, PROBE_SIZE, action_dim]
        actions = np.stack([np.asarray(policy(np.stack([x] * num_seeds))) for x in observations], axis=1)
    return [{"probe": {"observations": torch.as_tensor(observations), "actions": torch.as_tensor(a)}} for a in actions]


def check_task_return(summed: float, info: dict, k: int):
    """An evaluation episode's return, summed from the rewards env.step gave evaluate, is the task's: the one
    make_env's episode statistics recorded below any wrapper a fork put around the env. A reward wrapper around the
    evaluation env (TransformReward, NormalizeReward, ClipReward) would make every evaluation another number than the
    task's return, the one the paper and the other runs report."""
    task = info.get("episode", {}).get("r") if isinstance(info, dict) else None
    if task is None or np.isclose(summed, float(task), rtol=1e-5, atol=1e-5):  # None: an env not made by make_env
        return
    raise refusal(
        ValueError,
        f"evaluate: env {k}'s episode returned {summed:.6g} in the rewards evaluate was given, and {float(task):.6g} "
        "in the task's (make_env's record): a wrapper around the evaluation env changes its rewards (TransformReward, "
        "NormalizeReward, ClipReward), so the evaluation would not be the task's return; give evaluate the env make_env "
        "returns (a reward wrapper belongs on the training env only)",
    )


def evaluate(policy, envs: list, seeds: list, num_episodes: int) -> np.ndarray:
    """Undiscounted returns [num_envs, num_episodes] of `policy` (observations [num_envs, obs_dim] -> actions), one
    env per seed, stepped side by side. The envs are re-seeded with `seeds` each time, so every evaluation sees the
    same start states."""
    envs = list(envs)
    returns = np.zeros((len(envs), num_episodes))
    draws_before = torch_draws()
    obs = [env.reset(seed=seed)[0] for env, seed in zip(envs, seeds)]
    episode = [0] * len(envs)
    while min(episode) < num_episodes:
        actions = policy(np.stack(obs))
        check_actions("evaluate: the policy's actions", actions, len(envs), envs[0].action_space, EVALUATE_HINT)
        for k, env in enumerate(envs):
            if episode[k] == num_episodes:  # this seed is done; the others go on
                continue
            obs[k], reward, terminated, truncated, info = env.step(actions[k])
            returns[k, episode[k]] += reward
            if terminated or truncated:
                check_task_return(returns[k, episode[k]], info, k)
                episode[k] += 1
                if episode[k] < num_episodes:
                    obs[k], _ = env.reset()
    if not all(torch.equal(a, b) for a, b in zip(draws_before, torch_draws())):
        raise refusal(
            RuntimeError,
            "evaluate: the policy drew from torch's random generator (a dropout layer in training mode, a sampled "
            "action): an evaluation would report a random policy and, in a training run, move the run's draws, so "
            "that its numbers depend on --eval-frequency; run the networks in eval mode for the evaluation (actor.eval() "
            "before, actor.train() after) or act deterministically",
        )
    return returns


def torch_draws() -> list:
    """Where torch's generators are: the CPU's, and the current CUDA device's once CUDA is in use."""
    states = [torch.get_rng_state()]
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        try:
            states.append(torch.cuda.get_rng_state())
        except RuntimeError:  # a state this build cannot read (a graph-safe generator in use): the CPU's is looked at
            pass
    return states
