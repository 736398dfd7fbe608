"""Several seeds in one process (--num-seeds): seed, seed+1, ..., each an ordinary run with its own folder, trained
side by side as one batched computation. The scripts are written for one seed; two functions add the seeds:

    actor, qf = stack_seeds(networks, seeds)      # each seed's networks, their tensors stacked [num_seeds, ...]
    qf_loss = per_seed(critic_loss)(batch, qf, ...)  # tensors [num_seeds, ...] in and out, one seed's code

With one seed both step aside: the networks are the ones `networks()` built and the function runs as written, so a
single-seed run computes exactly what a plain PyTorch script does. With several, `per_seed` is `torch.func.vmap`
over the seeds with each network's stacked parameters and buffers (`functional_call`), and its random draws differ
per seed (`randomness="different"`): nothing flows between seeds, and each seed's loss enters the total as a sum.

A checkpoint holds one seed's share of all this, as a single-seed run would write it: `split_seeds` cuts a process's
state into one checkpoint per seed and `join_seeds` stacks them again; `model_of_seed` is --save-model's cut.
"""

import functools
import os

import torch
import torch.nn as nn
from torch.func import functional_call, vmap
from torch.utils._pytree import tree_flatten, tree_map


def stack_seeds(networks, seeds: list, device: torch.device) -> list:
    """The networks `networks()` returns, built once per seed, each parameter and buffer stacked along a new leading
    dimension, on the device. Seed k's initial weights (and buffers, a random projection's say) are those of a
    single-seed run of seed k; a parameter keeps its requires_grad. One seed's networks are the ones built."""
    if len(seeds) == 1:
        built = [net.to(device) for net in networks()]
    else:
        per_seed_nets = []
        for seed in seeds:
            with torch.random.fork_rng(devices=[]):  # the process's own generator stays as it was seeded
                torch.manual_seed(seed)
                per_seed_nets.append(networks())
        for nets in zip(*per_seed_nets):
            for name, param in list(nets[0].named_parameters()):
                stacked = torch.stack([net.get_parameter(name).detach() for net in nets])
                owner, _, attr = name.rpartition(".")
                setattr(nets[0].get_submodule(owner), attr, nn.Parameter(stacked, requires_grad=param.requires_grad))
            for name, _ in list(nets[0].named_buffers()):
                owner, _, attr = name.rpartition(".")
                module = nets[0].get_submodule(owner)
                persistent = attr not in module._non_persistent_buffers_set
                module.register_buffer(attr, torch.stack([net.get_buffer(name) for net in nets]), persistent=persistent)
        built = [net.to(device) for net in per_seed_nets[0]]
    for net in built:
        net.num_seeds = len(seeds)  # per_seed's check of its arguments reads it
    return built


class _Networks(nn.Module):
    """The networks one call of a per-seed function uses, under one root, so that functional_call swaps them all."""

    def __init__(self, networks: list):
        super().__init__()
        self.networks = nn.ModuleList(networks)

    def forward(self, fn, args):
        return fn(*args)


def num_seeds(fn, args) -> int:
    """How many seeds a call of per_seed(fn) has: the networks' (stack_seeds marks them), else the leading dimension
    of the first tensor among `args`."""
    for x in (fn, getattr(fn, "__self__", None), *args):
        if isinstance(x, nn.Module) and hasattr(x, "num_seeds"):
            return x.num_seeds
    return next(x for x in tree_flatten(args)[0] if isinstance(x, torch.Tensor)).shape[0]


def check_seeds_dimension(fn, args, n: int):
    """Every tensor argument of a per-seed function is one per seed: [n, ...]. A tensor shared by the seeds (an extra
    [batch] tensor, say) would be cut along its first dimension; this stops it with the fix, in one line."""
    for position, arg in enumerate(args, 1):
        for x in tree_flatten(arg)[0] if isinstance(arg, tuple) else [arg]:
            if isinstance(x, torch.Tensor) and (x.dim() == 0 or x.shape[0] != n):
                raise TypeError(
                    f"per_seed({getattr(fn, '__name__', fn)}): argument {position} is a tensor of shape {list(x.shape)}, "
                    f"but every tensor argument is one per seed, [{n}, ...] with {n} seed(s): give it that leading "
                    "dimension, or pass a tensor the seeds share inside the function (a closure, functools.partial)"
                )


