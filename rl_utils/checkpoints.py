"""Checkpoints: everything needed to continue a run exactly after a kill. An environment's state is its random
generators and, mid-episode, how its episode began and the actions since, which EpisodeRecord replays to rebuild it.
A process of several seeds writes one checkpoint per seed, each in its run folder, each the checkpoint a
single-seed run of that seed would write in form (its own cut of every stacked parameter)."""

import os
import random

import numpy as np
import torch
import torch.nn as nn

from rl_utils.cli import fail
from rl_utils.envs import rng_state, set_rng_state

CHECKPOINT = "checkpoint.pt"
FORMAT = 2  # 2: networks as plain modules (rl_utils); 1: stacked seeds in every layer (before e39c776's successor)


def snapshot(script: str, args, envs, global_step: int, nets: dict, optimizers: dict, parts: dict) -> dict:
    """A process's state at `global_step`: its flags, networks, optimizers and random generators, each env's state,
    and `parts`: objects with a state_dict() (the replay buffer), tensors (SAC's log_alpha) or plain values."""
    return {
        "script": script,
        "format": FORMAT,
        "args": vars(args),
        "global_step": global_step,
        "nets": {name: net.state_dict() for name, net in nets.items()},
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
    return part.state_dict() if hasattr(part, "state_dict") else part


def restore(checkpoint: dict, envs, nets: dict, optimizers: dict, parts: dict) -> list:
    """Loads a snapshot() into the objects it was taken of. Returns each env's observation now (None between
    episodes)."""
    for name, net in nets.items():
        net.load_state_dict(checkpoint["nets"][name])
    for name, opt in optimizers.items():
        state = checkpoint["optimizers"][name]
        for group, current in zip(state["param_groups"], opt.param_groups):  # --cudagraphs may differ from the run's
            group["capturable"] = current["capturable"]
        opt.load_state_dict(state)
    for name, part in parts.items():
        if isinstance(part, torch.Tensor):
            with torch.no_grad():
                part.copy_(checkpoint[name])
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
        fail(f"{path} was written by an older {script}, whose networks held every seed; resume it with that version (e39c776)")
    return checkpoint


# Many seeds in one process: each seed's checkpoint holds its cut of the stacked state. Networks and their optimizer
# states are stacked only when there are several seeds ([num_seeds, ...], cut to [...]); the replay buffer's rows and
# tensor parts always carry the seeds dimension (cut to [1, ...]).
def seed_share(net_state: dict, params: set, k: int) -> dict:
    """Seed k's cut of a stacked network's state_dict (buffers, such as action bounds, are every seed's)."""
    return {name: t[k].clone() if name in params else t for name, t in net_state.items()}


def part_share(state, k: int):
    if isinstance(state, torch.Tensor):
        return state[k : k + 1].clone()
    if isinstance(state, dict):
        return {key: value[k : k + 1].clone() if isinstance(value, torch.Tensor) else value for key, value in state.items()}
    return state


def split_seeds(state: dict, nets: dict, parts: dict, eval_returns: list, run_dirs: list) -> list:
    """One checkpoint per seed from a snapshot() of the stacked seeds: the seed's cut of every parameter, optimizer
    moment, replay buffer and tensor part, its env and its evaluations; the flags, the step and the process's
    random generators in all."""
    n = len(run_dirs)
    params = {name: {key for key, _ in net.named_parameters()} for name, net in nets.items()}
    checkpoints = []
    for k in range(n):
        checkpoint = {**state, "run_names": [os.path.basename(run_dir) for run_dir in run_dirs], "seed_index": k}
        checkpoint["eval_returns"] = eval_returns[k]
        checkpoint["envs"] = state["envs"][k : k + 1]
        if n > 1:  # one seed's state is its own (an on-policy rollout has no seeds dimension to cut)
            checkpoint.update({name: part_share(state[name], k) for name in parts})
            checkpoint["nets"] = {name: seed_share(sd, params[name], k) for name, sd in state["nets"].items()}
            checkpoint["optimizers"] = {
                name: {
                    **sd,
                    "state": {
                        i: {key: t[k].clone() if t.dim() else t for key, t in s.items()} for i, s in sd["state"].items()
                    },
                }
                for name, sd in state["optimizers"].items()
            }
        checkpoints.append(checkpoint)
    return checkpoints


def join_seeds(checkpoints: list, nets: dict, parts: dict) -> dict:
    """split_seeds() undone: the seeds' checkpoints as one snapshot() of the stacked seeds, for restore()."""
    first = checkpoints[0]
    if len(checkpoints) == 1:
        return first
    params = {name: {key for key, _ in net.named_parameters()} for name, net in nets.items()}
    state = dict(first)
    state["nets"] = {
        name: {
            key: torch.stack([c["nets"][name][key] for c in checkpoints]) if key in params[name] else t
            for key, t in sd.items()
        }
        for name, sd in first["nets"].items()
    }
    state["optimizers"] = {
        name: {
            **sd,
            "state": {
                i: {
                    key: torch.stack([c["optimizers"][name]["state"][i][key] for c in checkpoints]) if t.dim() else t
                    for key, t in s.items()
                }
                for i, s in sd["state"].items()
            },
        }
        for name, sd in first["optimizers"].items()
    }
    for name in parts:
        if isinstance(first[name], torch.Tensor):
            state[name] = torch.cat([c[name] for c in checkpoints])
        elif isinstance(first[name], dict):
            state[name] = {
                key: torch.cat([c[name][key] for c in checkpoints]) if isinstance(value, torch.Tensor) else value
                for key, value in first[name].items()
            }
    state["envs"] = [env for c in checkpoints for env in c["envs"]]
    return state


def write_checkpoints(run_dirs: list, states: list, name: str = CHECKPOINT):
    """Each seed's checkpoint into its run folder. All are written before any replaces its predecessor, so that a kill
    leaves either all the old ones or, for any seed still at the old step, its new one complete beside it."""
    paths = [os.path.join(run_dir, name) for run_dir in run_dirs]
    for path, state in zip(paths, states):
        torch.save(state, path + ".tmp")
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


def model_of_seed(saved: dict, k: int, num_seeds: int) -> dict:
    """--save-model: seed k's cut of these networks (or tensors), as a single-seed run saves them."""
    model = {}
    for name, x in saved.items():
        if isinstance(x, nn.Module):
            state = x.state_dict()
            model[name] = seed_share(state, {key for key, _ in x.named_parameters()}, k) if num_seeds > 1 else state
        elif isinstance(x, torch.Tensor):
            model[name] = x.detach().cpu()[k : k + 1].clone()
        else:  # an object with a state_dict(), e.g. PPO's observation statistics
            model[name] = x.state_dict()
    return model
