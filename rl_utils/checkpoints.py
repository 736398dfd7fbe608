"""Checkpoints: everything needed to continue a run exactly after a kill (`snapshot`, `restore`), written atomically
and loaded safely. An environment's state is its random generators and, mid-episode, how its episode began and the
actions since, which `EpisodeRecord` (the last wrapper of every env) replays to rebuild it. A process of several
seeds writes one checkpoint per seed (rl_utils.seeds cuts them), each in its run folder."""

import os
import random
import re
from collections import OrderedDict
from typing import Optional

import numpy as np
import gymnasium as gym
import torch

from rl_utils.errors import fail, refusal


def rng_state(rng) -> dict:
    """A numpy Generator's or RandomState's (dm_control's) state, in types `weights_only` loading accepts."""
    if isinstance(rng, np.random.RandomState):
        name, key, pos, has_gauss, gauss = rng.get_state()
        return {"legacy": (name, torch.from_numpy(key.astype(np.int64)), pos, has_gauss, gauss)}
    return {"generator": rng.bit_generator.state}


def set_rng_state(rng, state: dict):
    if "legacy" in state:
        name, key, pos, has_gauss, gauss = state["legacy"]
        rng.set_state((name, key.numpy().astype(np.uint32), pos, has_gauss, gauss))
    else:
        rng.bit_generator.state = state["generator"]


# a random generator of a script's own (a fork's noise), which a checkpoint holds when given to run.start's parts
GENERATORS = (np.random.Generator, np.random.RandomState, random.Random, torch.Generator)


def generator_state(rng) -> dict:
    """Its state, with no tensor directly under a key: a process's generator, kept whole in each seed's checkpoint."""
    if isinstance(rng, torch.Generator):
        return {"torch": (rng.get_state(),)}
    if isinstance(rng, random.Random):
        return {"python": rng.getstate()}
    return rng_state(rng)


def set_generator_state(rng, state: dict):
    if "torch" in state:
        rng.set_state(state["torch"][0])
    elif "python" in state:
        rng.setstate(state["python"])
    else:
        set_rng_state(rng, state)


