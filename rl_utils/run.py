"""A process's runs: one per seed (--num-seeds), each with its folder under runs/, its logs (rl_utils.logs), its
checkpoints and its saved model, as an ordinary single-seed run has them."""

import ast
import collections
import contextlib
import copy
import dataclasses
import functools
import hashlib
import inspect
import itertools
import linecache
import os
import random
import re
import sys
import textwrap
import time
import types
import weakref

import numpy as np
import torch
from torch.nn.utils.spectral_norm import SpectralNorm
from torch.nn.utils.weight_norm import WeightNorm
from torch.optim import lr_scheduler
from tqdm import tqdm

from rl_utils import checkpoints as ckpt
from rl_utils.cli import RESUMABLE_FLAGS, script_of
from rl_utils.buffers import ReplayBuffer
from rl_utils.envs import SeedEnvs, policy_probe
from rl_utils.errors import fail, refusal
from rl_utils.logs import Logs
from rl_utils.numerics import NonFiniteError
from rl_utils.seeds import check_parts_per_seed, join_seeds, model_of_seed, split_seeds, watch_steps


def global_generators() -> dict:
    """The states of the global random generators a checkpoint holds (Python's, NumPy's, torch's; CUDA's once in
    use), as bytes, by the name an error gives them."""
    states = {
        "Python's": repr(random.getstate()).encode(),
        "NumPy's": (lambda _, key, *rest: key.tobytes() + repr(rest).encode())(*np.random.get_state()),
        "torch's": torch.get_rng_state().numpy().tobytes(),
    }
    if torch.cuda.is_initialized():
        states["CUDA's"] = b"".join(state.numpy().tobytes() for state in torch.cuda.get_rng_state_all())
    return states


def args_counted(code, names: set) -> set:
    """The attributes of `names` (main's names for args) that main or a function it defines changes from their own
    value (args.acted += 1, args.acted = args.acted + 1); not one set anew (args.frac = 1 - step / total)."""
    body = main_body(code)
    counted = set()
    for n in ast.walk(body) if body is not None else ():
        targets = n.targets if isinstance(n, ast.Assign) else [n.target] if isinstance(n, ast.AugAssign) else []
        for t in targets:
            if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id in names:
                if isinstance(n, ast.AugAssign) or from_its_value(t, n.value):
                    counted.add(t.attr)
    return counted


def fresh_run_only(frame) -> bool:
    """Whether main runs code between run.start and its loop only in a fresh run (if not run.checkpoints: a warm-up
    of random steps): a resumed run skips it, so its draws are not redrawn on --resume."""
    body = main_body(frame.f_code)
    loop = training_loop(body)
    if loop is None:
        return False
    start = frame.f_lineno - frame.f_code.co_firstlineno + 1  # run.start's line, in body's numbering
    between = [n for n in own_nodes(body) if isinstance(n, ast.If) and start < n.lineno < loop.lineno]
    return any(
        isinstance(v, ast.Attribute) and v.attr in ("checkpoints", "start_step") for n in between for v in ast.walk(n.test)
    )


def part_name(name: str) -> str:
    """A name run.start can take for a part main holds as `name` (`q_schedulers[0]`: q_schedulers_0), not one of a
    checkpoint's own keys."""
    name = re.sub(r"\W+", "_", name).strip("_")
    return f"my_{name}" if name in ckpt.OWN_KEYS else name


def own_generator(x) -> bool:
    """A random generator with a state of its own: not the process's global ones (Python's, NumPy's, torch's), which
    every checkpoint holds, nor a random.SystemRandom, which has no state."""
    is_global = any(x is g for g in (random._inst, np.random.mtrand._rand, torch.default_generator))
    return isinstance(x, ckpt.GENERATORS) and not isinstance(x, random.SystemRandom) and not is_global


def held(names: dict, depth: int = 2):
    """(label, object) for each of main's names and what its lists, tuples and dicts hold, `depth` levels down
    (`q_optimizers[0]`, `nets['actor']`): where a network, optimizer or state main holds may be."""
    for name, x in names.items():
        yield name, x
        if depth and isinstance(x, (list, tuple)):
            yield from held({f"{name}[{i}]": v for i, v in enumerate(x)}, depth - 1)
        elif depth and isinstance(x, dict):
            yield from held({f"{name}[{k!r}]": v for k, v in x.items()}, depth - 1)


def enclosed(names: dict, own: str = "", skip=frozenset(), depth: int = 2):
    """(label, object) for what the functions and objects among `names` (and in their lists, tuples and dicts) hold,
    `depth` levels down: a closure's variables (the function a helper returns, closing over the model it built there),
    a function's default arguments, a functools.partial's arguments, a bound method's object, the attributes of an
    object of the script's own class (module `own`: a helper object holding a model and its optimizer); and what their
    lists, tuples and dicts hold. What `skip` names (by id: run.start's parts, checkpointed whole) is not looked into."""
    for name, x in held(names, 1):
        if id(x) in skip:
            continue
        inner = {}
        attributes = vars_of(x) if type(x).__module__ == own and not isinstance(x, (type, torch.nn.Module)) else None
        if isinstance(attributes, dict):
            inner |= {f"{name}.{k}": v for k, v in attributes.items()}
        if isinstance(x, functools.partial):
            inner |= {f"{name}'s argument {i}": v for i, v in enumerate(x.args)}
            inner |= {f"{name}'s argument `{k}`": v for k, v in x.keywords.items()}
            x = x.func
        if isinstance(x, types.MethodType):
            inner[f"{name}'s object"] = x.__self__
            x = x.__func__
        if isinstance(x, types.FunctionType):
            inner |= {f"{name}'s default {i}": v for i, v in enumerate(x.__defaults__ or ())}
            inner |= {f"{name}'s default `{k}`": v for k, v in (x.__kwdefaults__ or {}).items()}
            for var, cell in zip(x.__code__.co_freevars, x.__closure__ or ()):
                try:
                    inner[f"{name}'s `{var}`"] = cell.cell_contents
                except ValueError:  # a cell not yet bound
                    pass
        yield from held(inner, 1)
        if depth > 1:
            yield from enclosed(inner, own, skip, depth - 1)


def vars_of(x) -> "dict | None":
    try:
        return vars(x)
    except TypeError:  # no __dict__ (__slots__, a builtin)
        return None


def own_nodes(node):
    """The nodes of `node`'s own code: not those of the functions, lambdas and classes it defines (their def is
    yielded, not their body)."""
    for child in ast.iter_child_nodes(node):
        yield child
        if not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            yield from own_nodes(child)


def functions_of(node, shadowed=frozenset()):
    """(function, names an enclosing function between `node` and it binds itself) for each function `node` defines,
    nested ones too: a nonlocal there names that function's variable, not node's."""
    for child in own_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield child, shadowed
            yield from functions_of(child, shadowed | bound_in(child))


def main_body(code) -> "ast.AST | None":
    """The syntax tree of `code` (main, or a script's module: a script without main), its lines numbered from 1 at
    code's first; None if its source cannot be read (exec)."""
    try:
        if code.co_name == "<module>":  # inspect reads a module's code as its first statement only
            linecache.checkcache(code.co_filename)
            source = "".join(linecache.getlines(code.co_filename))
        else:
            source = textwrap.dedent(inspect.getsource(code))
        tree = ast.parse(source)
    except (OSError, TypeError, SyntaxError, IndentationError):
        return None
    return tree if code.co_name == "<module>" or not tree.body else tree.body[0]


def loops(node):
    """The loops `node` runs, outermost first; those of the functions and classes it defines are theirs."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            continue
        if isinstance(child, (ast.For, ast.While, ast.AsyncFor)):
            yield child
        yield from loops(child)


def end_step_calls(node) -> list:
    """The calls of something's end_step (run.end_step(step)) within `node`."""
    return [
        n
        for n in ast.walk(node)
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "end_step"
    ]


def calls_end_step(node) -> bool:
    return bool(end_step_calls(node))


def training_loop(body) -> "ast.AST | None":
    """The first loop of `body` (main_body's) that calls run.end_step, or None (no such loop, or no source)."""
    return next((loop for loop in loops(body) if calls_end_step(loop)), None) if body is not None else None


# methods that change their object from what it held (an accumulation: a list's, a deque's or a set's new items, a
# tensor's in-place arithmetic, mul_); not those that overwrite it whole (copy_, fill_, zero_, an in-place draw,
# bernoulli_) or empty it (clear), nor a dict's update
ADDERS = {"append", "extend", "appendleft", "extendleft", "insert", "add"}
OVERWRITERS = {"copy_", "fill_", "zero_", "set_", "requires_grad_", "share_memory_", "clear"}
OVERWRITERS |= {"normal_", "uniform_", "bernoulli_", "exponential_", "geometric_", "cauchy_", "log_normal_", "random_"}


def root_of(target) -> "tuple[str | None, bool]":
    """The plain name a subscript or attribute chain changes (counts[0], stats["a"]["n"], update.calls) and whether the
    chain goes through an attribute; (None, ...) where it starts from something else (self.x[0]: self is a name)."""
    through_attribute = False
    while isinstance(target, (ast.Subscript, ast.Attribute)):
        through_attribute |= isinstance(target, ast.Attribute)
        target = target.value
    return (target.id if isinstance(target, ast.Name) else None), through_attribute


