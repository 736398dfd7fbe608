"""Several seeds in one process (--num-seeds): seed, seed+1, ..., each an ordinary run with its own folder, trained
side by side as one batched computation. The scripts are written for one seed; two functions add the seeds:

    actor, qf = stack_seeds(networks, seeds)      # each seed's networks, their parameters stacked [num_seeds, ...]
    qf_loss = per_seed(critic_loss)(batch, qf, ...)  # tensors [num_seeds, ...] in and out, one seed's code

With one seed both step aside: the networks are the ones `networks()` built and the function runs as written, so a
single-seed run computes exactly what a plain PyTorch script does. With several, `per_seed` is `torch.func.vmap`
over the seeds with each network's stacked parameters (`functional_call`), and its random draws differ per seed
(`randomness="different"`): nothing flows between seeds, and each seed's loss enters the total as a sum.
"""

import functools

import torch
import torch.nn as nn
from torch.func import functional_call, vmap
from torch.utils._pytree import tree_flatten, tree_map


def stack_seeds(networks, seeds: list, device: torch.device) -> list:
    """The networks `networks()` returns, built once per seed, each parameter stacked along a new leading dimension,
    on the device. Seed k's initial weights are those of a single-seed run of seed k; one seed's networks are the
    ones built."""
    if len(seeds) == 1:
        return [net.to(device) for net in networks()]
    built = []
    for seed in seeds:
        with torch.random.fork_rng(devices=[]):  # the process's own generator stays as it was seeded
            torch.manual_seed(seed)
            built.append(networks())
    for nets in zip(*built):
        for name, _ in list(nets[0].named_parameters()):
            owner, _, attr = name.rpartition(".")
            stacked = torch.stack([net.get_parameter(name).detach() for net in nets])
            setattr(nets[0].get_submodule(owner), attr, nn.Parameter(stacked))
    return [net.to(device) for net in built[0]]


class _Networks(nn.Module):
    """The networks one call of a per-seed function uses, under one root, so that functional_call swaps them all."""

    def __init__(self, networks: list):
        super().__init__()
        self.networks = nn.ModuleList(networks)

    def forward(self, fn, args):
        return fn(*args)


def num_seeds(args) -> int:
    """The leading dimension of the first tensor among `args`: the number of seeds."""
    return next(x for x in tree_flatten(args)[0] if isinstance(x, torch.Tensor)).shape[0]


def per_seed(fn):
    """fn (a function or a network), written for one seed, run for every seed: its tensor arguments (and NamedTuples
    of them) carry a leading seeds dimension, its networks come from stack_seeds, what it returns gains that dimension."""

    @functools.wraps(fn)
    def run(*args):
        if num_seeds(args) == 1:  # as written, on seed 0's share of each tensor
            one_seed = tree_map(lambda x: x[0] if isinstance(x, torch.Tensor) else x, args)
            return tree_map(lambda x: x.unsqueeze(0) if isinstance(x, torch.Tensor) else x, fn(*one_seed))
        modules = [fn, getattr(fn, "__self__", None), *args]  # fn may be a network or its method: per_seed(actor)(obs)
        networks = _Networks(list({id(x): x for x in modules if isinstance(x, nn.Module)}.values()))
        params = dict(networks.named_parameters())
        in_dims = [0 if isinstance(x, (torch.Tensor, tuple)) else None for x in args]

        def one_seed(params, *args):
            return functional_call(networks, params, (fn, args))

        return vmap(one_seed, in_dims=(0, *in_dims), randomness="different")(params, *args)

    return run
