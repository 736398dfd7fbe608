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

What a fork adds in plain PyTorch keeps working per seed: importing this module makes gradient clipping by norm
(`torch.nn.utils.clip_grad_norm_`) and re-initialisation (`reset_parameters()`, `torch.nn.init`) treat each seed of
a stacked parameter as the one-seed tensor it is; anything else stays PyTorch's own.
"""

import functools
import inspect
import os
import random
import weakref

import numpy as np
import torch
import torch.nn as nn
import torch.nn.init as init
import torch.nn.utils.clip_grad as clip_grad
from torch.func import functional_call, vmap
from torch.utils._pytree import tree_flatten, tree_map

from rl_utils.checkpoints import uncompiled
from rl_utils.errors import refusal

# every parameter stack_seeds stacked for several seeds, by id (gradient clipping finds their gradients); such a
# parameter carries its number of seeds as `num_seeds`
STACKED = weakref.WeakValueDictionary()


def stack_seeds(networks, seeds: list, device: torch.device) -> list:
    """The networks `networks()` returns, built once per seed, each parameter and buffer stacked along a new leading
    dimension, on the device. Built right after the process's generator was seeded with the first seed (main's first
    build), seed k's initial weights (and buffers, a random projection's say) are those of a single-seed run of seed
    k; a later build (a second call: another network, a reset) draws each seed's anew, as a single-seed run's later
    build does, from seeds drawn from the process's generator, which checkpoints hold. A parameter keeps its
    requires_grad; a layer two networks share (an encoder), and a parameter tied under two names, stay shared, stacked
    once. With several seeds, calling a network outside per_seed stops in one line. One seed's networks are the ones
    built."""
    if len(seeds) == 1:
        built = [net.to(device) for net in networks()]
        check_networks(built)
    else:
        if torch.equal(torch.get_rng_state(), torch.Generator().manual_seed(seeds[0]).get_state()):  # main's first build
            draws = seeds
            torch.randint(2**62, (1,))  # the process's generator moves on: a next call is a later build
        else:
            draws = torch.randint(2**62, (len(seeds),)).tolist()
        per_seed_nets, after = [], []
        for seed in draws:
            with torch.random.fork_rng(devices=[]):  # the process's own generator stays as it was
                torch.manual_seed(seed)
                per_seed_nets.append(networks())
                after.append(torch.get_rng_state())
        check_networks(per_seed_nets[0])
        if torch.equal(after[0], after[1]) or same_weights(per_seed_nets[0], per_seed_nets[1]):
            raise refusal(
                RuntimeError,
                f"stack_seeds: seeds {seeds[0]} and {seeds[1]} were built with the same initial weights: networks() draws "
                "them apart from the generator stack_seeds seeds for each seed (torch.manual_seed inside it, a "
                "torch.Generator of its own, a copy of one network built before); leave the seeding to main and "
                "stack_seeds (torch.manual_seed(args.seed) before stack_seeds, as the scripts do). To start every seed from "
                "the same weights on purpose (pretrained ones), copy them in after stack_seeds (p.copy_(q) for each "
                "stacked parameter p and its weight q)",
            )
        stacked_buffers = set()  # by id: a buffer of a layer two networks share is stacked once
        replaced = {}  # a parameter stacked, by the id of seed 0's: a parameter tied to it (two names) gets the same
        for nets in zip(*per_seed_nets):
            for name, param in list(nets[0].named_parameters(remove_duplicate=False)):
                owner, _, attr = name.rpartition(".")
                if id(param) in STACKED:  # a layer this network shares with one stacked before
                    continue
                if id(param) in replaced:  # tied to a parameter stacked before
                    setattr(nets[0].get_submodule(owner), attr, replaced[id(param)])
                    continue
                stacked = torch.stack([net.get_parameter(name).detach() for net in nets])
                stacked = nn.Parameter(stacked, requires_grad=param.requires_grad)
                stacked.num_seeds = len(seeds)
                STACKED[id(stacked)] = stacked
                replaced[id(param)] = stacked
                setattr(nets[0].get_submodule(owner), attr, stacked)
            for name, buffer in list(nets[0].named_buffers()):
                if id(buffer) in stacked_buffers:
                    continue
                owner, _, attr = name.rpartition(".")
                module = nets[0].get_submodule(owner)
                persistent = attr not in module._non_persistent_buffers_set
                module.register_buffer(attr, torch.stack([net.get_buffer(name) for net in nets]), persistent=persistent)
                stacked_buffers.add(id(module.get_buffer(attr)))
        built = [net.to(device) for net in per_seed_nets[0]]
        for net in built:
            net.register_forward_pre_hook(called_through_per_seed)
    for net in built:
        net.num_seeds = len(seeds)  # per_seed's check of its arguments reads it
    return built


def same_weights(a: list, b: list) -> bool:
    """Two builds of networks() whose drawn parameters (those not one value throughout, as a bias of zeros) are all
    equal: the same initial weights for two seeds."""
    drawn = [
        (p, q)
        for x, y in zip(a, b)
        for p, q in zip(x.parameters(), y.parameters())
        if p.numel() > 1 and p.shape == q.shape and not (p == p.reshape(-1)[0]).all()
    ]
    return bool(drawn) and all(torch.equal(p, q) for p, q in drawn)


def check_networks(nets):
    """networks() returns networks: a learnable tensor of their own (SAC's log_alpha) is a part of run.start's."""
    for k, net in enumerate(nets):
        if not isinstance(net, nn.Module):
            raise refusal(
                TypeError,
                f"stack_seeds: networks() returned a {type(net).__name__} (item {k}), not a network (nn.Module): a "
                "learnable tensor outside a network, SAC's log_alpha say, is a tensor [num_seeds, ...] given to run.start's "
                "parts and its optimizer (as sac_continuous_action.py's log_alpha)",
            )


# how many per_seed calls are running (a per-seed function may call another): a network stacked for several seeds
# runs only inside one
inside_per_seed = [0]


def called_through_per_seed(module, inputs):
    """A stacked network runs on one seed's weights, which per_seed swaps in (batched tensors of the vmap); called
    outside per_seed, or inside it without being one of its arguments (a network a per-seed function closes over), it
    would run on the stacked [num_seeds, ...] weights."""
    weight = next(module.parameters(), None)
    if weight is not None and not torch._C._functorch.is_batchedtensor(weight):
        where = "inside per_seed without being its argument" if inside_per_seed[0] else "outside per_seed"
        raise refusal(
            RuntimeError,
            f"{type(module).__name__}, stacked for {module.num_seeds} seeds (its weights [{module.num_seeds}, ...]), was "
            f"called {where}: call it through per_seed, per_seed(actor)(obs), or pass it to the function run through "
            "per_seed as an argument, which gives each seed its own weights and inputs",
        )


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


def name_of(fn) -> str:
    """A per-seed function's name in a message: a function's or method's name (a partial's function's), a network's
    class."""
    fn = unwrapped(fn)
    return getattr(fn, "__name__", None) or type(fn).__name__


def one_per_seed(x: torch.Tensor, n: int) -> bool:
    """A tensor holds one entry per seed: [n, ...]."""
    return x.dim() > 0 and x.shape[0] == n


def by_position(fn, args: tuple, kwargs: dict) -> tuple:
    """Arguments given by keyword, as per_seed takes them: by position, so that their tensors are cut per seed and
    their networks swapped; a keyword-only one that holds no tensor is closed over. Returns (args, fn to call)."""
    signature = inspect.signature(fn.forward if isinstance(fn, nn.Module) else fn)
    try:
        bound = signature.bind(*args, **kwargs)
    except TypeError as error:
        raise refusal(TypeError, f"per_seed({name_of(fn)}): {error}") from None
    bound.apply_defaults()  # every parameter that can be positional is, defaults included
    for name, value in bound.kwargs.items():
        if any(isinstance(x, (torch.Tensor, nn.Module)) for x in tree_flatten(value)[0]):
            kind = "keyword-only argument" if name in signature.parameters else "argument taken by **kwargs"
            raise refusal(
                TypeError,
                f"per_seed({name_of(fn)}): its {kind} `{name}` holds a tensor or a network, which per_seed cuts per "
                "seed only among the arguments it can give by position: make it a positional parameter",
            )
    return bound.args, functools.partial(fn, **bound.kwargs) if bound.kwargs else fn


def check_seeds_dimension(fn, args, n: int):
    """Every tensor argument of a per-seed function is one per seed: [n, ...], in tuples, lists and dicts too. A tensor
    shared by the seeds (an extra [batch] tensor, say) would be cut along its first dimension; this stops it with the
    fix, in one line. So does, with several seeds, an object of another kind (a dataclass) holding a tensor of the
    seeds' shape, which per_seed would not cut: every seed would see all of them. One holding tensors the seeds share
    is passed whole, as written."""
    for position, arg in enumerate(args, 1):
        if n > 1 and not isinstance(arg, (torch.Tensor, tuple, list, dict, nn.Module)) and hasattr(arg, "__dict__"):
            inside = next((k for k, v in vars(arg).items() if isinstance(v, torch.Tensor) and one_per_seed(v, n)), None)
            if inside is not None:
                raise refusal(
                    TypeError,
                    f"per_seed({name_of(fn)}): argument {position} is a {type(arg).__name__} holding `{inside}`, a tensor "
                    f"[{n}, ...] with {n} seeds, which per_seed would not cut per seed (it cuts tensors, and tuples, lists "
                    "and dicts of them): pass it as a tensor or in a NamedTuple; a tensor the seeds share goes inside the "
                    "function (a closure, functools.partial)",
                )
        for x in tree_flatten(arg)[0] if isinstance(arg, (tuple, list, dict)) else [arg]:
            if isinstance(x, torch.Tensor) and not one_per_seed(x, n):
                raise refusal(
                    TypeError,
                    f"per_seed({name_of(fn)}): argument {position} is a tensor of shape {list(x.shape)}, but every "
                    f"tensor argument is one per seed, [{n}, ...] with {n} seed(s): give it that leading dimension, or "
                    "pass a tensor the seeds share inside the function (a closure, functools.partial)",
                )


# the parameters and buffers (by id) of the per-seed calls check_stacked passed: a training step's calls pass the same
# tensors each time, and a parameter added or replaced makes another set
checked_states = set()


def check_stacked(fn, networks: nn.Module, state: dict, n: int):
    """Every parameter and buffer (`state`) of the networks a per-seed function uses holds the n seeds: a parameter
    stack_seeds stacked (one a fork adds to a built network, after stacking, is the same tensor for every seed, and
    vmap would cut it along its first dimension), a buffer [n, ...]."""
    for name, x in state.items():
        parameter = isinstance(x, nn.Parameter)
        if getattr(x, "num_seeds", 1) == n if parameter else one_per_seed(x, n):
            continue
        _, index, path = name.split(".", 2)  # networks.<k>.<path>
        what = (
            f"{'parameter' if parameter else 'buffer'} {type(networks.networks[int(index)]).__name__}.{path} {list(x.shape)}"
        )
        if one_per_seed(x, n):  # the seeds' shape, but not stack_seeds' parameter
            cause = "replaced after stack_seeds built it (load_state_dict(..., assign=True)?): load in place instead"
        else:
            cause = (
                "added to a network after stack_seeds built it?: make it in the network's __init__, so that networks() "
                "builds it and stack_seeds gives each seed its own"
            )
        raise refusal(
            RuntimeError, f"per_seed({name_of(fn)}) with {n} seeds: the {what} is not stacked for the seeds ({cause})"
        )


def python_draws() -> tuple:
    """The states of the generators a vmap cannot draw from per seed: Python's and NumPy's global ones."""
    return random.getstate(), np.random.get_state(legacy=False)


GENERATORS = (np.random.Generator, np.random.RandomState, random.Random)


def reached(fn) -> list:
    """What fn reads that is not an argument, [(label, value)]: its closure, a partial's arguments, the globals it
    names and its helpers' (rl_utils.gpu.probes), and its default arguments."""
    from rl_utils.gpu import probes

    found = []
    for label, read in probes(fn):
        try:
            found.append((label, read()))
        except (ValueError, KeyError, AttributeError, IndexError):  # an unfilled cell
            continue
    function = unwrapped(fn)
    defaults = [*(getattr(function, "__defaults__", None) or ()), *(getattr(function, "__kwdefaults__", None) or {}).values()]
    return found + [(f"{name_of(fn)}'s default argument {k}", x) for k, x in enumerate(defaults)]


def held_by(label: str, x, module) -> list:
    """What a list, tuple or dict holds, or an object of the script's own classes (`module`) in its attributes,
    [(label, value)]; [] for anything else."""
    if isinstance(x, (list, tuple)):
        return [(f"{label}[{i}]", v) for i, v in enumerate(x)]
    if isinstance(x, dict):
        return [(f"{label}[{k!r}]", v) for k, v in x.items()]
    if type(x).__module__ == module and hasattr(x, "__dict__") and not isinstance(x, type):
        return [(f"{label}.{k}", v) for k, v in vars(x).items()]
    return []


def check_trained_tensors_read(fn, n: int, reads: list):
    """With several seeds, a trained tensor (one that requires grad: a multiplier, a network's weight) that fn reads
    from outside its arguments (`reads`, reached(fn)) is not cut into the seeds' rows: every seed's loss reads all of
    it, and its gradient reaches every seed's values. Looked for there and one level into what those hold (a list, a
    dict, an object's attributes, a module's tensors that are not its parameters)."""
    from rl_utils.gpu import module_of

    module = module_of(fn)
    for label, x in reads:
        if isinstance(x, nn.Module):  # its tensors that are not parameters or buffers (per_seed cuts those)
            inside = [(f"{label}.{k}", v) for k, v in vars(x).items() if isinstance(v, torch.Tensor)]
        else:
            inside = held_by(label, x, module)
        for label, x in [(label, x), *inside]:
            if isinstance(x, torch.Tensor) and x.requires_grad:
                raise refusal(
                    RuntimeError,
                    f"per_seed({name_of(fn)}) with {n} seeds reads `{label}`, a trained tensor {list(x.shape)} (it "
                    "requires grad), from outside its arguments (a closure, functools.partial, a global, a default "
                    "argument): every seed's loss would read all of it and its gradient reach every seed's values; give "
                    "it as an argument, one row per seed [num_seeds, ...], which per_seed cuts",
                )


def own_generators(fn, networks: nn.Module, reads: list) -> list:
    """The random generators of a fork's own that fn reaches, [(name, generator)]: a NumPy Generator or RandomState
    or a random.Random (not SystemRandom, which has no state), itself or a method of it (rng.normal), among what fn
    reads (`reads`, reached(fn)), in a list or dict there, among the attributes of an object of the script's own
    classes there (an OU noise's self.rng), or of the networks'."""
    from rl_utils.gpu import module_of

    found = {}

    def look(label, x, depth=0):
        x = x.__self__ if isinstance(getattr(x, "__self__", None), GENERATORS) else x  # a method: rng.normal
        if isinstance(x, GENERATORS):
            if not isinstance(x, random.SystemRandom):
                found.setdefault(id(x), (label, x))
            return
        for item_label, v in held_by(label, x, module) if depth < 2 else ():
            look(item_label, v, depth + 1)

    module = module_of(fn)
    for label, x in reads:
        look(label, x)
    for network in networks.networks:
        for name, layer in network.named_modules():
            for k, v in vars(layer).items():
                look(".".join([type(network).__name__, *([name] if name else []), k]), v, 2)
    return list(found.values())


def generator_state(generator):
    if isinstance(generator, np.random.Generator):
        return generator.bit_generator.state
    return generator.getstate() if isinstance(generator, random.Random) else generator.get_state(legacy=False)


def same_state(a, b) -> bool:
    """Two generator states (nested dicts and tuples of arrays, numbers and strings) are the same."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same_state(a[k], b[k]) for k in a)
    if isinstance(a, tuple) and any(isinstance(x, (dict, np.ndarray)) for x in a):
        return isinstance(b, tuple) and len(a) == len(b) and all(same_state(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and np.array_equal(a, b)
    return a == b


# how many calls of each per-seed function (with several seeds) are watched for draws from Python's or NumPy's
# generator: counted by the function's code, since the scripts wrap it anew at every call (per_seed(fn)(...))
WATCHED_CALLS = 10
watched_calls = {}


def unwrapped(fn):
    """The function a partial (functools.partial(loss, shared)) or a bound method calls."""
    while isinstance(fn, functools.partial):
        fn = fn.func
    return getattr(fn, "__func__", fn)


def code_of(fn):
    """What identifies a per-seed function across its wrappings: its code (a network: its forward's)."""
    fn = unwrapped(fn)
    return getattr(fn, "__code__", None) or getattr(getattr(type(fn), "forward", None), "__code__", type(fn))


def vmap_refusal(fn, n: int, error: RuntimeError) -> RuntimeError:
    """torch.func.vmap's refusal of something a one-seed function did, as one line that says what per_seed needs."""
    if str(error).startswith("Batching rule not implemented for "):
        operation = str(error).split()[5].rstrip(".;")
        return refusal(
            RuntimeError,
            f"per_seed({name_of(fn)}) with {n} seeds: PyTorch cannot run {operation} per seed (torch.func.vmap has no "
            "rule for it), and the function or a layer it calls (spectral_norm's, say) uses it: write that part with "
            "other operations, or train one seed per process (--num-seeds 1)",
        )
    what = " ".join(str(error).split(". ")[0].removeprefix("vmap: ").split())
    if "inplace randomness" in what:  # torch.distributions draws into a tensor it made: no seeds dimension
        what += " (torch.distributions' sample() and rsample() draw that way: write mean + std * torch.randn_like(mean))"
    return refusal(
        RuntimeError,
        f"per_seed({name_of(fn)}) with {n} seeds: {what}. With several seeds the function runs for all "
        "of them at once (torch.func.vmap): it cannot read a tensor's value into Python (.item(), float(), an `if` on a "
        "tensor), take a shape from values (a boolean mask), or draw in place into a tensor the seeds share; write it "
        "with tensor operations (torch.where, a mask multiplied in, clamp) and draw with torch.randn_like(x) and the like",
    )


# how many times each loss (by its name in optimize) was checked for a gradient that crosses the seeds
apart_calls = {}


def gradients(output: torch.Tensor, params: list, name: str) -> tuple:
    """The gradients of `output` in `params` (None where it has none), its graph kept for the loss's own backward."""
    try:
        return torch.autograd.grad(output, params, retain_graph=True, allow_unused=True)
    except RuntimeError as error:
        if "backward through the graph a second time" not in str(error):
            raise
        raise refusal(
            RuntimeError,
            f"{name}: its graph was freed by a backward before the check of the seeds (check_finite after "
            "loss.backward()): check the loss before its backward, as optimize does",
        ) from error


def check_apart(loss: torch.Tensor, name: str):
    """With several seeds, on a loss's first WATCHED_CALLS steps: the first and the last seed's losses have no gradient
    in another seed's weights. A term a fork computes outside per_seed over the stacked parameters (an L2 penalty over
    qf.parameters(), one norm over them all) is one number in every seed's loss: it mixes the seeds, and optimize's sum
    gives each seed num_seeds times its gradient. The seeds' slices of a gradient are exactly zero when they are apart."""
    if not loss.requires_grad or loss.dim() > 1:
        return
    apart_calls[name] = calls = apart_calls.get(name, 0) + 1
    if calls > WATCHED_CALLS:
        return
    if loss.numel() == 1:  # one number: with stacked weights in it, the seeds' losses reduced before optimize
        check_one_per_seed(loss, name)
        return
    n = loss.shape[0]
    params = [p for p in list(STACKED.values()) if p.num_seeds == n and p.requires_grad]
    for k in (0, n - 1) if params else ():
        grads = gradients(loss[k], params, name)
        found = [(p, torch.cat([g[:k], g[k + 1 :]])) for p, g in zip(params, grads) if g is not None]
        crossing = [(others != 0).any() & others.isfinite().all() for _, others in found]  # non-finite: the NaN guard's
        if not found or not torch.stack(crossing).any():  # one read of the device
            continue
        p = found[int(torch.stack(crossing).int().argmax())][0]
        raise refusal(
            RuntimeError,
            f"{name}: seed index {k}'s loss has a gradient in other seeds' weights (a parameter {list(p.shape)}): a term "
            "computed outside per_seed over the stacked parameters (an L2 penalty over qf.parameters(), a norm over them "
            "all, a mean over the seeds) is one number in every seed's loss, which mixes the seeds and gives each seed "
            "num_seeds times its gradient; compute it inside the function run through per_seed, on one seed's weights",
        )


# With several seeds, the optimizers run.start was given, each watched on its first WATCHED_CALLS steps (their count
# here): a step's gradients come from losses optimize took (check_finite saw them), whose trained tensors (the leaves
# of their graphs, by id) are in `checked_leaves`. The watch ends after WATCH_RECORDS losses, so an optimizer that
# never steps (SAC's alpha optimizer without --autotune) does not keep it going.
WATCH_RECORDS = 100
watched_steps = weakref.WeakKeyDictionary()
checked_leaves = set()
records_left = 0
handles = {}  # each watched optimizer's hook, by the optimizer's id


def record_checked(loss: torch.Tensor):
    """While optimizers are watched: the tensors `loss` trains (its graph's leaves), which an optimizer's step may then
    update."""
    global records_left
    if not watched_steps or loss.grad_fn is None:
        return
    if records_left <= 0:
        watched_steps.clear()  # the watch is over; each hook removes itself at its next call
        return
    records_left -= 1
    leaves, seen, nodes = set(), set(), [loss.grad_fn]
    while nodes:
        node = nodes.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        if getattr(node, "variable", None) is not None:  # AccumulateGrad: a leaf's gradient
            leaves.add(id(node.variable))
        nodes.extend(next_node for next_node, _ in node.next_functions)
    checked_leaves.update(leaves)


def watch_steps(optimizers: dict, num_seeds: int):
    """With several seeds, each optimizer's first WATCHED_CALLS steps stop if a gradient they apply comes from a loss
    optimize did not take: a backward written by hand (qf_loss.mean().backward(), then q_optimizer.step()) divides each
    seed's gradient by the number of seeds, and no check sees a term that mixes the seeds. An earlier run's watch
    ends."""
    global records_left
    for handle in handles.values():  # an earlier run's watch ends
        handle.remove()
    handles.clear()
    watched_steps.clear()
    checked_leaves.clear()  # ids of an earlier run's tensors, which new ones may reuse
    apart_calls.clear()  # this run's losses are looked at on their first steps (check_apart), as its first run's were
    records_left = WATCH_RECORDS if num_seeds > 1 else 0
    named = {}  # each optimizer once, by its first name
    for name, optimizer in optimizers.items():
        named.setdefault(id(optimizer), (name, optimizer))
    for name, optimizer in named.values() if num_seeds > 1 else ():

        def before_step(optimizer, args, kwargs, name=name):
            if optimizer not in watched_steps:  # its watch is over
                handles.pop(id(optimizer)).remove()
                return
            params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
            if any(p.is_cuda for p in params) and torch.cuda.is_current_stream_capturing():
                return  # a recorded update: its eager calls were watched
            watched_steps[optimizer] += 1
            if watched_steps[optimizer] >= WATCHED_CALLS:
                del watched_steps[optimizer]
            unchecked = [p for p in params if id(p) not in checked_leaves]
            checked_leaves.difference_update(id(p) for p in params)
            if unchecked:
                raise refusal(
                    RuntimeError,
                    f"{name}.step() with {num_seeds} seeds: a gradient it applies (a parameter "
                    f"{list(unchecked[0].shape)}) comes from a loss optimize did not see: a backward written by hand "
                    f"(qf_loss.mean().backward()) divides each seed's gradient by {num_seeds}, and no check sees a term "
                    f'that mixes the seeds; step through optimize(qf_loss, "qf_loss", {name}), which takes the loss one '
                    "per seed (a step of your own: check_finite(loss, name) on the loss before its backward)",
                )

        watched_steps[optimizer] = 0
        handles[id(optimizer)] = optimizer.register_step_pre_hook(before_step)


def check_one_per_seed(loss: torch.Tensor, name: str):
    """A loss of one number with a gradient in weights stacked for several seeds: the seeds' losses were reduced
    before optimize (loss.mean(): each seed's gradient divided by the number of seeds, which SGD and clipping by
    norm keep; loss.sum(): a reduction optimize makes itself). optimize takes them one per seed and sums them."""
    params = [p for p in list(STACKED.values()) if p.num_seeds > 1 and p.requires_grad]
    if not params:
        return
    grads = gradients(loss.reshape(()), params, name)
    reached = [(p, g) for p, g in zip(params, grads) if g is not None]
    if not reached or not torch.stack([(g != 0).any() for _, g in reached]).any():  # one read of the device
        return
    n = reached[0][0].num_seeds
    raise refusal(
        RuntimeError,
        f"{name}: one number for {n} seeds' weights (a loss of shape {list(loss.shape)}): the seeds' losses were "
        f"reduced before optimize (a mean divides each seed's gradient by {n}; a sum is optimize's own work); pass them "
        f"one per seed, [num_seeds] as per_seed returns them (optimize({name}, ...), not optimize({name}.mean(), ...))",
    )


def per_seed(fn):
    """fn (a function or a network), written for one seed, run for every seed: its tensor arguments (and NamedTuples
    of them) carry a leading seeds dimension, its networks come from stack_seeds, what it returns gains that dimension.
    With several seeds, what vmap cannot run per seed stops with one line: a value read into Python, and (on the
    first WATCHED_CALLS calls) a draw from Python's or NumPy's generator, or from one of the fork's own that fn reaches,
    which would be one draw all seeds share."""

    @functools.wraps(fn)
    def run(*args, **kwargs):
        args, call = by_position(fn, args, kwargs) if kwargs else (args, fn)
        n = num_seeds(fn, args)
        check_seeds_dimension(fn, args, n)
        if n == 1:  # as written, on seed 0's share of each tensor
            one_seed = tree_map(lambda x: x[0] if isinstance(x, torch.Tensor) else x, args)
            return tree_map(lambda x: x.unsqueeze(0) if isinstance(x, torch.Tensor) else x, call(*one_seed))
        if torch.compiler.is_compiling():
            raise refusal(
                RuntimeError,
                f"per_seed({name_of(fn)}) with {n} seeds under torch.compile: the seeds' vmap and its checks do not "
                "compile; train one seed per process (--num-seeds 1) to compile, or record the update with --cudagraphs",
            )
        modules = [fn, getattr(fn, "__self__", None), *args]  # fn may be a network or its method: per_seed(actor)(obs)
        networks = _Networks(list({id(x): x for x in modules if isinstance(x, nn.Module)}.values()))
        state = {**dict(networks.named_parameters()), **dict(networks.named_buffers())}
        checked = tuple(map(id, state.values()))  # the same tensors as a call checked before: nothing new to look at
        if checked not in checked_states:
            check_stacked(fn, networks, state, n)
            if len(checked_states) >= 64:  # a network that makes new buffers at each call: keep the set small
                checked_states.clear()
            checked_states.add(checked)
        # each tensor is cut along the seeds, in tuples, lists and dicts too; anything else is the seeds' own
        in_dims = [tree_map(lambda x: 0 if isinstance(x, torch.Tensor) else None, x) for x in args]

        def one_seed(state, *args):
            return functional_call(networks, state, (call, args))

        code = code_of(fn)
        watched_calls[code] = calls = watched_calls.get(code, 0) + 1
        if calls <= WATCHED_CALLS:
            reads = reached(fn)
            check_trained_tensors_read(fn, n, reads)
            own = own_generators(fn, networks, reads)
            before = python_draws(), [generator_state(g) for _, g in own]
        else:
            before = None
        inside_per_seed[0] += 1
        try:
            out = vmap(one_seed, in_dims=(0, *in_dims), randomness="different")(state, *args)
        except RuntimeError as error:
            refused = ("vmap:", "Batching rule not implemented for ")
            if str(error).startswith(refused) or "doesn't have storage" in str(error):  # .tolist() gives the latter
                raise vmap_refusal(fn, n, error) from error
            raise
        finally:
            inside_per_seed[0] -= 1
        if before is not None:
            moved = [
                f"`{label}`, a random generator of its own"
                for (label, g), was in zip(own, before[1])
                if not same_state(was, generator_state(g))
            ]
            if not same_state(before[0], python_draws()):
                moved.insert(0, "Python's or NumPy's random generator (random, np.random)")
            if moved:
                raise refusal(
                    RuntimeError,
                    f"per_seed({name_of(fn)}) with {n} seeds drew from {moved[0]}, "
                    "which a vmap over the seeds runs once, for all of them: one draw the seeds would share; draw with "
                    "torch (torch.randn_like(x), torch.rand(shape), ...), which gives each seed its own",
                )
        return out

    return run


# Gradient clipping by norm, per seed. torch.nn.utils.clip_grad_norm_ takes one norm over all the gradients it is
# given; with several seeds stacked that would be one norm over every seed's, and a seed's step would depend on the
# others'. Its two parts, which it looks up at each call, are replaced: given the gradients of stacked parameters they
# take each seed's own norm (a tensor [num_seeds]) and scale each seed's gradients by its own coefficient, as a
# single-seed run of that seed would; any other gradients go to PyTorch's own functions unchanged.
torch_total_norm, torch_clip_grads_with_norm = clip_grad._get_total_norm, clip_grad._clip_grads_with_norm_


def stacked_seeds(grads: list) -> int:
    """The number of seeds stacked in these gradients (0 when none is a stacked parameter's gradient)."""
    stacked = {id(p.grad): p.num_seeds for p in list(STACKED.values()) if p.grad is not None}
    found = {stacked.get(id(g), 0) for g in grads}
    if len(found) > 1:
        counts = ", ".join(f"{n} seeds" if n else "no seeds dimension" for n in sorted(found))
        raise refusal(
            RuntimeError,
            f"clip_grad_norm_: gradients of parameters stacked otherwise ({counts}) in one call; one norm over them "
            "would mix the seeds: clip each process's stacked networks in a call of their own",
        )
    return found.pop() if found else 0


@torch.no_grad()
def get_total_norm(tensors, norm_type=2.0, error_if_nonfinite=False, foreach=None) -> torch.Tensor:
    tensors = [tensors] if isinstance(tensors, torch.Tensor) else list(tensors)
    n = stacked_seeds(tensors)
    if not n:
        return torch_total_norm(tensors, norm_type, error_if_nonfinite, foreach)
    norm_type = float(norm_type)  # PyTorch takes 'inf' too
    norms = torch.stack([torch.linalg.vector_norm(t.reshape(n, -1), norm_type, dim=1) for t in tensors])
    total = torch.linalg.vector_norm(norms, norm_type, dim=0)  # [num_seeds]: each seed's norm over its gradients
    if error_if_nonfinite and not torch.isfinite(total).all():
        raise refusal(
            RuntimeError, f"the total norm of order {norm_type} of a seed's gradients is non-finite: it cannot be clipped"
        )
    return total


@torch.no_grad()
def clip_grads_with_norm_(parameters, max_norm, total_norm, foreach=None):
    parameters = [parameters] if isinstance(parameters, torch.Tensor) else list(parameters)
    grads = [p.grad for p in parameters if p.grad is not None]
    n = stacked_seeds(grads)
    if not n:
        return torch_clip_grads_with_norm(parameters, max_norm, total_norm, foreach)
    coefficient = (float(max_norm) / (torch.as_tensor(total_norm) + 1e-6)).clamp(max=1.0)  # one per seed (or one for all)
    for g in grads:
        g.mul_(coefficient.reshape(-1, *[1] * (g.dim() - 1)))


clip_grad._get_total_norm, clip_grad._clip_grads_with_norm_ = get_total_norm, clip_grads_with_norm_
torch.nn.utils.get_total_norm, torch.nn.utils.clip_grads_with_norm_ = get_total_norm, clip_grads_with_norm_


# Re-initialising a stacked parameter mid-run (a reset: layer.reset_parameters(), nn.init.kaiming_uniform_(weight))
# treats each seed's slice as the one-seed tensor it is. The fan-based initialisations (kaiming, xavier, nn.Linear's
# own) read a weight's fans from one seed's [out, in], not from [num_seeds, out, in]; the initialisations shaped by
# the whole tensor (orthogonal_, sparse_, eye_, dirac_), called through torch.nn.init, initialise each seed's slice
# on its own. The element-wise ones (normal_, uniform_, zeros_, trunc_normal_ with its std) need nothing.
torch_fans = init._calculate_fan_in_and_fan_out


def seeds_in(tensor: torch.Tensor) -> int:
    """How many seeds a tensor holds stacked: a stacked parameter's number, also for its .data or .detach() (the same
    memory, the same shape); 1 for any other tensor and for one seed's slice, weight[k]. Another part of a stacked
    parameter (weight[:, :3]) is refused: no initialisation of it is one seed's."""
    if getattr(tensor, "num_seeds", 1) > 1:
        return tensor.num_seeds
    for p in list(STACKED.values()):
        if p.device == tensor.device and p.untyped_storage().data_ptr() == tensor.untyped_storage().data_ptr():
            if tensor.shape == p.shape and tensor.data_ptr() == p.data_ptr():
                return p.num_seeds
            if tensor.shape != p.shape[1:]:
                raise refusal(
                    RuntimeError,
                    f"nn.init on a part {list(tensor.shape)} of a parameter stacked for {p.num_seeds} seeds "
                    f"{list(p.shape)}: initialise the whole parameter (each seed's slice as one seed's) or a seed's "
                    "slice, weight[k]",
                )
    return 1


def fans(tensor: torch.Tensor) -> tuple:
    return torch_fans(tensor[0] if seeds_in(tensor) > 1 else tensor)


def each_seed(initialise):
    @functools.wraps(initialise)
    def initialise_each_seed(tensor, *args, **kwargs):
        if seeds_in(tensor) == 1:
            return initialise(tensor, *args, **kwargs)
        for seed_tensor in tensor:  # each a view into the stacked parameter, initialised in place
            initialise(seed_tensor, *args, **kwargs)
        return tensor

    return initialise_each_seed


init._calculate_fan_in_and_fan_out = fans

# a copy of a stacked network (copy.deepcopy(qf): a fork's second target, say) stays stacked, for the clipping and
# the initialisations above
torch_parameter_deepcopy = nn.Parameter.__deepcopy__


def parameter_deepcopy(self, memo):
    copied = torch_parameter_deepcopy(self, memo)
    if getattr(self, "num_seeds", 1) > 1 and getattr(copied, "num_seeds", 1) == 1:
        copied.num_seeds = self.num_seeds
        STACKED[id(copied)] = copied
    return copied


nn.Parameter.__deepcopy__ = parameter_deepcopy
for name in ("orthogonal_", "sparse_", "eye_", "dirac_"):
    setattr(init, name, each_seed(getattr(init, name)))


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


def check_parts_per_seed(states: dict, n: int):
    """With n seeds, each tensor of a part's state (the part itself, or its state_dict()'s) is one per seed, [n, ...]
    (a ReplayBuffer's rows, SAC's log_alpha): one [1] or [] would be one value every seed trains and reads."""
    for name, value in states.items():
        tensors = {name: value} if isinstance(value, torch.Tensor) else value if isinstance(value, dict) else {}
        for key, t in tensors.items():
            if isinstance(t, torch.Tensor) and not one_per_seed(t, n):
                raise refusal(
                    ValueError,
                    f"run.start's part `{name}`: its state holds `{key}`, a tensor of shape {list(t.shape)}, but with {n} "
                    f"seeds each tensor of a part is one per seed, [{n}, ...], which a checkpoint cuts into the seeds' "
                    "shares (one tensor for all would be one value every seed trains and reads); give it that leading "
                    "dimension",
                )


def split_seeds(state: dict, parts: dict, eval_returns: list, run_dirs: list) -> list:
    """One checkpoint per seed from a snapshot() of the stacked seeds: the seed's cut of every parameter, optimizer
    moment, replay buffer and tensor part, its env and its evaluations; the flags, the step and the process's
    random generators in all."""
    n = len(run_dirs)
    if n > 1:
        check_parts_per_seed({name: state[name] for name in parts}, n)
    # an optimizer's state per parameter: its moments are the parameter's shape, one per seed; its step counter
    # (0-d) is the seeds'. The keys cut are recorded, as a moment of a 0-d parameter is 0-d in a seed's cut too.
    cut = {
        name: {i: [key for key, t in s.items() if isinstance(t, torch.Tensor) and t.dim()] for i, s in sd["state"].items()}
        for name, sd in (state["optimizers"].items() if n > 1 else ())
    }
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
                        i: {key: t[k].clone() if key in cut[name][i] else t for key, t in s.items()}
                        for i, s in sd["state"].items()
                    },
                }
                for name, sd in state["optimizers"].items()
            }
            checkpoint["seed_cut"] = cut
        checkpoints.append(checkpoint)
    return checkpoints


