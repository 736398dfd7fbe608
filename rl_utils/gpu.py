"""The GPU's own machinery: --cudagraphs (`CudaGraph`: a training update recorded once and replayed) and copies to
the GPU that do not wait for it (`to_device`)."""

import dataclasses
import functools
import inspect
import types

import torch

PLAIN = (bool, int, float, complex, str, bytes, tuple, frozenset, type(None))  # what a graph records as a constant


def probes(fn) -> list:
    """What `fn` reads that is not an argument and that a recorded graph keeps as it was: [(label, read)], each
    `read()` giving the value now (a plain one is compared by value, an object by identity: the one recorded). Found
    in `fn`'s closure, the globals it names, the functions and partials it reaches that way (three levels deep), and in
    what they hold: plain values, the fields of a dataclass or SimpleNamespace (args), a dict's or list's plain
    entries, an optimizer's hyperparameters (lr, betas, ...), a network's plain attributes and training flags."""
    found, seen = [], set()

    def value(label, read, depth):
        try:
            x = read()
        except (ValueError, KeyError, AttributeError, IndexError):  # an unfilled cell: nothing a graph could have read
            return
        found.append((label, read))
        if is_plain(x) or id(x) in seen:
            return
        seen.add(id(x))
        if isinstance(x, torch.optim.Optimizer):
            for i, group in enumerate(x.param_groups):
                for k in group:
                    if k != "params":
                        value(f"{label}.param_groups[{i}]['{k}']", lambda g=group, k=k: g[k], depth)
        elif isinstance(x, torch.nn.Module):  # its mode (eval() and train() set every layer's) and its plain attributes
            for k, v in vars(x).items():
                if not k.startswith("_") and isinstance(v, PLAIN):
                    found.append((f"{label}.{k}", lambda m=x, k=k: getattr(m, k)))
        elif dataclasses.is_dataclass(x) and not isinstance(x, type):
            for field in dataclasses.fields(x):
                found.append((f"{label}.{field.name}", lambda x=x, k=field.name: getattr(x, k)))
        elif isinstance(x, types.SimpleNamespace):
            for k in vars(x):
                found.append((f"{label}.{k}", lambda x=x, k=k: getattr(x, k)))
        elif isinstance(x, dict):
            for k, v in x.items():
                if isinstance(v, PLAIN):
                    found.append((f"{label}[{k!r}]", lambda x=x, k=k: x[k]))
        elif isinstance(x, list):
            for i, v in enumerate(x):
                if isinstance(v, PLAIN):
                    found.append((f"{label}[{i}]", lambda x=x, i=i: x[i]))
        elif depth < 3 and (isinstance(x, functools.partial) or getattr(x, "__module__", None) == module):
            # the script's own functions (not rl_utils'), and partials
            function(label, x, depth + 1)

    def function(label, f, depth):
        if isinstance(f, functools.partial):
            value(f"{label}.func", lambda: f.func, depth)
            for i in range(len(f.args)):
                value(f"{label}.args[{i}]", lambda i=i: f.args[i], depth)
            for k in f.keywords:
                value(f"{label}.keywords[{k!r}]", lambda k=k: f.keywords[k], depth)
            return
        if isinstance(f, types.MethodType):
            value(f"{label}.__self__", lambda: f.__self__, depth)
            f = f.__func__
        f = inspect.unwrap(f) if isinstance(f, types.FunctionType) else f
        if not isinstance(f, types.FunctionType):
            return
        for name, cell in zip(f.__code__.co_freevars, f.__closure__ or ()):
            value(name, lambda c=cell: c.cell_contents, depth)
        for name in f.__code__.co_names if f.__module__ == module else ():
            if name in f.__globals__ and not isinstance(f.__globals__[name], (types.ModuleType, type)):
                value(name, lambda g=f.__globals__, k=name: g[k], depth)

    module = module_of(fn)
    function(getattr(fn, "__name__", "fn"), fn, 0)
    return found


def module_of(fn):
    """The module whose functions `probes` follows: fn's own (a partial's function's, a wrapped function's)."""
    top = fn.func if isinstance(fn, functools.partial) else fn
    return getattr(inspect.unwrap(top) if isinstance(top, types.FunctionType) else top, "__module__", None)


def is_plain(x) -> bool:
    return isinstance(x, PLAIN) and (not isinstance(x, (tuple, frozenset)) or all(map(is_plain, x)))


def now(watched: list) -> tuple:
    """The watched values now: plain ones themselves, objects by identity."""
    values = []
    for _, read in watched:
        try:
            x = read()
        except (ValueError, KeyError, AttributeError, IndexError):
            x = None
        values.append(x if is_plain(x) else ("object", id(x)))
    return tuple(values)


def same(a, b) -> bool:
    return a == b or (a != a and b != b)  # NaN is NaN


