"""The replay buffer of the off-policy scripts: preallocated tensors on the training device, uniform sampling."""

from typing import NamedTuple

import numpy as np
import torch

from rl_utils import checkpoints as ckpt
from rl_utils import envs as env_layer
from rl_utils.errors import refusal


class Batch(NamedTuple):
    observations: torch.Tensor
    actions: torch.Tensor
    next_observations: torch.Tensor
    rewards: torch.Tensor
    terminations: torch.Tensor


def check_what_is_stored(next_obs, terminations, time_limits_end_episodes=False):
    """The two CleanRL-era slips. Storing the next_obs `SeedEnvs.step` returned, whose rows where an episode ended are
    the next episode's first observation: refused where such a row is stored as not terminated (its target would
    bootstrap from it), found by value in any array against the latest step's record. And storing `terminations |
    truncations` as terminations, which stops the target bootstrapping where a time limit cut an episode (every
    DeepMind Control episode): found by the `truncated` mark on the arrays step returned and their copies
    (rl_utils.envs.StepObservations)."""
    ended = np.asarray(terminations)
    ends = env_layer.latest_episode_ends
    if ends is not None and np.shape(next_obs) == ends.shape:
        stored = np.asarray(next_obs)
        for row, first, real in zip(ends.rows, ends.first_observations, ends.real_next_observations):
            if ended[row] == 0 and np.array_equal(stored[row], first) and not np.array_equal(first, real):
                raise refusal(
                    ValueError,
                    f"ReplayBuffer.add: next_obs's row for seed index {row} is the next episode's first observation "
                    "(envs.step's next_obs, or a copy of it), where the episode ended at this step, stored as not "
                    "terminated: its target would bootstrap from it; store the observation the step led to, "
                    'infos["real_next_obs"]',
                )
    cut = None if time_limits_end_episodes else getattr(next_obs, "truncated", None)
    if cut is not None and (stopped := cut & (ended != 0)).any():
        raise refusal(
            ValueError,
            f"ReplayBuffer.add: terminations is 1 for seed index {int(stopped.argmax())}, whose episode its time limit "
            "cut (truncated, not terminated): its target must bootstrap from the next observation; store the "
            "terminations envs.step returned, not terminations | truncations (a fork that means a time limit to end "
            "its episodes sets rb.time_limits_end_episodes = True)",
        )