def changed_in_place(node) -> "str | None":
    """The plain name whose object `node` changes from what it held (returns.append(r), noise.mul_(0.99),
    counts[0] += 1, stats["a"]["n"] += 1), or None."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Name):
        method = node.func.attr
        if method in ADDERS or (method.endswith("_") and not method.startswith("_") and method not in OVERWRITERS):
            return node.func.value.id
    if isinstance(node, ast.AugAssign) and isinstance(node.target, ast.Subscript):
        name, through_attribute = root_of(node.target)
        return None if through_attribute else name
    return None


def overwrites_from_itself(call, name: str) -> bool:
    """Whether an overwriting call's arguments read the name it overwrites (ema.copy_(0.9 * ema + x)): a change."""
    arguments = [*call.args, *(k.value for k in call.keywords)]
    return any(isinstance(v, ast.Name) and v.id == name for a in arguments for v in ast.walk(a))


def from_its_value(target, value) -> bool:
    """Whether an assignment to an entry or attribute (stats["n"] = ..., update.calls = ...) computes it from that
    entry's or attribute's own value: stats["n"] + 1, stats.get("n", 0) + 1, getattr(update, "calls", 0) + 1; not
    another entry (adv[t] = r[t] + g * adv[t + 1]) nor the container's dtype or device (buf[i] = as_tensor(x,
    dtype=buf.dtype))."""
    written, container = ast.unparse(target), ast.unparse(target.value)
    for v in ast.walk(value):
        if isinstance(v, (ast.Subscript, ast.Attribute)) and ast.unparse(v) == written:
            return True
        if isinstance(v, ast.Call) and isinstance(v.func, ast.Attribute) and v.func.attr == "get":
            if isinstance(target, ast.Subscript) and ast.unparse(v.func.value) == container:
                return True
        if isinstance(v, ast.Call) and isinstance(v.func, ast.Name) and v.func.id == "getattr" and len(v.args) >= 2:
            attribute = isinstance(target, ast.Attribute) and ast.unparse(v.args[0]) == container
            if attribute and isinstance(v.args[1], ast.Constant) and v.args[1].value == target.attr:
                return True
    return False


def overwritten_whole(node) -> "str | None":
    """The plain name whose object `node` overwrites or empties whole (x.copy_(y), x.fill_(0), x.clear(), x[:] = y),
    so that what it held before is gone, or None."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Name):
        return node.func.value.id if node.func.attr in OVERWRITERS else None
    if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Store) and isinstance(node.value, ast.Name):
        whole = isinstance(node.slice, ast.Slice) and not (node.slice.lower or node.slice.upper or node.slice.step)
        return node.value.id if whole else None
    return None


def name_events(node, local=frozenset()):
    """(name, what, line) for each plain name `node` reads (what: "read"), binds or overwrites whole ("set": x = ...,
    x.fill_(0), x.clear(), x[:] = ...) or changes in place ("changed", which reads it too: x.append(r), x[0] += 1,
    x.copy_(0.9 * x + y)), in the order Python does it (an assignment's value before its target; `x += 1`
    reads x first); what functions and lambdas defined there read is left out, as are a comprehension's own names."""
    changed = changed_in_place(node)
    if changed and changed not in local:
        yield changed, "changed", node.lineno
    overwritten = overwritten_whole(node)
    if overwritten and overwritten not in local:
        if isinstance(node, ast.Call):  # its arguments first; from its own value (ema.copy_(0.9 * ema + x)): a change
            yield from (e for a in [*node.args, *(k.value for k in node.keywords)] for e in name_events(a, local))
            yield overwritten, "changed" if overwrites_from_itself(node, overwritten) else "set", node.lineno
            return
        yield overwritten, "set", node.lineno  # x[:] = ...: the assignment's value came first
        return
    if isinstance(node, ast.Name):
        if node.id not in local:
            yield node.id, "read" if isinstance(node.ctx, ast.Load) else "set", node.lineno
        return
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        yield from (e for d in node.decorator_list for e in name_events(d, local))
        yield node.name, "set", node.lineno
        return
    if isinstance(node, ast.Lambda):
        return
    if isinstance(node, (ast.ListComp, ast.SetComp, ast.GeneratorExp, ast.DictComp)):
        own = local | {n.id for g in node.generators for n in ast.walk(g.target) if isinstance(n, ast.Name)}
        yield from name_events(node.generators[0].iter, local)
        parts = [*(x for g in node.generators for x in [*g.ifs]), *(g.iter for g in node.generators[1:])]
        parts += [node.key, node.value] if isinstance(node, ast.DictComp) else [node.elt]
        for part in parts:
            yield from name_events(part, own)
        return
    if isinstance(node, ast.AugAssign):
        if isinstance(node.target, ast.Name) and node.target.id not in local:
            yield node.target.id, "read", node.lineno
        order = [node.value, node.target]
    elif isinstance(node, (ast.Assign, ast.AnnAssign)):
        order = [node.value] if node.value is not None else []
        order += node.targets if isinstance(node, ast.Assign) else [node.target]
    elif isinstance(node, ast.NamedExpr):
        order = [node.value, node.target]
    elif isinstance(node, (ast.For, ast.AsyncFor)):
        order = [node.iter, node.target, *node.body, *node.orelse]
    else:
        order = ast.iter_child_nodes(node)
    for child in order:
        yield from name_events(child, local)


NOT_A_VALUE = object()
# what an expression main binds before its loop may call to be computed at run.start (value_before_loop): makers of
# numbers, arrays, tensors and containers, from these modules
SAFE_CALLS = {"zeros", "ones", "full", "zeros_like", "ones_like", "full_like", "array", "asarray", "tensor", "as_tensor"}
SAFE_CALLS |= {"list", "dict", "set", "tuple", "deque", "len", "float", "int", "bool", "min", "max", "abs"}
SAFE_MODULES = {"numpy", "torch", "collections", "builtins"}


@dataclasses.dataclass
class Carried:
    """A plain local main's loop carries from one step to the next (carried_locals)."""

    name: str
    line: int  # where the loop first reads it (or changes it in place)
    set_at: int  # the line of its last binding before the loop
    value: "ast.expr | None"  # that binding's expression, where it binds the name alone (not x += 1, nor a, b = f())
    via: str = ""  # a function main defines that changes it, where the loop itself does not
    how: str = ""  # how `via` changes it (changed_by): "nonlocal", "in place", "attribute", "default"
    text: str = ""  # the statement that changes it, as written (counts[0] += 1)


def value_before_loop(node, frame):
    """The value `node` (an expression main binds a carried local to, after run.start) gives, computed at run.start
    from main's names where it makes nothing but numbers, strings, arrays, tensors and containers (0.0, -np.inf,
    np.zeros(len(run.seeds)), deque(maxlen=100)) and can be computed there; else NOT_A_VALUE."""
    if node is None:
        return NOT_A_VALUE
    names = {**frame.f_globals, **frame.f_locals}

    def evaluate(expression):
        return eval(compile(ast.Expression(body=expression), "<main>", "eval"), names)

    try:
        for n in ast.walk(node):
            if isinstance(n, (ast.Lambda, ast.NamedExpr, ast.Await, ast.Yield, ast.YieldFrom, ast.comprehension)):
                return NOT_A_VALUE
            if isinstance(n, ast.Call):
                if not all(isinstance(x, (ast.Name, ast.Attribute, ast.Load)) for x in ast.walk(n.func)):
                    return NOT_A_VALUE
                fn = evaluate(n.func)
                module = (getattr(fn, "__module__", None) or "").split(".")[0]
                if module not in SAFE_MODULES or getattr(fn, "__name__", None) not in SAFE_CALLS:
                    return NOT_A_VALUE
        return evaluate(node)
    except Exception:  # a name bound after run.start, a value it cannot compute
        return NOT_A_VALUE