def join_seeds(checkpoints: list, parts: dict) -> dict:
    """split_seeds() undone: the seeds' checkpoints as one snapshot() of the stacked seeds, for restore()."""
    first = checkpoints[0]
    if len(checkpoints) == 1:
        return first
    state = dict(first)
    cut = first.get("seed_cut", {})  # which optimizer states split_seeds cut (before it recorded them: the n-d ones)

    def was_cut(name, i, key, t) -> bool:
        return key in cut[name][i] if name in cut else t.dim() > 0

    state["nets"] = {
        name: {key: torch.stack([c["nets"][name][key] for c in checkpoints]) for key in sd}
        for name, sd in first["nets"].items()
    }
    state["optimizers"] = {
        name: {
            **sd,
            "state": {
                i: {
                    key: torch.stack([c["optimizers"][name]["state"][i][key] for c in checkpoints])
                    if was_cut(name, i, key, t)
                    else t
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
            state = uncompiled(x).state_dict()  # a torch.compile'd network saved as the network it wraps
            model[name] = seed_share(state, k) if num_seeds > 1 else state
        elif isinstance(x, torch.Tensor):
            model[name] = x.detach().cpu()[k : k + 1].clone()
        else:  # an object with a state_dict(), e.g. PPO's observation statistics: its tensors one per seed
            model[name] = part_share(x.state_dict(), k) if num_seeds > 1 else x.state_dict()
    return model