class ReplayBuffer:
    """Each seed's transitions in one preallocated [num_seeds, capacity, fields] tensor: one row per seed per add, one
    gather per batch, each seed's batch drawn from its own transitions."""

    # the base's own attributes; a subclass's others go into state_dict()
    FIELDS = ("capacity", "pos", "size", "num_seeds", "widths", "storage", "ends", "added_at", "time_limits_end_episodes")

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, num_seeds: int, device: torch.device):
        self.capacity, self.pos, self.size, self.num_seeds = capacity, 0, 0, num_seeds
        self.widths = [obs_dim, action_dim, obs_dim, 1, 1]  # the fields of `Batch`, in order
        self.storage = torch.zeros((num_seeds, capacity, sum(self.widths)), dtype=torch.float32, device=device)
        self.ends = None  # where the last add stored an episode's end as not terminated: (rows, next_obs there)
        self.added_at = None  # env_layer.steps_taken at the last add
        self.time_limits_end_episodes = False  # a fork that stores terminations | truncations on purpose sets it

    def add(self, obs, next_obs, actions, rewards, terminations):
        """One transition per seed, in CleanRL's order: obs and next_obs [num_seeds, obs_dim], actions [num_seeds,
        action_dim], rewards and terminations [num_seeds]. A field of the wrong shape stops here, naming it."""
        fields = {"obs": obs, "next_obs": next_obs, "actions": actions, "rewards": rewards, "terminations": terminations}
        obs_dim, action_dim = self.widths[0], self.widths[1]
        shapes = {"obs": (obs_dim,), "next_obs": (obs_dim,), "actions": (action_dim,), "rewards": (), "terminations": ()}
        for name, value in fields.items():
            if np.shape(value) != (self.num_seeds, *shapes[name]):
                raise refusal(
                    ValueError,
                    f"ReplayBuffer.add: {name} has shape {list(np.shape(value))}, not {[self.num_seeds, *shapes[name]]}; "
                    "the order is add(obs, next_obs, actions, rewards, terminations), each with a leading seeds dimension",
                )
        check_what_is_stored(next_obs, terminations, self.time_limits_end_episodes)
        self.check_time_limits(next_obs, rewards, terminations)
        self.check_the_last_end(obs)
        scalars = np.stack([rewards, terminations], -1)
        row = np.concatenate([obs, actions, next_obs, scalars], -1, dtype=np.float32)
        self.storage[:, self.pos] = torch.from_numpy(row)
        self.remember_the_ends(obs, next_obs, rewards, np.asarray(terminations))
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def of_the_latest_step(self, next_obs, rewards):
        """The latest envs.step's record of ended episodes, where this add is of that step's transition (a step taken
        since this buffer's add before, whose rewards these are); else None."""
        ends = env_layer.latest_episode_ends
        if ends is None or self.added_at is None or ends.step <= self.added_at or np.shape(next_obs) != ends.shape:
            return None
        return ends if np.array_equal(np.asarray(rewards, dtype=np.float32), ends.rewards) else None

    def check_time_limits(self, next_obs, rewards, terminations):
        """`terminations | truncations` stored with observations the mark does not follow (computed: normalised):
        found by the latest step's record instead, where the next_obs row is not the observation the step led to
        as it is (np.asarray(infos["real_next_obs"]) is the way to mean it). A fork that means a time limit to end
        its episodes with computed observations sets `time_limits_end_episodes`."""
        ends = self.of_the_latest_step(next_obs, rewards)
        if ends is None or getattr(next_obs, "truncated", None) is not None or self.time_limits_end_episodes:
            return
        for row, real, cut in zip(ends.rows, ends.real_next_observations, ends.cut):
            stored = np.asarray(next_obs[row], dtype=np.float32)
            if cut and terminations[row] != 0 and not np.array_equal(stored, real.astype(np.float32)):
                raise refusal(
                    ValueError,
                    f"ReplayBuffer.add: terminations is 1 for seed index {row}, whose episode its time limit cut "
                    "(truncated, not terminated): its target must bootstrap from the next observation; store the "
                    "terminations envs.step returned, not terminations | truncations (a fork that means a time limit "
                    "to end its episodes sets rb.time_limits_end_episodes = True)",
                )

    def check_the_last_end(self, obs):
        """A next_obs computed from envs.step's (normalised: (next_obs - mean) / std) is not found by value; but where
        an episode ended, its row is the one the next step's obs has, computed from the same first observation of the
        next episode: refused at that next add, one step late. Computed from infos["real_next_obs"], the two differ
        (where the observation the step led to is not the next episode's first one, which remember_the_ends keeps)."""
        ends, self.ends = self.ends, None
        if ends is None or np.shape(obs)[0] != self.num_seeds:
            return
        same = [row for row, kept in zip(*ends) if np.array_equal(np.asarray(obs[row], dtype=np.float32), kept)]
        if same:
            raise refusal(
                ValueError,
                f"ReplayBuffer.add: the next_obs stored for seed index {same[0]} where its episode ended (the add before "
                "this one) is this add's obs, made from the next episode's first observation: computed from envs.step's "
                'next_obs (normalised, say), its target would bootstrap from it; compute it from infos["real_next_obs"], '
                "the observation the step led to",
            )

    def remember_the_ends(self, obs, next_obs, rewards, terminations):
        """The rows of next_obs just stored where the latest envs.step ended an episode, stored as not terminated, and
        whose observation the step led to is not the next episode's first: check_the_last_end's. Only for the
        transition of that step (a step taken since this buffer's add before, whose rewards these are; not one
        added a step late, nor another loop's envs), and where the row says something (its obs and next_obs differ)."""
        ends, self.added_at = self.of_the_latest_step(next_obs, rewards), env_layer.steps_taken
        if ends is None:
            return
        kept = [
            (row, np.asarray(next_obs[row], dtype=np.float32))
            for row, first, real in zip(ends.rows, ends.first_observations, ends.real_next_observations)
            if terminations[row] == 0
            and not np.array_equal(first, real)
            and not np.array_equal(np.asarray(obs[row], dtype=np.float32), np.asarray(next_obs[row], dtype=np.float32))
        ]
        self.ends = tuple(zip(*kept)) if kept else None

    def sample(self, *shape: int) -> Batch:
        """Transitions drawn uniformly with replacement, for each seed a batch of this shape: `sample(256)` gives
        fields [num_seeds, 256, width], `sample(20, 256)` twenty batches each ([num_seeds, 20, 256, width])."""
        device = self.storage.device
        indices = torch.randint(self.size, (self.num_seeds, *shape), device=device)
        seed = torch.arange(self.num_seeds, device=device).view(-1, *[1] * len(shape))
        obs, actions, next_obs, rewards, terminations = self.storage[seed, indices].split(self.widths, dim=-1)
        return Batch(obs, actions, next_obs, rewards.squeeze(-1), terminations.squeeze(-1))

    def state_dict(self) -> dict:
        """The rows stored and where the next goes; and, for a subclass that does not write its own, what it adds (a
        prioritised buffer's priorities and largest priority): its tensors, arrays (as tensors), numbers and other
        values a checkpoint can hold, so that --resume restores them too."""
        state = {"rows": self.storage[:, : self.size].cpu().clone(), "pos": self.pos}
        return state if type(self).state_dict is not ReplayBuffer.state_dict else {**state, **self.added_state()}

    def added_state(self) -> dict:
        added = {}
        for name, value in vars(self).items():
            if name in ReplayBuffer.FIELDS:
                continue
            if isinstance(value, np.generic):  # max_priority from an array's max()
                value = value.item()
            if isinstance(value, (torch.Tensor, np.ndarray)):
                value = torch.from_numpy(value.copy()) if isinstance(value, np.ndarray) else value.cpu().clone()
            elif ckpt.unloadable(value):
                raise refusal(
                    TypeError,
                    f"{type(self).__name__}.{name} is a {type(value).__name__}, which a checkpoint of the buffer cannot "
                    "hold: hold a subclass's state in tensors, arrays and numbers, or give the subclass a state_dict() "
                    "and a load_state_dict() of its own",
                )
            added[name] = value
        return added

    def load_state_dict(self, state: dict):
        self.storage[:, : state["rows"].shape[1]] = state["rows"].to(self.storage.device)
        self.size, self.pos = state["rows"].shape[1], state["pos"]
        if type(self).load_state_dict is not ReplayBuffer.load_state_dict:  # the subclass restores its own
            return
        for name in vars(self).keys() & state.keys() - {"rows", "pos"}:
            now, value = getattr(self, name), state[name]
            if isinstance(now, torch.Tensor):
                now.copy_(value)
            elif isinstance(now, np.ndarray):
                now[...] = value.numpy()
            else:
                setattr(self, name, value)