def carried_locals(code, given=frozenset()) -> list:
    """Each plain local of `code` (main, or a script's module) that its loop with run.end_step carries from one step
    to the next: read in the loop before the loop sets it (noise *= 0.99, best = max(best, ret), a recurrent state), or
    changed there in place (returns.append(ret)); no checkpoint holds it, so --resume starts it again from its value
    before the loop. Left out: the names in `given` (what run.start was given: the checkpoints hold them), the loop's
    own variable, and what run.start restores: its return and run.start_step, and names computed before the loop from
    them or, after run.start, from what it was given (alpha = log_alpha.exp()). [] if the source cannot be read."""
    body = main_body(code)
    loop = training_loop(body)
    if loop is None:
        return []
    runs = {call.func.value.id for call in end_step_calls(loop) if isinstance(call.func.value, ast.Name)}

    def from_run(node) -> bool:  # run.start(...) or run.start_step
        return any(
            isinstance(n, ast.Attribute) and n.attr in ("start", "start_step") and getattr(n.value, "id", None) in runs
            for n in ast.walk(node)
        )

    kinds = (ast.Assign, ast.AnnAssign, ast.AugAssign, ast.NamedExpr)
    before = sorted(
        (n for n in own_nodes(body) if isinstance(n, kinds) and n.value is not None and n.lineno < loop.lineno),
        key=lambda n: (n.lineno, n.col_offset),
    )
    started = min((n.lineno for n in ast.walk(body) if isinstance(n, ast.Call) and from_run(n.func)), default=loop.lineno)
    restored, set_at, value = set(), {}, {}
    for node in before:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target]
        names = [n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)]
        read = {n.id for n in ast.walk(node.value) if isinstance(n, ast.Name)}
        if from_run(node.value) or read & restored or (node.lineno >= started and read & set(given)):
            restored |= set(names)
        pairs = [] if isinstance(node, ast.AugAssign) or len(targets) > 1 else [(targets[0], node.value)]
        if pairs and isinstance(pairs[0][0], ast.Tuple) and isinstance(node.value, ast.Tuple):
            pairs = list(zip(pairs[0][0].elts, node.value.elts)) if len(node.value.elts) == len(pairs[0][0].elts) else []
        expressions = {t.id: v for t, v in pairs if isinstance(t, ast.Name)}
        for name in names:
            set_at[name] = code.co_firstlineno + node.lineno - 1
            value[name] = expressions.get(name)
    own = {n.id for n in ast.walk(loop.target) if isinstance(n, ast.Name)} if isinstance(loop, ast.For) else set()
    events = list(name_events(ast.Module(body=[*loop.body, *loop.orelse], type_ignores=[])))
    if isinstance(loop, ast.While):
        events = [*name_events(loop.test), *events]
    carrying = {name for name, what, _ in events if what != "read"}  # set or changed in the loop
    first = {}
    for name, what, line in events:
        first.setdefault(name, (what, line))
    carried = [  # a name the loop reads that main binds nowhere before it is a global's, or unbound
        Carried(name, code.co_firstlineno + line - 1, set_at[name], value[name])
        for name, (what, line) in first.items()
        if what != "set" and name in carrying and name in set_at and name not in restored | own | set(given)
    ]
    # a function main defines that rebinds one of main's names from its own value (nonlocal count; count += 1),
    # changes one in place (counts[0] += 1, history.append(x)), changes an attribute of one of its functions
    # (update.calls += 1) or its own default argument (def update(batch, n=[0]): n[0] += 1): a counter kept in update.
    # Not a name main's loop binds or empties itself (a list update appends to, emptied at each step)
    defined = {n.name: n for n in own_nodes(body) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    for function, shadowed in functions_of(body):
        for name, line, how, text in changed_by(function, set(defined)):
            if how == "global" or name in carrying:  # a module-level name's (rebound_globals), one the loop sets
                continue
            if how in ("attribute", "default") and name not in set_at:  # a function main defines, as run.start finds it
                if name not in defined:  # a function's own function: not main's
                    continue
                set_at[name] = code.co_firstlineno + defined[name].lineno - 1
                value[name] = None
            if name not in shadowed and name in set_at and name not in restored | own | set(given) | {c.name for c in carried}:
                line = code.co_firstlineno + line - 1
                carried.append(Carried(name, line, set_at[name], value[name], function.name, how, text))
    return carried


def bound_in(function) -> set:
    """The names `function` binds itself (its parameters, what it assigns), not those it declares nonlocal or global."""
    declared = {n for s in own_nodes(function) if isinstance(s, (ast.Nonlocal, ast.Global)) for n in s.names}
    params = {a.arg for a in [*function.args.posonlyargs, *function.args.args, *function.args.kwonlyargs]}
    params |= {a.arg for a in (function.args.vararg, function.args.kwarg) if a}
    stores = {n.id for n in own_nodes(function) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    stores |= {n.name for n in own_nodes(function) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}
    return (params | stores) - declared


MUTABLE_DEFAULTS = (ast.List, ast.Dict, ast.Set, ast.ListComp, ast.DictComp, ast.SetComp)


def changed_by(function, defined=frozenset()) -> list:
    """(name, line, how, text) for each name of an enclosing scope that `function` changes and that carries from one
    call to the next: one it rebinds from its own value (how: "nonlocal" or "global"; count += 1, not a stash: last =
    loss), changes in place ("in place": counts[0] += 1, history.append(x), stats["n"] = stats["n"] + 1; not after
    overwriting it whole in the same call: x.fill_(0), x.clear()), an attribute of a function in `defined` it changes
    from its value ("attribute": update.calls += 1), or its own mutable default argument changed in place ("default",
    under the function's name: def update(batch, n=[0]): n[0] += 1). `text` is the statement as written."""
    found, own = {}, bound_in(function)
    first = {}
    for name, what, _ in name_events(ast.Module(body=function.body, type_ignores=[])):
        first.setdefault(name, what)
    stored = {n.id for n in own_nodes(function) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    read = {n.id for n in own_nodes(function) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
    read |= {n.target.id for n in own_nodes(function) if isinstance(n, ast.AugAssign) and isinstance(n.target, ast.Name)}
    for statement in (n for n in own_nodes(function) if isinstance(n, (ast.Nonlocal, ast.Global))):
        for name in statement.names:
            if name in stored and name in read:  # count += 1, ema = d * ema + ...; a stash (last = loss) is overwritten
                how = "nonlocal" if isinstance(statement, ast.Nonlocal) else "global"
                found.setdefault(name, (name, statement.lineno, how, ast.unparse(statement)))
    defaults = [*function.args.defaults, *(d for d in function.args.kw_defaults if d is not None)]
    params = (
        [*function.args.posonlyargs, *function.args.args][-len(function.args.defaults) :] if function.args.defaults else []
    )
    params += [a for a, d in zip(function.args.kwonlyargs, function.args.kw_defaults) if d is not None]
    mutable = {a.arg for a, d in zip(params, defaults) if isinstance(d, MUTABLE_DEFAULTS)}
    reset = set()  # entries and attributes the call sets before it changes them (stats["n"] = 0, then += 1)
    for n in sorted(own_nodes(function), key=lambda n: (getattr(n, "lineno", 0), getattr(n, "col_offset", 0))):
        name, how = changed_in_place(n), "in place"
        whole = overwritten_whole(n) if isinstance(n, ast.Call) else None
        if whole and overwrites_from_itself(n, whole):
            name = whole  # ema.copy_(0.9 * ema + x): from its own value
        if isinstance(n, (ast.AugAssign, ast.Assign)):
            name, targets = None, n.targets if isinstance(n, ast.Assign) else [n.target]
            for target in (t for t in targets if isinstance(t, (ast.Subscript, ast.Attribute))):
                root, through_attribute = root_of(target)
                from_itself = isinstance(n, ast.AugAssign) or from_its_value(target, n.value)
                if not from_itself:
                    reset.add(ast.unparse(target))
                    continue
                if root is not None and ast.unparse(target) not in reset and (not through_attribute or root in defined):
                    name, how = root, "attribute" if through_attribute else "in place"
        if name is None or first.get(name) == "set":
            continue
        if name in mutable:
            found.setdefault(function.name, (function.name, n.lineno, "default", ast.unparse(n)))
        elif name not in own:
            found.setdefault(name, (name, n.lineno, how, ast.unparse(n)))
    return list(found.values())


def rebound_globals(code) -> list:
    """(name, function, line, how, text) for each module-level name a function of `code`'s script changes from call
    to call (changed_by: global count; count += 1, STATS["n"] += 1, counted.calls += 1, a default argument): state the
    script's module holds, which no checkpoint holds. [] if the source cannot be read."""
    linecache.checkcache(code.co_filename)
    try:
        tree = ast.parse("".join(linecache.getlines(code.co_filename)))
    except (SyntaxError, ValueError):
        return []
    module = {n.id for n in own_nodes(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    defined = {n.name for n in own_nodes(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    functions = (n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)))
    found = {}
    for function in functions:
        for name, line, how, text in changed_by(function, defined):
            if how == "global" or (how != "nonlocal" and name in module | defined):
                found.setdefault(name, (name, function.name, line, how, text))
    return list(found.values())


def after_end_step(code) -> "int | None":
    """The line of the first statement that a loop of `code` (main, or a script's module) runs after its
    run.end_step(...) in the same step, or None (the source unreadable, no such statement). A path that ends the step
    after end_step (continue, break, return, raise) runs nothing more in it, and a counter's increment (step += 1) is
    the loop's own; loops of functions defined inside `code` are theirs."""
    body = main_body(code)
    if body is None:
        return None
    ends = (ast.Continue, ast.Break, ast.Return, ast.Raise)

    def counter(statement) -> bool:  # step += 1, step += args.num_envs, left -= 1 (not a decay: noise *= 0.99, beta += 0.001)
        if not (isinstance(statement, ast.AugAssign) and isinstance(statement.target, ast.Name)):
            return False
        value = statement.value
        by = isinstance(value, (ast.Name, ast.Attribute)) or (isinstance(value, ast.Constant) and type(value.value) is int)
        return isinstance(statement.op, (ast.Add, ast.Sub)) and by

    def scan(statements, after: bool):
        """(the line of a statement run after end_step, or None; whether a path falls through with end_step run)."""
        for statement in statements:
            if isinstance(statement, ends):
                return None, False  # this path's step ends here
            if isinstance(statement, ast.Pass) or (after and counter(statement)):
                continue
            branches = None
            if isinstance(statement, ast.If):
                branches = [statement.body, statement.orelse]
            elif isinstance(statement, ast.Match):
                branches = [case.body for case in statement.cases] + [[]]
            if branches is not None and calls_end_step(statement):
                falls = False
                for branch in branches:
                    line, through = scan(branch, after)
                    if line:
                        return line, True
                    falls = falls or through
                after = falls
                continue
            if isinstance(statement, (ast.With, ast.AsyncWith)) and calls_end_step(statement):
                line, after = scan(statement.body, after)
                if line:
                    return line, True
                continue
            if isinstance(statement, ast.Try) and calls_end_step(statement):
                line, through = scan(statement.body + statement.orelse, after)
                for handler in statement.handlers:
                    line = line or scan(handler.body, after)[0]
                line = line or scan(statement.finalbody, after or through)[0]
                if line:
                    return line, True
                after = after or through
                continue
            if after:
                return statement.lineno, True
            if not isinstance(statement, (ast.For, ast.While, ast.AsyncFor)) and calls_end_step(statement):
                after = True  # run.end_step(step), or a value taken from it
        return None, after

    for loop in loops(body):
        line = scan(loop.body, False)[0]
        if line:
            return code.co_firstlineno + line - 1
    return None


# a part of the script's own class above this is not copied to check its state_dict() (check_parts_whole)
PART_CHECK_BYTES = 64 * 2**20
NUMBERS = (np.ndarray, np.generic, torch.Tensor, int, float)


def first_difference(a, b, module: str, skip: set, depth: int = 0) -> "str | None":
    """Where a part (`a`) and the copy its state_dict() restores (`b`) first differ in their numbers, arrays and
    tensors (`.obs_rms.var`), following the script's own classes' attributes, lists, tuples and dicts three levels
    down; None if nowhere. Left alone: what `skip` holds by id (the flags, the networks, optimizers and parts a
    checkpoint holds anyway), networks, and a field the copy holds as None (a cache load_state_dict resets)."""
    if id(a) in skip or isinstance(a, (torch.nn.Module, torch.optim.Optimizer)) or b is None:
        return None
    if isinstance(a, NUMBERS) and not isinstance(a, bool):
        if not isinstance(b, NUMBERS):
            return ""
        try:  # as float64 tensors (a bfloat16 tensor has no NumPy form); NaN equal to NaN
            x, y = (torch.as_tensor(v.detach().cpu() if isinstance(v, torch.Tensor) else np.asarray(v)) for v in (a, b))
            x, y = x.double(), y.double()
        except (TypeError, RuntimeError):  # not numbers after all (an array of objects): not compared
            return None
        same = x.shape == y.shape and bool(((x == y) | (x.isnan() & y.isnan())).all())
        return None if same else ""
    if depth == 3:
        return None
    if isinstance(a, (list, tuple)):
        items = [(f"[{i}]", v, b[i] if isinstance(b, (list, tuple)) and i < len(b) else None) for i, v in enumerate(a)]
    elif isinstance(a, dict):
        items = [(f"[{k!r}]", v, b.get(k) if isinstance(b, dict) else None) for k, v in a.items()]
    elif type(a).__module__ == module and hasattr(a, "__dict__") and not isinstance(a, type):
        items = [(f".{k}", v, getattr(b, k, None)) for k, v in vars(a).items()]
    else:
        return None
    for label, x, y in items:
        found = first_difference(x, y, module, skip, depth + 1)
        if found is not None:
            return label + found
    return None


def size_of(x, depth: int = 0) -> int:
    """The bytes of the arrays and tensors an object holds, three levels down (its attributes, lists and dicts)."""
    if isinstance(x, torch.Tensor):
        return x.numel() * x.element_size()
    if isinstance(x, np.ndarray):
        return x.nbytes
    if depth == 3 or isinstance(x, (str, bytes, type, torch.nn.Module)):
        return 0
    values = (
        x.values()
        if isinstance(x, dict)
        else x
        if isinstance(x, (list, tuple))
        else vars(x).values()
        if hasattr(x, "__dict__")
        else ()
    )
    return sum(size_of(v, depth + 1) for v in values)


def part_state(part):
    """A part's state as a checkpoint takes it: the tensor, or its state_dict() (not a ReplayBuffer's, which copies
    every row, nor one above PART_CHECK_BYTES); None where not taken here."""
    if isinstance(part, torch.Tensor):
        return part
    if isinstance(part, ReplayBuffer) or not callable(getattr(part, "state_dict", None)) or size_of(part) > PART_CHECK_BYTES:
        return None
    try:
        return part.state_dict()
    except Exception:  # a state_dict() that needs what the run has not made yet: met at the checkpoint
        return None


def part_state_tensors(part) -> list:
    return [v for v in torch.utils._pytree.tree_leaves(part_state(part)) if isinstance(v, (torch.Tensor, np.ndarray))]


def recomputed(module) -> set:
    """The attributes a layer's forward pre-hook computes anew from its parameters (torch.nn.utils.weight_norm's and
    spectral_norm's `weight`): a cache, not state."""
    return {hook.name for hook in module._forward_pre_hooks.values() if isinstance(hook, (WeightNorm, SpectralNorm))}


def fingerprint(value):
    """(where it is, what it holds) of an array or tensor: its storage's address (a tensor's; an array's id) and a digest
    of its shape, dtype and bytes; None for an array of Python objects or a tensor without plain storage."""
    try:
        if isinstance(value, (np.ndarray, np.generic)):  # a NumPy number (np.float64) too: a 0-d array's update
            if value.dtype == object:
                return None
            data, where = np.ascontiguousarray(value), id(value)
        else:
            where = value.untyped_storage().data_ptr()
            data = value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy()
    except (RuntimeError, TypeError, NotImplementedError):  # a sparse or meta tensor: not followed
        return None
    digest = hashlib.blake2b(data.tobytes(), digest_size=16).hexdigest()
    return where, tuple(value.shape), str(value.dtype), digest


def change_phrase(function: str, how: str, whose: str, text: str, line: str) -> str:
    """How `function` changes a name it carries (changed_by's how), as an error says it: "`update` rebinds main's
    `count` (nonlocal, x.py:9)", "`update` changes main's `counts` in place (`counts[0] += 1`, x.py:9)"."""
    if how in ("nonlocal", "global"):
        return f"`{function}` rebinds {whose} ({how}, {line})"
    if how == "in place":
        return f"`{function}` changes {whose} in place (`{text}`, {line})"
    if how == "attribute":
        return f"`{function}` changes an attribute of {whose} (`{text}`, {line})"
    if how == "default":
        return f"`{function}` changes its own default argument in place (`{text}`, {line})"
    raise ValueError(f"change_phrase: no phrase for {how!r}")


CARRIED_FIX = (
    "keep it where a checkpoint holds it: compute it from global_step (a schedule: 0.1 * 0.99 ** global_step), keep it in "
    "a flag (args.exploration_noise *= 0.999, which --resume restores), or in a tensor given to run.start's parts and "
    "changed in place (noise.mul_(0.999), a row per seed)"
)


def carried_state(x, depth: int = 0):
    """What --resume would have to bring back of a value main's loop carries, to compare: a number's or string's repr
    (NaN equals NaN), an array's or tensor's shape, dtype and bytes, the items of a list, tuple, deque, dict or set
    (three levels down, the first 1,000), another object's identity."""
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
        return repr(x)
    if isinstance(x, (np.ndarray, np.generic, torch.Tensor)):
        seen = fingerprint(x)
        return seen[1:] if seen else ("object", id(x))
    if isinstance(x, types.FunctionType):  # its attributes (update.calls) and default arguments (n=[0])
        return "function", id(x), carried_state([dict(vars(x)), x.__defaults__, x.__kwdefaults__], depth)
    if depth < 3 and isinstance(x, (list, tuple, collections.deque)):
        return type(x).__name__, len(x), tuple(carried_state(v, depth + 1) for v in itertools.islice(x, 1000))
    if depth < 3 and isinstance(x, dict):
        items = itertools.islice(x.items(), 1000)
        return "dict", len(x), tuple((repr(k), carried_state(v, depth + 1)) for k, v in items)
    if depth < 3 and isinstance(x, (set, frozenset)):
        return "set", len(x), frozenset(repr(v) for v in itertools.islice(x, 1000))
    return "object", id(x)


class Run:
    """The machinery around a script's loop, in the order the loop meets it:

    run = Run(args)                        # run folders; with --resume, the checkpoints to continue from
    obs = run.start(envs, device, nets, optimizers, buffer=rb)   # restored on --resume (else None); opens the logs
    run.evaluate(step, returns)            # a deterministic evaluation: recorded, logged, printed (run.logs)
    run.log(logs, step); run.log_episodes(infos, step)
    with run.stop_on_nan(step): ...        # a non-finite loss ends the run, its last finite state saved
    run.end_step(step)                     # speed, progress bar, a checkpoint when one is due
    return run.finish(save={"actor": actor}, eval_envs=eval_envs, policy=policy)   # --save-model; the envs closed

    What a checkpoint holds is the objects `start` was given: a network or optimizer that main binds anew afterwards
    (a reset by assignment) would not be in it, nor in a --cudagraphs update recorded before; end_step stops such a run
    at the step it happens, saying how to reset in place instead.
    """

    def __init__(self, args):
        self.args, self.script = args, script_of(type(args))
        # the flags as main got them: what --resume parses again, so that what main makes of them before run.start
        # (args.exploration_noise *= max_action) is made once; run.start then restores any flag main changed since
        self.args_given = copy.deepcopy(vars(args))  # a list flag main changes in place is not changed here
        self.seeds = list(range(args.seed, args.seed + getattr(args, "num_seeds", 1)))  # trained side by side
        self.checkpoints = ckpt.load_checkpoints(args.resume, self.script) if args.resume else None  # one per seed
        self.run_dirs = self.folders()
        self.first_step = self.checkpoints[0]["global_step"] if self.checkpoints else 0
        self.generators_at_start = None  # run.start's record of the global generators, for start_step's check
        self.last_logged = -1  # the furthest step run.log has logged at (check_logged_steps)
        self.eval_returns = [c["eval_returns"] for c in self.checkpoints] if self.checkpoints else [[] for _ in self.seeds]
        self.finished = self.first_step >= args.total_timesteps
        if self.finished:
            print(f"{', '.join(self.run_dirs)} had already finished its {args.total_timesteps} steps")
        self.guarded = 0  # how many run.stop_on_nan blocks are open
        self.own_state = {}  # check_own_state_unchanged's record of the script's own objects: id -> (object, values)
        self.evaluation_due = None  # on --resume, the step whose evaluation the first step must make (start)
        self.video_folders = [f"videos/{os.path.basename(d)}" if args.capture_video else None for d in self.run_dirs]
        if not args.capture_video:  # nothing renders: spare dm_control its probe for a display (and its warning)
            os.environ.setdefault("MUJOCO_GL", "disable")

    def folders(self) -> list:
        """Each seed's run folder: --resume's and those of the seeds that trained beside it, or runs/ + --run-name
        ({seed} replaced by each seed's number), by default {env_id}__{exp_name}__{seed}__{unix time}."""
        args = self.args
        if self.checkpoints:
            parent = os.path.dirname(os.path.normpath(args.resume))
            return [os.path.join(parent, name) for name in self.checkpoints[0]["run_names"]]
        template = args.run_name or f"{args.env_id.replace('/', '-')}__{args.exp_name}__{{seed}}__{int(time.time())}"
        return [os.path.join("runs", template.replace("{seed}", str(seed))) for seed in self.seeds]

    def start(self, envs, device: torch.device, nets: dict, optimizers: dict, **parts):
        """Names what a checkpoint holds (with the envs and the random generators): the networks, the optimizers and
        `parts` (the replay buffer, tensors such as SAC's log_alpha, objects with a state_dict(), random generators of
        the script's own); restores them on --resume; opens the logs. Returns the observations a resumed run acts on
        next (for SeedEnvs [num_seeds, obs_dim]; for one plain env, its observation or None where an episode starts),
        and None for a fresh run."""
        for name, part in parts.items():
            if name in ckpt.OWN_KEYS:
                fail(
                    f"run.start's part `{name}`: a checkpoint keeps its own `{name}` under that name, which would replace "
                    f"it; give the part another name (run.start(..., my_{name}=...))"
                )
            if not isinstance(part, (torch.Tensor, *ckpt.GENERATORS)) and not hasattr(part, "load_state_dict"):
                fail(
                    f"run.start's part `{name}` is a {type(part).__name__}, which --resume cannot restore in place (main "
                    "would go on with the object it made, not the checkpoint's): hold it in a tensor changed in place "
                    f"({name} = torch.tensor(...), then {name}.copy_(...) or {name}.mul_(...)), or in an object with "
                    "state_dict() and load_state_dict()"
                )
        self.envs, self.nets, self.optimizers, self.parts = envs, nets, optimizers, parts
        self.env_list = list(envs) if isinstance(envs, SeedEnvs) else [envs]
        for k, wrapper in self.wrapped_envs() if self.args.checkpoint_frequency or self.checkpoints else []:
            if wrapper:
                fail(
                    f"run.start's env {k} is a {wrapper}, not the env make_env made (or one it wraps): a "
                    "checkpoint saves an env, and --resume rebuilds it, through make_env's own wrapper (EpisodeRecord), "
                    "which would leave this wrapper's state out and give the loop observations it has not seen; do in the "
                    "script what the wrapper does (as the scripts normalise observations), or run without "
                    "--checkpoint-frequency"
                )
        # the names main binds these networks, optimizers and parts to, which end_step watches; one it holds but did
        # not give (by a name, or in a list or dict) would be left out of the checkpoints, and start again from its
        # initial state on --resume
        self.caller = sys._getframe(1)
        watched = {id(x): x for x in [*nets.values(), *optimizers.values(), *parts.values()]}
        self.bound = {name: x for name, x in self.caller.f_locals.items() if id(x) in watched and x is watched[id(x)]}
        self.watched = set(watched)  # by id: what run.start was given, which the checkpoints hold
        self.check_nets_held(starting=True)
        self.net_attributes = {}  # check_nets_attributes' record: (net, layer, id) -> its plain tensor attributes
        script = self.caller.f_globals
        for name, x in held({k: v for k, v in script.items() if not k.startswith("__")}):
            if (isinstance(x, torch.nn.Module) and x.state_dict()) or isinstance(x, torch.optim.Optimizer):
                fail(
                    f"`{name}`, a {'network' if isinstance(x, torch.nn.Module) else 'optimizer'} of the script's module "
                    "(built as the script is imported), starts from weights drawn before main seeds torch's generator, "
                    "another draw in every process, and a checkpoint would not hold it: build it in main after the "
                    "seeding and add it to run.start's nets (its optimizer to the optimizers)"
                )
        self.check_optimizers_held(nets, optimizers, parts, watched)
        line = after_end_step(self.caller.f_code) if self.args.checkpoint_frequency else None
        if line:
            fail(
                f"main's loop runs code after run.end_step ({self.main_line(line)}), which "
                "writes the checkpoints: a run resumed from one would never run that code for the step it was written at "
                "(a reset, a decay, a target copy, an evaluation); end the loop's body with run.end_step(global_step), as "
                "the scripts do"
            )
        # what main's loop carries from step to step outside the checkpoints, as it is before the loop: compared at
        # each checkpoint (check_carried), where a change would be lost on --resume
        self.carried = {}
        found = carried_locals(self.caller.f_code, set(self.bound)) if self.args.checkpoint_frequency else []
        held_storage = self.held_tensors() if found else set()
        for carried in found:
            if carried.set_at < self.caller.f_lineno:  # bound before run.start: as it is now (if bound: a flag's if)
                value = self.caller.f_locals.get(carried.name, NOT_A_VALUE)
                if value is NOT_A_VALUE:
                    continue
            else:
                value = value_before_loop(carried.value, self.caller)  # bound after it: 0.0, np.zeros(len(run.seeds))
            if isinstance(value, torch.Tensor) and value.untyped_storage().data_ptr() in held_storage:
                continue  # another name of a tensor the checkpoints hold (w = actor.fc.weight, decayed in place)
            if value is NOT_A_VALUE:
                fail(
                    f"{self.carried_line(carried)}, and no checkpoint holds it: --resume would start it again from its "
                    f"value before the loop ({self.main_line(carried.set_at)}); " + CARRIED_FIX
                )
            self.carried[carried.name] = (carried, carried_state(value))
        # module-level names a function of the script rebinds (global count): compared at each checkpoint too
        rebound = rebound_globals(self.caller.f_code) if self.args.checkpoint_frequency else []
        held_storage = self.held_tensors() if rebound else set()
        self.carried_globals = {}
        for name, *where in rebound:
            x = script.get(name)
            if id(x) in self.watched or (isinstance(x, torch.Tensor) and x.untyped_storage().data_ptr() in held_storage):
                continue  # a part given to run.start (a script without main), another name of a held tensor
            self.carried_globals[name] = (*where, carried_state(x))
        self.check_stacked_for_the_seeds()
        if len(self.seeds) > 1:  # a tensor part (log_alpha) one per seed, with or without checkpoints
            states = {name: part_state(p) for name, p in parts.items()}
            check_parts_per_seed({name: state for name, state in states.items() if state is not None}, len(self.seeds))
        watch_steps(optimizers, len(self.seeds))  # with several seeds: each step's gradients from a loss optimize took
        self.check_one_learning_rate_follows_one_seed()  # before check_state_held, which would ask to checkpoint it
        self.check_state_held()
        # each part of the script's own class as it starts (before a restore): what check_parts_whole loads its
        # state_dict() into, to see that the state_dict holds all that changed
        own = self.caller.f_globals.get("__name__")
        self.part_templates = {}
        for name, part in parts.items() if self.args.checkpoint_frequency else ():
            if type(part).__module__ != own or isinstance(part, ReplayBuffer) or size_of(part) > PART_CHECK_BYTES:
                continue  # a replay buffer, or a part as large (a fork's own buffer), is not copied to be checked
            try:
                self.part_templates[name] = copy.deepcopy(part)
            except Exception as error:  # a part that cannot be copied (it holds a lock, a file)
                print(
                    f"warning: run.start's part `{name}` cannot be copied ({error}): whether its state_dict() holds all "
                    "its state is not checked",
                    file=sys.stderr,
                )
        self.evaluation_due = self.next_evaluation() if self.checkpoints else None
        observations = None
        if self.checkpoints:
            observations = ckpt.restore(join_seeds(self.checkpoints, parts), self.env_list, nets, optimizers, parts)
            self.restore_changed_flags()
        self.check_nets_attributes()  # the networks' plain tensor attributes as the loop starts with them
        self.logs = Logs(self.args, self.run_dirs, self.seeds, self.first_step, self.eval_returns, device, self.args_given)
        self.next_checkpoint = self.first_step + self.args.checkpoint_frequency
        self.args_at_start, self.args_set_in_main = set(vars(self.args)), None
        self.args_counted = args_counted(self.caller.f_code, {k for k, v in self.caller.f_locals.items() if v is self.args})
        if self.checkpoints or (self.args.checkpoint_frequency and not fresh_run_only(self.caller)):
            self.generators_at_start = global_generators()
        if isinstance(envs, SeedEnvs):
            return np.stack(observations) if observations else None
        return observations[0] if observations else None

    @property
    def start_step(self) -> int:
        """The step main's loop begins at: 0, or the checkpoint's (for global_step in range(run.start_step, ...)). Read
        as the loop begins, after run.start, it checks that nothing drew from the global random generators since."""
        if self.generators_at_start is not None:
            before, self.generators_at_start = self.generators_at_start, None
            drawn = [name for name, state in global_generators().items() if name in before and state != before[name]]
            if drawn:
                fail(
                    f"main drew from {' and '.join(drawn)} random generator{'s' if len(drawn) > 1 else ''} between "
                    "run.start and its loop (a random "
                    "prior, a fresh network built there): a run resumed from a checkpoint would draw it from the "
                    "checkpoint's generator, not as the run began; draw it before run.start (and give a tensor that must "
                    "stay to run.start's parts, a network to its nets), or in the loop"
                )
        return self.first_step

    def wrapped_envs(self) -> list:
        """(k, the class name of a wrapper around make_env's env, or None) for each env given to run.start: a checkpoint
        saves and rebuilds an env through make_env's EpisodeRecord, which a wrapper of the fork's own hides."""
        return [
            (k, None if isinstance(env, ckpt.EpisodeRecord) else type(env).__name__) for k, env in enumerate(self.env_list)
        ]

    def check_nets_held(self, starting: bool):
        """Every network and optimizer main holds is one run.start was given (self.watched, by id): by a name, in a list or
        dict, or through a function or object main holds (enclosed: a closure, a partial's arguments, a helper object's
        attributes); else a checkpoint would not
        hold it, and --resume would start it from its initial state. At run.start; at each checkpoint, the optimizers
        and what main's functions hold (a network main binds after run.start may be a copy loaded into one given: a
        reset's `fresh`)."""
        # a layer of a network given is held, and a network given compiled (torch.compile) is its own network too
        modules = {id(m) for net in self.nets.values() for m in [net, *ckpt.uncompiled(net).modules()]}

        def left_out(x) -> bool:  # a loss module (nn.MSELoss()) has no state; torch.compile(actor) is the actor given
            if isinstance(x, torch.nn.Module):
                return id(ckpt.uncompiled(x)) not in modules and bool(x.state_dict())
            return isinstance(x, torch.optim.Optimizer) and id(x) not in self.watched and (starting or bool(x.state))

        by_name = list(held(self.caller.f_locals))
        for name, x in by_name:
            if left_out(x) and (starting or isinstance(x, torch.optim.Optimizer)):
                kind = "nets" if isinstance(x, torch.nn.Module) else "optimizers"
                fail(
                    f"`{name}` is not in run.start's {kind}: a checkpoint would not hold it; add it there"
                    + ("" if name.isidentifier() else f" (each under a name of its own: '{part_name(name)}': {name})")
                )
        named = {id(x) for _, x in by_name}  # a network main itself names: the rule above
        parts = {id(part) for part in self.parts.values()}
        for name, x in enclosed(self.caller.f_locals, self.caller.f_globals.get("__name__"), parts):
            if left_out(x) and (starting or isinstance(x, torch.optim.Optimizer) or id(x) not in named):
                what, kind = ("network", "nets") if isinstance(x, torch.nn.Module) else ("optimizer", "optimizers")
                fail(
                    f"{name} is a {what} that run.start's {kind} do not hold: a checkpoint would not hold it, and "
                    f"--resume would start it from its initial state; build it in main and add it there"
                )

    def check_optimizers_held(self, nets: dict, optimizers: dict, parts: dict, watched: dict):
        """Every tensor an optimizer given trains is a checkpoint's too (a parameter of a network given, a tensor part
        such as SAC's log_alpha, a tensor in a part's state_dict()): else --resume would restore the optimizer's state
        and start the tensor from its initial value. And an optimizer a network holds as an attribute
        (`qf.optimizer = ...`) is among the optimizers given."""

        def storage(tensors) -> set:
            return {t.untyped_storage().data_ptr() for t in tensors if isinstance(t, torch.Tensor) and t.numel()}

        def tensors_in(state) -> list:  # a state_dict()'s tensors, in nested dicts, lists and tuples too
            if isinstance(state, torch.Tensor):
                return [state]
            values = state.values() if isinstance(state, dict) else state if isinstance(state, (list, tuple)) else []
            return [t for v in values for t in tensors_in(v)]

        trained = [p for optimizer in optimizers.values() for group in optimizer.param_groups for p in group["params"]]
        held_storage = storage([*(t for net in nets.values() for t in [*net.parameters(), *net.buffers()]), *parts.values()])
        in_states = []  # the tensors of the parts' state_dict()s (not the replay buffer's: a copy of its rows)
        if not storage(trained) <= held_storage:
            for part in parts.values():
                if callable(getattr(part, "state_dict", None)) and not isinstance(part, ReplayBuffer):
                    in_states += tensors_in(part.state_dict())

        held_storage |= storage(in_states)

        def is_held(p) -> bool:  # its storage, or in a part's state_dict(), itself or a copy (its shape and values)
            copies = (t for t in in_states if t.shape == p.shape and t.device == p.device)
            return p.untyped_storage().data_ptr() in held_storage or any(torch.equal(t.detach(), p.detach()) for t in copies)

        names = {id(x): name for name, x in held(self.caller.f_locals)}
        for label, optimizer in optimizers.items():
            for p in (p for group in optimizer.param_groups for p in group["params"]):
                if p.numel() and not is_held(p):
                    name = names.get(id(p))
                    fail(
                        f"`{label}` trains a tensor{f' (`{name}`)' if name else ''} that is in no network or part given to "
                        "run.start: a checkpoint would hold the optimizer's state but not the tensor, and --resume would "
                        "start it from its initial value; add it to run.start's parts"
                        + (f" (run.start(..., {part_name(name)}={name}))" if name else "")
                    )
        for net_name, net in nets.items():
            for module_name, module in net.named_modules():
                for key, x in vars(module).items():
                    if isinstance(x, torch.optim.Optimizer) and id(x) not in watched:
                        path = [f"[{k}]" if k.isdigit() else f".{k}" for k in filter(None, module_name.split("."))]
                        label = net_name + "".join(path) + f".{key}"  # qf[1].optimizer
                        fail(
                            f"`{label}`, an optimizer a network holds, is not in run.start's optimizers: a checkpoint would "
                            f"not hold its state, and --resume would start it again; add it there ('{part_name(label)}': "
                            f"{label})"
                        )

    def restore_changed_flags(self):
        """On --resume, every flag as it was at the checkpoint (but those a resume may change): --resume parsed them as
        main got them, main has redone what it does before run.start, and a flag it changed during the run (a decay:
        args.exploration_noise *= 0.99 a step) takes its checkpoint's value again."""
        for name, value in self.checkpoints[0]["args"].items():
            if name not in RESUMABLE_FLAGS:
                setattr(self.args, name, value)

    def evaluate(self, step: int, returns: np.ndarray):
        self.logs.evaluate(step, returns)

    def next_evaluation(self):
        """The step a resumed run evaluates first if its record's evaluations, two or more evenly spaced, put one at the
        step it resumes at; else None."""
        steps = [step for step, _ in self.eval_returns[0]]
        gaps = {b - a for a, b in zip(steps, steps[1:])}
        if len(gaps) == 1 and steps[-1] + gaps.pop() == self.first_step < self.args.total_timesteps:
            return self.first_step
        return None

    def log(self, logs: dict, step: int):
        self.last_logged = max(self.last_logged, int(step))
        try:
            self.logs.log(logs, step)
        except NonFiniteError as error:
            if self.guarded:  # stop_on_nan ends the run, saving its last finite state
                raise
            raise refusal(
                FloatingPointError,
                f"run.log: `{error.tag}` is not finite at step {step} (logged outside run.stop_on_nan, which would end "
                "the run saving its last finite state): a logged value must be finite; a loss goes through optimize's "
                "NaN check, a statistic may be undefined (a std of one value)",
            ) from None

    def check_stacked_for_the_seeds(self):
        """With several seeds, every network given is stack_seeds': one built in plain PyTorch (`Net().to(device)`) is
        one network for all the seeds, which would train on every seed's data, and a checkpoint would cut its weights
        as if they were stacked."""
        n = len(self.seeds)
        for name, net in self.nets.items() if n > 1 else ():
            loose = next((p for p in net.parameters() if getattr(p, "num_seeds", 1) != n), None)
            if loose is not None:
                fail(
                    f"`{name}` ({type(net).__name__}) is not stacked for the {n} seeds (a parameter {list(loose.shape)}): "
                    "one network would train on every seed's data; build it with stack_seeds, in networks() or a call "
                    "of its own, which gives each seed its own weights"
                )

    def log_episodes(self, infos, step: int):
        self.logs.log_episodes(infos, step)

    def check_one_learning_rate_follows_one_seed(self):
        """With several seeds, one optimizer steps every seed's weights, at one learning rate: a schedule of the step
        count is each seed's own, but a ReduceLROnPlateau follows one number, one seed's loss or all of theirs."""
        if len(self.seeds) == 1:
            return
        for name, x in [*held(self.caller.f_locals), *self.parts.items()]:
            if isinstance(x, lr_scheduler.ReduceLROnPlateau):
                fail(
                    f"`{name}` (ReduceLROnPlateau) follows one number, and its optimizer steps every seed's weights: with "
                    f"{len(self.seeds)} seeds it would set one learning rate for all of them; train one seed per process "
                    "(--num-seeds 1)"
                )
            if isinstance(x, torch.amp.GradScaler) and x.is_enabled():
                fail(
                    f"`{name}` (GradScaler) keeps one loss scale for every seed, and skips every seed's step when one "
                    f"seed's gradients overflow: with {len(self.seeds)} seeds one seed would stop the others; train one "
                    "seed per process (--num-seeds 1), or in bfloat16 (--bf16), which needs no scaler"
                )

    def check_state_held(self):
        """Every object main holds that has a state (a state_dict() and a load_state_dict(): a learning-rate
        scheduler, a running normaliser, a GradScaler; a random generator of its own) is checkpointed, among
        run.start's parts: else a resumed run would start it from its initial state, silently. Found among main's
        names, and a learning-rate scheduler also by the optimizer step it wraps (one made in a helper). Looked at
        where checkpoints are written."""
        if not self.args.checkpoint_frequency:
            return
        # a scheduler made of others (SequentialLR, ChainedScheduler) holds theirs in its state_dict
        parts = [*self.parts.values(), *(s for part in self.parts.values() for s in getattr(part, "_schedulers", []))]
        held_parts = {id(part) for part in parts}
        held_optimizers = {id(getattr(part, "optimizer", None)) for part in parts}
        for name, x in held(self.caller.f_locals):
            if id(x) in held_parts or isinstance(x, (type, torch.nn.Module, torch.optim.Optimizer)):  # a class: no state
                continue
            if isinstance(x, (lr_scheduler.LRScheduler, lr_scheduler.ReduceLROnPlateau)):
                fail(
                    f"`{name}`, a learning-rate scheduler, is not in run.start's parts: a checkpoint would not hold where "
                    "its schedule is, and --resume would start it again; add it there "
                    f"(run.start(..., {part_name(name)}={name}))"
                )
            if own_generator(x):
                fail(
                    f"`{name}` ({type(x).__name__}), a random generator of the script's own, is not in run.start's parts: a "
                    f"checkpoint would not hold it, and --resume would start it again; add it there (run.start(..., "
                    f"{part_name(name)}={name})), or draw from torch's generator, which checkpoints hold"
                )
            if callable(getattr(x, "state_dict", None)) and callable(getattr(x, "load_state_dict", None)):
                fail(
                    f"`{name}` ({type(x).__name__}) has a state_dict() but is not in run.start's parts: a checkpoint would "
                    f"not hold it, and --resume would start it from its initial state; add it there "
                    f"(run.start(..., {part_name(name)}={name}))"
                )
        own = self.caller.f_globals.get("__name__")  # the script's own classes: a helper object (an OU noise)
        held_tensors = None  # what the checkpoints hold, looked up once, at the first object of the script's own
        for name, x in held(self.caller.f_locals):
            if type(x).__module__ != own or id(x) in held_parts or isinstance(x, (type, torch.nn.Module, type(self.args))):
                continue
            attributes = getattr(x, "__dict__", None)
            held_tensors = self.held_tensors() if held_tensors is None else held_tensors
            self.check_own_state_unchanged(name, x, attributes if isinstance(attributes, dict) else {}, held_tensors)
            for label, value in held(
                {f"{name}.{k}": v for k, v in attributes.items()} if isinstance(attributes, dict) else {}, 1
            ):
                if own_generator(value) and id(value) not in held_parts:  # noise.rng, or noise.rngs[0]
                    fail(
                        f"`{label}` ({type(value).__name__}), a random generator of the script's own, is not in run.start's "
                        "parts: a checkpoint would not hold it, and --resume would start it again; add it there "
                        f"(run.start(..., {part_name(label)}={label})), or draw from torch's generator, which checkpoints hold"
                    )
        for name, x in enclosed(self.caller.f_locals, own, held_parts):  # a helper's scheduler a function closes over
            if id(x) in held_parts or isinstance(x, (type, torch.nn.Module, torch.optim.Optimizer)):
                continue
            stateful = callable(getattr(x, "state_dict", None)) and callable(getattr(x, "load_state_dict", None))
            if stateful or own_generator(x) or isinstance(x, lr_scheduler.ReduceLROnPlateau):
                fail(
                    f"{name} ({type(x).__name__}) has a state that run.start's parts do not hold: a checkpoint would not "
                    "hold it, and --resume would start it from its initial state; hold it in main and add it there "
                    "(run.start(..., name=it))"
                )
        for name, optimizer in self.optimizers.items():
            if hasattr(optimizer.step, "_wrapped_by_lr_sched") and id(optimizer) not in held_optimizers:
                fail(
                    f"`{name}` has a learning-rate scheduler that run.start's parts do not hold: a checkpoint would not "
                    "hold where its schedule is, and --resume would start it again; add the scheduler there "
                    "(run.start(..., scheduler=scheduler))"
                )

    def check_own_state_unchanged(self, name: str, x, attributes: dict, held: set):
        """An object of the script's own class that main holds outside run.start's parts (CleanRL's RunningMeanStd,
        an OU noise's x_prev) keeps its arrays and tensors where no checkpoint holds them: once one of them changes
        (between run.start, or the checkpoint that first met the object, and a later checkpoint), --resume would start
        it from its initial state. NumPy numbers count (a 0-d array's update gives one); Python numbers are left alone
        (a stopwatch's seconds), and so is a tensor a checkpoint holds (a part, a network's parameter, an optimizer's
        state, or a view of one: `held`, held_tensors())."""
        try:
            ref = weakref.ref(x)
        except TypeError:  # an object without a weak reference (__slots__): not followed
            return
        now = {k: fingerprint(v) for k, v in attributes.items() if isinstance(v, (np.ndarray, np.generic, torch.Tensor))}
        now = {k: v for k, v in now.items() if v is not None and v[0] not in held}
        self.own_state = {key: seen for key, seen in self.own_state.items() if seen[0]() is not None}
        seen = self.own_state.setdefault(id(x), (ref, now))
        if seen[0]() is not x:  # another object at a freed object's id
            self.own_state[id(x)] = seen = (ref, now)
        changed = [k for k, v in seen[1].items() if k in now and now[k][1:] != v[1:]]
        if changed:
            fail(
                f"`{name}` ({type(x).__name__}), an object of the script's own class, changed since run.start or the "
                f"checkpoint that first met it (`{name}.{changed[0]}`), and it is not in run.start's parts: a checkpoint "
                "would not hold it, and --resume would start it from its initial state; give its class state_dict() and "
                f"load_state_dict() (its arrays as tensors) and add it there (run.start(..., {part_name(name)}={name})), or "
                "keep that state in a tensor given to run.start"
            )

    def main_line(self, line: int) -> str:
        """file:line of a line of main's script."""
        return f"{os.path.basename(self.caller.f_code.co_filename)}:{line}"

    def carried_line(self, carried) -> str:
        if carried.via:
            return (
                change_phrase(carried.via, carried.how, f"main's `{carried.name}`", carried.text, self.main_line(carried.line))
                + ", which main's loop carries from one step to the next"
            )
        return f"main's loop carries `{carried.name}` from one step to the next ({self.main_line(carried.line)})"

    def check_carried(self, step: int):
        """Each plain local main's loop carries from step to step (run.start's carried_locals) is at a checkpoint what
        it was before the loop (a per-episode sum reset as the episode ends, a flag): else --resume, which starts it
        again from that value, would go on with another."""
        for carried, before in self.carried.values():
            if carried_state(self.caller.f_locals.get(carried.name)) != before:
                fail(
                    f"{self.carried_line(carried)}, and by step {step} it is no longer what it was before the loop: no "
                    "checkpoint holds it, so --resume would start it again from that value; " + CARRIED_FIX
                )
        for name, (function, line, how, text, before) in self.carried_globals.items():
            if carried_state(self.caller.f_globals.get(name)) != before:
                whose = f"the script's module-level `{name}`"
                fail(
                    change_phrase(function, how, whose, text, self.main_line(line)) + f", and by step {step} it is no longer "
                    "what it was at run.start: no checkpoint holds it, so --resume would start it again from that value; "
                    + CARRIED_FIX
                )

    def held_tensors(self) -> set:
        """Where the checkpoints' tensors and arrays are: the parts (and their attributes), the networks' parameters and
        buffers, the optimizers' states; by object and by a tensor's storage."""
        held = set()

        def add(v):
            held.add(id(v))
            if isinstance(v, torch.Tensor):
                held.add(v.untyped_storage().data_ptr())

        for part in self.parts.values():
            add(part)
            for v in getattr(part, "__dict__", {}).values():
                add(v)
            for v in part_state_tensors(part):  # what its state_dict() holds, however deep in the part it lies
                add(v)
        for net in self.nets.values():
            for v in [*net.parameters(), *net.buffers()]:
                add(v)
        for optimizer in self.optimizers.values():
            for state in optimizer.state.values():
                for v in state.values():
                    add(v)
        return held

    def check_parts_whole(self):
        """Each part of the script's own class (a normaliser, a rollout) comes back whole from its state_dict(): loaded
        into a copy of the part as it started, it equals the part now. A field a fork adds to the class but not to its
        state_dict() (a reward normaliser's statistics) would start again on --resume, silently."""
        held = {id(x) for x in [self.args, *self.nets.values(), *self.optimizers.values(), *self.parts.values()]}
        for name, template in self.part_templates.items():
            part = self.parts[name]
            restored = copy.deepcopy(template)
            restored.load_state_dict(copy.deepcopy(part.state_dict()))  # what a resumed run's part would hold
            differs = first_difference(part, restored, type(part).__module__, held - {id(part)})
            if differs is not None:
                fail(
                    f"run.start's part `{name}` ({type(part).__name__}) does not come back whole from its state_dict(): "
                    f"`{name}{differs}` is not what load_state_dict() restores from it (left out, or restored otherwise), "
                    "and --resume would start it from its initial state; add it to the class's state_dict() and "
                    "load_state_dict() (a cache recomputed from the state: set it to None in load_state_dict())"
                )

    def check_nets_attributes(self):
        """A tensor or array a network given to run.start (or one of its layers) holds as a plain attribute, not as a
        parameter or buffer (self.value_scale = torch.ones(())), or as a buffer registered with persistent=False, is not
        in its state_dict(): once it changes (between run.start and a checkpoint), --resume would start it from its
        initial value. Recorded at run.start."""
        held = self.held_tensors()
        for name, net in self.nets.items():
            for path, module in ckpt.uncompiled(net).named_modules():
                attributes = {
                    k: fingerprint(v) for k, v in vars(module).items() if isinstance(v, (np.ndarray, np.generic, torch.Tensor))
                }
                cache = recomputed(module)
                now = {k: v for k, v in attributes.items() if v is not None and v[0] not in held and k not in cache}
                unsaved = {k: module._buffers.get(k) for k in module._non_persistent_buffers_set}  # persistent=False
                now |= {k: f for k, v in unsaved.items() if v is not None and (f := fingerprint(v)) is not None}
                seen = self.net_attributes.setdefault((name, path, id(module)), now)
                changed = [k for k, v in seen.items() if k in now and now[k][1:] != v[1:]]
                if changed:
                    label = ".".join(x for x in (name, path, changed[0]) if x)
                    fail(
                        f"`{label}`, a tensor a network holds as a plain attribute or a non-persistent buffer (not a "
                        "parameter or a buffer), changed since run.start: a network's state_dict() leaves it out, so no "
                        "checkpoint holds it, and --resume would start it from its initial value; register it as a buffer "
                        f"(self.register_buffer('{changed[0]}', ...), persistent) and change it in place"
                    )

    def state(self, step: int) -> list:
        """One checkpoint per seed of the process's state at `step`."""
        self.check_nets_held(starting=False)
        self.check_state_held()
        self.check_parts_whole()
        state = ckpt.snapshot(self.script, self.args, self.env_list, step, self.nets, self.optimizers, self.parts)
        return split_seeds({**state, "args_given": self.args_given}, self.parts, self.eval_returns, self.run_dirs)

    @contextlib.contextmanager
    def stop_on_nan(self, step: int):
        """Ends the run on a non-finite loss. An eager update stops before the optimizer step that the loss would
        have poisoned, so the state is still finite and is saved (each seed's in its folder); a recorded graph is
        checked only when it logs."""
        self.guarded += 1
        try:
            yield
        except NonFiniteError as quantity:
            if getattr(self.args, "cudagraphs", False):
                fail(
                    f"{quantity} became non-finite by step {step} (--cudagraphs checks every 100 steps and keeps no last "
                    "finite state; without it a run stops at the first bad update)"
                )
            fields = [f.name for f in dataclasses.fields(self.args)]
            rates = [f"--{name.replace('_', '-')}" for name in fields if name.endswith(("lr", "learning_rate"))]
            wrapped = [wrapper for _, wrapper in self.wrapped_envs() if wrapper]
            if wrapped:  # a checkpoint saves an env through make_env's EpisodeRecord, which a wrapper hides
                fail(
                    f"{quantity} became non-finite at step {step} (try a smaller {' or '.join(rates)}); the last finite "
                    f"state is not saved: the env given to run.start is a {wrapped[0]}, not the env make_env made"
                )
            ckpt.write_checkpoints(self.run_dirs, self.state(step), "last_good_state.pt")
            path = os.path.join(self.run_dirs[0], "last_good_state.pt")
            where = path if len(self.run_dirs) == 1 else f"{path} and the other seeds' folders"
            fail(
                f"{quantity} became non-finite at step {step} (try a smaller {' or '.join(rates)}); the last finite state "
                f"is in {where}"
            )
        finally:
            self.guarded -= 1

    def end_step(self, step: int, can_checkpoint: bool = True):
        """After step `step`: the training speed every 1000 steps (evaluations excluded), the progress bar, a
        checkpoint every --checkpoint-frequency steps (where `can_checkpoint`; the last one is finish()'s), and the
        check that main still holds the networks and optimizers `start` was given."""
        args = self.args
        if self.evaluation_due is not None:  # the first step of a resumed run
            due, self.evaluation_due = self.evaluation_due, None
            if step == due and self.eval_returns[0][-1][0] != due:
                fail(
                    f"step {step} ended without its evaluation: the run resumed at step {step}, where its record's "
                    f"evaluations, every {step - self.eval_returns[0][-1][0]} steps, put the next one, and the checkpoint it "
                    "resumed from was written before that evaluation; one made after run.end_step (run.evaluate(step + 1, "
                    "...)) is not made again by a resumed run, whose record would miss it: evaluate at the top of the step, "
                    "as the scripts do (if global_step % args.eval_frequency == 0: run.evaluate(global_step, ...))"
                )
        self.logs.step(step)
        now = self.caller.f_locals
        for name, x in self.bound.items():
            if now.get(name) is not x and isinstance(x, (torch.nn.Module, torch.optim.Optimizer)):
                what = "network" if isinstance(x, torch.nn.Module) else "optimizer"
                fail(
                    f"`{name}` was bound to a new object by step {step}: the checkpoints, --save-model and a --cudagraphs "
                    f"update hold the {what} given to run.start; change it in place instead (a reset: "
                    f"{name}.load_state_dict(fresh.state_dict()), fresh built as main builds it, by stack_seeds)"
                )
            if now.get(name) is not x:
                fail(
                    f"`{name}` was bound to a new object by step {step}: the checkpoints hold the part given to run.start, "
                    f"and --resume would restore that one; change it in place instead ({name}.copy_(...), "
                    f"{name}.mul_(...); an object: its load_state_dict(...))"
                )
        if self.args_set_in_main is None:  # attributes main gave args after run.start and changes from their own value
            counted = {k: v for k, v in vars(args).items() if k not in self.args_at_start and k in self.args_counted}
            self.args_set_in_main = {k: carried_state(v) for k, v in counted.items()}
        if args.checkpoint_frequency and can_checkpoint and self.next_checkpoint <= step + 1 < args.total_timesteps:
            self.check_logged_steps(step + 1)
            self.check_args_set_in_main(step + 1)
            self.check_carried(step + 1)
            self.check_nets_attributes()
            ckpt.write_checkpoints(self.run_dirs, self.state(step + 1))
            self.next_checkpoint = step + 1 + args.checkpoint_frequency

    def check_logged_steps(self, step: int):
        """Nothing is logged at the checkpoint's step or after it: a run resumed from it starts its logs again there,
        erasing what was logged at and after that step (TensorBoard's purge_step), which it would not log again."""
        if self.last_logged >= step:
            fail(
                f"run.log logged at step {self.last_logged} by the checkpoint at step {step}: a run resumed from it "
                "would erase what is logged at and after that step (the logs start again there) and not log it again; "
                "log at the step the loop is at (global_step), and another count (the updates) as a value"
            )

    def check_args_set_in_main(self, step: int):
        """An attribute main gives args after run.start is at each checkpoint what it was at the loop's first step's
        end: --resume restores args at run.start, then main sets it again, so a change since would be lost."""
        for name, before in self.args_set_in_main.items():
            if carried_state(getattr(self.args, name, None)) != before:
                fail(
                    f"main sets `args.{name}` after run.start, and by step {step} it is no longer what it was after the "
                    "loop's first step: --resume restores args at run.start, and main would then set it again; set it "
                    "before run.start (--resume then restores its value at the checkpoint)"
                )

    def finish(self, save: dict, eval_envs=None, policy=None) -> dict:
        """The last checkpoint, --save-model (each seed's cut of the `save` networks, tensors or objects, and how the
        evaluated `policy` acts, for tools/evaluate.py to check the policy it rebuilds from them), the envs and logs
        closed. Returns the runs' folders and evaluations."""
        args = self.args
        if args.checkpoint_frequency:
            self.check_nets_attributes()
            ckpt.write_checkpoints(self.run_dirs, self.state(args.total_timesteps))
        if args.save_model:
            n = len(self.run_dirs)
            models = [model_of_seed(save, k, n) for k in range(n)]  # before the probe, which a policy could move
            probes, why = [{}] * n, "run.finish was given no policy"
            try:  # a policy that fails on the probe leaves it out: the model is what the run was for
                probes = policy_probe(policy, self.env_list[0].observation_space, n) if policy is not None else probes
            except Exception as e:
                why = f"{type(e).__name__}: {(str(e).splitlines() or [''])[0]}"
            if not probes[0]:
                warning = f"warning: --save-model leaves out the policy's probe ({why}); evaluate.py cannot check it"
                tqdm.write(warning, file=sys.stderr)
            for model, probe, run_dir in zip(models, probes, self.run_dirs):
                model_path = os.path.join(run_dir, f"{args.exp_name}.cleanrl_model")
                torch.save({**model, **probe}, model_path)
                tqdm.write(f"model saved to {model_path}")
        for env in [*self.env_list, *(eval_envs if isinstance(eval_envs, SeedEnvs) else [eval_envs] if eval_envs else [])]:
            env.close()
        self.logs.close()
        return self.results()

    def results(self) -> dict:
        """What main returns about the runs: every seed's, and the first seed's as a single-seed run gives them."""
        return {
            "run_dir": self.run_dirs[0],
            "eval_returns": self.eval_returns[0],
            "run_dirs": self.run_dirs,
            "seeds_eval_returns": self.eval_returns,
        }