class EpisodeRecord(gym.Wrapper):
    """Remembers how the current episode began (the reset's seed, or the env's random state before the reset) and
    the actions taken since, so that a checkpoint taken mid-episode rebuilds the env exactly by replaying them."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.episode = None  # None: between episodes

    def reset(self, *, seed=None, options=None):
        start = rng_state(self.env.unwrapped.np_random) if seed is None else None
        self.episode = {"seed": seed, "rng": start, "actions": []}
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        if np.shape(action) != self.action_space.shape:  # DeepMind Control would take a number for every actuator
            raise refusal(
                ValueError,
                f"env.step: an action of shape {list(np.shape(action))} for an env whose actions are "
                f"{list(self.action_space.shape)}: one action a step",
            )
        if self.episode is None:
            raise refusal(
                RuntimeError,
                "env.step: the env's episode has ended (or it was never reset), and it was stepped before a reset: reset "
                "an env whose episode ended before its next step (an evaluation given the training envs, evaluate(policy, "
                "envs, ...), ends their episodes: give it envs of its own, eval_envs)",
            )
        self.episode["actions"].append(np.array(action))
        result = self.env.step(action)
        if result[2] or result[3]:  # terminated or truncated
            self.episode = None
        return result

    def state_dict(self) -> Optional[dict]:
        if self.episode is None:
            return None
        actions = self.episode["actions"]
        return {**self.episode, "actions": torch.from_numpy(np.stack(actions)) if actions else torch.zeros(0)}

    def replay(self, state: Optional[dict]):
        """Rebuilds the episode of a state_dict(): its observation now, or None between episodes."""
        if state is None:
            self.episode = None
            return None
        if state["rng"] is not None:
            set_rng_state(self.env.unwrapped.np_random, state["rng"])
        obs, _ = self.reset(seed=state["seed"])
        for action in state["actions"].numpy():
            obs = self.step(action)[0]
        return obs


CHECKPOINT = "checkpoint.pt"
# the keys a checkpoint keeps its own state under (snapshot(), split_seeds()), which no part of run.start may take
OWN_KEYS = (
    "script",
    "format",
    "args",
    "args_given",
    "global_step",
    "nets",
    "optimizers",
    "rng",
    "envs",
    "run_names",
    "seed_index",
)
OWN_KEYS += ("eval_returns", "seed_cut")
# 3: critics as modules of nn.Linear layers (QNetwork); 2: critics as one hand-batched module; 1: every seed stacked
# in each layer, before rl_utils. A checkpoint of another format resumes only with the scripts that wrote it.
FORMAT = 3


def uncompiled(net):
    """A torch.compile'd network's own network (its state_dict names every tensor `_orig_mod.`...): a checkpoint of
    the one resumes the other."""
    return getattr(net, "_orig_mod", net)


def snapshot(script: str, args, envs, global_step: int, nets: dict, optimizers: dict, parts: dict) -> dict:
    """A process's state at `global_step`: its flags, networks, optimizers and random generators, each env's state,
    and `parts`: objects with a state_dict() (the replay buffer), tensors (SAC's log_alpha) and random generators of the
    script's own."""
    return {
        "script": script,
        "format": FORMAT,
        "args": vars(args),
        "global_step": global_step,
        "nets": {name: uncompiled(net).state_dict() for name, net in nets.items()},
        "optimizers": {name: opt.state_dict() for name, opt in optimizers.items()},
        **{name: state_of(part) for name, part in parts.items()},
        "rng": {
            "python": random.getstate(),
            "numpy": rng_state(np.random.mtrand._rand),
            "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else [],
        },
        "envs": [
            {
                "action_space": rng_state(env.action_space.np_random),
                "env": rng_state(env.unwrapped.np_random),
                "episode": env.state_dict(),
            }
            for env in envs
        ],
    }


def state_of(part):
    if isinstance(part, torch.Tensor):
        return part.detach().cpu().clone()
    if isinstance(part, GENERATORS):
        return generator_state(part)
    return part.state_dict() if hasattr(part, "state_dict") else part


def restore(checkpoint: dict, envs, nets: dict, optimizers: dict, parts: dict) -> list:
    """Loads a snapshot() into the objects it was taken of. Returns each env's observation now (None between
    episodes)."""
    for name, net in nets.items():
        uncompiled(net).load_state_dict(checkpoint["nets"][name])
    for name, opt in optimizers.items():
        state = checkpoint["optimizers"][name]
        for group, current in zip(state["param_groups"], opt.param_groups):  # --cudagraphs may differ from the run's
            group["capturable"] = current["capturable"]
        opt.load_state_dict(state)
    for name, part in parts.items():
        if isinstance(part, torch.Tensor):
            with torch.no_grad():
                part.copy_(checkpoint[name])
        elif isinstance(part, GENERATORS):
            set_generator_state(part, checkpoint[name])
        elif hasattr(part, "load_state_dict"):
            part.load_state_dict(checkpoint[name])
    rng = checkpoint["rng"]
    random.setstate(rng["python"])
    set_rng_state(np.random.mtrand._rand, rng["numpy"])
    torch.set_rng_state(rng["torch"])
    if rng["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(rng["cuda"])
    observations = []
    for env, state in zip(envs, checkpoint["envs"]):
        observations.append(env.replay(state["episode"]))
        set_rng_state(env.action_space.np_random, state["action_space"])
        set_rng_state(env.unwrapped.np_random, state["env"])
    return observations


def write_checkpoint(path: str, state: dict):
    """Write atomically: a kill during the write leaves the previous file intact."""
    torch.save(state, path + ".tmp")
    os.replace(path + ".tmp", path)


def load_checkpoint(run_dir: str, script: str, name: str = CHECKPOINT) -> dict:
    path = os.path.join(run_dir, name)
    if not os.path.isdir(run_dir):
        fail(f"--resume {run_dir}: no such run folder")
    if not os.path.isfile(path):
        fail(f"--resume {run_dir}: it holds no {CHECKPOINT} (write one with --checkpoint-frequency N)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as e:  # truncated, foreign or corrupt files all land here
        fail(f"{path} is not a readable checkpoint ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'no detail'})")
    if not isinstance(checkpoint, dict) or checkpoint.get("script") != script:
        found = checkpoint.get("script") if isinstance(checkpoint, dict) else None
        fail(f"{path} was not written by {script} (written by {found or 'something else'})")
    if checkpoint.get("format") != FORMAT:
        fail(
            f"{path} was written by an older {script} (checkpoint format {checkpoint.get('format')}, now {FORMAT}: its "
            "networks are laid out otherwise); resume it with the version that wrote it"
        )
    return checkpoint


# what torch.load(weights_only=True), --resume's safe loading, reads back: these values, in dicts, lists and tuples
LOADABLE = (torch.Tensor, int, float, bool, str, bytes, type(None), complex, torch.Size, torch.dtype, torch.device)


def unloadable(state, path="") -> Optional[tuple]:
    """The first value in a checkpoint's state that weights_only loading refuses (a NumPy array, a deque, an Enum, a
    NumPy number): (where, its type's name), or None."""
    if type(state) in (dict, OrderedDict):
        found = (unloadable(v, f"{path}[{k!r}]") for k, v in state.items())
    elif type(state) in (list, tuple, set):
        found = (unloadable(v, f"{path}[{i}]") for i, v in enumerate(state))
    else:
        loadable = isinstance(state, LOADABLE) and not isinstance(state, np.generic)  # np.float64 is a float
        return None if loadable else (path, f"{type(state).__module__}.{type(state).__qualname__}")
    return next((f for f in found if f), None)


def check_loadable(path: str, state: dict):
    """A checkpoint --resume could not load is refused when written, not hours later at the resume: what it holds
    that safe loading refuses, named (a part's or a flag's)."""
    if not torch.serialization.get_unsafe_globals_in_checkpoint(path):
        return
    found = unloadable(state)
    if found is None:
        what = f"the checkpoint holds {', '.join(torch.serialization.get_unsafe_globals_in_checkpoint(path))}"
    else:
        keys = [k.strip("'") for k in re.findall(r"\[('[^']*'|\d+)\]", found[0])]
        if keys[0] in ("args", "args_given"):
            what = f"the flag `{keys[1]}` holds a {found[1]}"
        else:
            inside = "".join(f"[{k!r}]" if not k.isdigit() else f"[{k}]" for k in keys[1:])
            what = f"run.start's part `{keys[0]}`{f', at {inside},' if inside else ''} holds a {found[1]}"
    os.remove(path)
    fail(
        f"{what}, which --resume's safe loading (torch.load(weights_only=True)) refuses: the run could not be resumed "
        "from its checkpoints; hold tensors, numbers and strings there, in dicts, lists or tuples "
        "(torch.from_numpy(array), float(x), list(a_deque))"
    )


def write_checkpoints(run_dirs: list, states: list, name: str = CHECKPOINT):
    """Each seed's checkpoint into its run folder. All are written before any replaces its predecessor, so that a kill
    leaves either all the old ones or, for any seed still at the old step, its new one complete beside it. One that
    --resume could not load is refused."""
    paths = [os.path.join(run_dir, name) for run_dir in run_dirs]
    for path, state in zip(paths, states):
        torch.save(state, path + ".tmp")
        check_loadable(path + ".tmp", state)
    for path in paths:
        os.replace(path + ".tmp", path)


def load_checkpoints(run_dir: str, script: str) -> list:
    """The checkpoints of the seeds that trained in one process with the run in run_dir, at one step, in seed order."""
    first = load_checkpoint(run_dir, script)
    run_dirs = [os.path.join(os.path.dirname(os.path.normpath(run_dir)), name) for name in first["run_names"]]
    checkpoints = [load_checkpoint(d, script) if os.path.isfile(os.path.join(d, CHECKPOINT)) else None for d in run_dirs]
    step = max(checkpoint["global_step"] for checkpoint in checkpoints if checkpoint)
    for k, d in enumerate(run_dirs):
        if checkpoints[k] is None or checkpoints[k]["global_step"] < step:  # killed between the renames: finish them
            tmp = os.path.join(d, CHECKPOINT + ".tmp")
            checkpoints[k] = load_checkpoint(d, script, CHECKPOINT + ".tmp") if os.path.isfile(tmp) else None
            if checkpoints[k] is None or checkpoints[k]["global_step"] != step:
                fail(f"--resume {run_dir}: {d} holds no checkpoint at step {step}, the step of the seeds beside it")
            os.replace(tmp, os.path.join(d, CHECKPOINT))
        if checkpoints[k]["seed_index"] != k:
            fail(f"--resume {run_dir}: {d} holds the checkpoint of another seed of the process")
    return checkpoints