def per_seed(fn):
    """fn (a function or a network), written for one seed, run for every seed: its tensor arguments (and NamedTuples
    of them) carry a leading seeds dimension, its networks come from stack_seeds, what it returns gains that dimension."""

    @functools.wraps(fn)
    def run(*args):
        n = num_seeds(fn, args)
        check_seeds_dimension(fn, args, n)
        if n == 1:  # as written, on seed 0's share of each tensor
            one_seed = tree_map(lambda x: x[0] if isinstance(x, torch.Tensor) else x, args)
            return tree_map(lambda x: x.unsqueeze(0) if isinstance(x, torch.Tensor) else x, fn(*one_seed))
        modules = [fn, getattr(fn, "__self__", None), *args]  # fn may be a network or its method: per_seed(actor)(obs)
        networks = _Networks(list({id(x): x for x in modules if isinstance(x, nn.Module)}.values()))
        state = {**dict(networks.named_parameters()), **dict(networks.named_buffers())}
        in_dims = [0 if isinstance(x, (torch.Tensor, tuple)) else None for x in args]

        def one_seed(state, *args):
            return functional_call(networks, state, (fn, args))

        return vmap(one_seed, in_dims=(0, *in_dims), randomness="different")(state, *args)

    return run


# Each seed's checkpoint holds its cut of the stacked state. Networks (parameters and buffers) and their optimizer
# states are stacked only when there are several seeds ([num_seeds, ...], cut to [...]); the replay buffer's rows and
# tensor parts always carry the seeds dimension (cut to [1, ...]).
def seed_share(net_state: dict, k: int) -> dict:
    """Seed k's cut of a stacked network's state_dict."""
    return {name: t[k].clone() for name, t in net_state.items()}


def part_share(state, k: int):
    if isinstance(state, torch.Tensor):
        return state[k : k + 1].clone()
    if isinstance(state, dict):
        return {key: value[k : k + 1].clone() if isinstance(value, torch.Tensor) else value for key, value in state.items()}
    return state


def split_seeds(state: dict, parts: dict, eval_returns: list, run_dirs: list) -> list:
    """One checkpoint per seed from a snapshot() of the stacked seeds: the seed's cut of every parameter, optimizer
    moment, replay buffer and tensor part, its env and its evaluations; the flags, the step and the process's
    random generators in all."""
    n = len(run_dirs)
    checkpoints = []
    for k in range(n):
        checkpoint = {**state, "run_names": [os.path.basename(run_dir) for run_dir in run_dirs], "seed_index": k}
        checkpoint["eval_returns"] = eval_returns[k]
        checkpoint["envs"] = state["envs"][k : k + 1]
        if n > 1:  # one seed's state is its own (an on-policy rollout has no seeds dimension to cut)
            checkpoint.update({name: part_share(state[name], k) for name in parts})
            checkpoint["nets"] = {name: seed_share(sd, k) for name, sd in state["nets"].items()}
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


def join_seeds(checkpoints: list, parts: dict) -> dict:
    """split_seeds() undone: the seeds' checkpoints as one snapshot() of the stacked seeds, for restore()."""
    first = checkpoints[0]
    if len(checkpoints) == 1:
        return first
    state = dict(first)
    state["nets"] = {
        name: {key: torch.stack([c["nets"][name][key] for c in checkpoints]) for key in sd}
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


def model_of_seed(saved: dict, k: int, num_seeds: int) -> dict:
    """--save-model: seed k's cut of these networks (or tensors), as a single-seed run saves them."""
    model = {}
    for name, x in saved.items():
        if isinstance(x, nn.Module):
            state = x.state_dict()
            model[name] = seed_share(state, k) if num_seeds > 1 else state
        elif isinstance(x, torch.Tensor):
            model[name] = x.detach().cpu()[k : k + 1].clone()
        else:  # an object with a state_dict(), e.g. PPO's observation statistics
            model[name] = x.state_dict()
    return model