class CudaGraph:
    """--cudagraphs: `update = CudaGraph(update)` runs `update(batch, policy_step)` as a CUDA graph, one graph per
    value of the arguments that are not tensors (at most `max_graphs` values: a number that changes at every call is
    passed as a tensor). The first `warmup` calls of each value run eagerly on a side stream (they allocate the
    gradients and optimizer states the graph will reuse), the next one records the graph, and from then on a call
    copies its tensors (a tensor, or a NamedTuple of them such as a Batch) into the graph's own inputs and replays it:
    one launch instead of hundreds of small kernels, with no host synchronisation. What it returns is overwritten by
    its next replay. The default CUDA generator is registered with each graph, so that a replay draws anew from it and
    advances it as `fn` would. A graph replays the networks it recorded: reset them in place, never by assignment.

    A graph also keeps every number `fn` read while it was recorded, and the objects it read. So what `fn` reads
    without taking it is watched (`probes`: its closure, the globals it names, its helpers' and what they hold: args'
    fields, optimizers' hyperparameters, networks' modes); a replay after one of them changed (within CHECK_EVERY
    replays) stops, naming it: a value that changes goes in as a tensor changed in place, which a graph reads anew at
    each replay (an optimizer's lr: a tensor, .fill_(new_lr))."""

    CHECK_EVERY = 10  # replays between two looks at what the recorded update read (a look costs ~10-70 us on a CPU)

    def __init__(self, fn, warmup: int = 3, max_graphs: int = 8):
        self.fn, self.warmup, self.max_graphs = fn, warmup, max_graphs
        self.calls, self.graphs, self.inputs, self.outputs, self.watched, self.recorded = {}, {}, {}, {}, {}, {}
        self.replays = {}

    def check_reads(self, key: tuple):
        """Stops a replay of the graph recorded for `key` if something it read as a constant has changed since (looked
        at every CHECK_EVERY replays: a change stops the run within that many updates)."""
        self.replays[key] = self.replays.get(key, 0) + 1
        if self.replays[key] % self.CHECK_EVERY != 1:
            return
        values = now(self.watched[key])
        if values == self.recorded[key]:
            return
        for (label, _), then, value in zip(self.watched[key], self.recorded[key], values):
            if not same(then, value):
                break
        else:
            return  # only a NaN read anew
        if isinstance(then, tuple) and then[:1] == ("object",):
            raise ValueError(
                f"CudaGraph({getattr(self.fn, '__name__', self.fn)}): `{label}` is another object than when the graph "
                "was recorded, and the graph replays the one it recorded: keep the object and change what it holds in "
                "place (a network or optimizer: load_state_dict(fresh.state_dict()); a tensor: .copy_(new))"
            )
        raise ValueError(
            f"CudaGraph({getattr(self.fn, '__name__', self.fn)}): `{label}` was {then!r} when the graph was recorded and "
            f"is {value!r} now; a graph replays the values it recorded: make a value that changes a tensor, changed in "
            "place (an optimizer's lr: torch.tensor(lr, device=...), then .fill_(new_lr)), which the graph reads anew at "
            "each replay"
        )

    @staticmethod
    def key(*inputs) -> tuple:
        return tuple(x for x in inputs if not isinstance(x, (torch.Tensor, tuple)))

    @staticmethod
    def clone(x):  # a tensor, or a NamedTuple of them, copied; anything else as it is
        if isinstance(x, torch.Tensor):
            return x.clone()
        return type(x)(*map(torch.clone, x)) if isinstance(x, tuple) else x

    @staticmethod
    def tensors(inputs) -> list:
        return [t for x in inputs for t in ([x] if isinstance(x, torch.Tensor) else x if isinstance(x, tuple) else [])]

    def __call__(self, *inputs):
        key = self.key(*inputs)
        if key not in self.calls and len(self.calls) == self.max_graphs:  # a number that changes at every call
            raise ValueError(
                f"CudaGraph({getattr(self.fn, '__name__', self.fn)}): its arguments that are not tensors took "
                f"{self.max_graphs + 1} different values ({', '.join(map(str, [*self.calls, key][-3:]))}, ...); each value "
                f"runs {self.warmup} calls eagerly and then records a graph of its own: pass a number that changes from "
                "call to call as a tensor (torch.tensor(x, device=...)), which the graph reads anew at each replay"
            )
        if key in self.graphs:
            self.check_reads(key)
            for static, new in zip(self.tensors(self.inputs[key]), self.tensors(inputs)):
                static.copy_(new)
        else:
            self.calls[key] = self.calls.get(key, 0) + 1
            if self.calls[key] <= self.warmup:
                stream = torch.cuda.Stream()
                stream.wait_stream(torch.cuda.current_stream())
                with torch.cuda.stream(stream):
                    outputs = self.fn(*inputs)
                torch.cuda.current_stream().wait_stream(stream)
                return outputs
            self.inputs[key] = [self.clone(x) for x in inputs]
            self.watched[key] = probes(self.fn)
            self.recorded[key] = now(self.watched[key])
            self.graphs[key] = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graphs[key]):  # records the kernels without running them
                self.outputs[key] = self.fn(*self.inputs[key])
        self.graphs[key].replay()
        outputs = self.outputs[key]  # a dict (the logs) as a copy: a key the caller adds must not outlive this call
        return dict(outputs) if isinstance(outputs, dict) else outputs


def to_device(x, device: torch.device) -> torch.Tensor:
    """x (an array or a tensor) on the device. To a GPU it goes through pinned memory without waiting for the GPU:
    a copy from ordinary (pageable) memory first waits for every kernel queued, a replaying --cudagraphs update's
    too, and only then could acting launch its kernels; this way they are queued behind the update while it runs."""
    x = torch.as_tensor(x)
    if device.type != "cuda" or x.is_cuda:
        return x.to(device)
    # pin_memory copies x (an already pinned x it returns as it is, which must then not change until the copy
    # has read it); the pinned block is not reused before that
    return x.pin_memory().to(device, non_blocking=True)
