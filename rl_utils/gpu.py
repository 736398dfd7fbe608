"""The GPU's own machinery: --cudagraphs (`CudaGraph`: a training update recorded once and replayed) and copies to
the GPU that do not wait for it (`to_device`)."""

import dataclasses

import torch

PLAIN = (bool, int, float, str, tuple, type(None))  # values a graph records as constants (a tuple: Adam's betas)


class CudaGraph:
    """--cudagraphs: `update = CudaGraph(update)` runs `update(batch, policy_step)` as a CUDA graph, one graph per
    value of the arguments that are not tensors (at most `max_graphs` values: a number that changes at every call is
    passed as a tensor). The first `warmup` calls of each value run eagerly on a side stream (they allocate the
    gradients and optimizer states the graph will reuse), the next one records the graph, and from then on a call
    copies its tensors (a tensor, or a NamedTuple of them such as a Batch) into the graph's own inputs and replays it:
    one launch instead of hundreds of small kernels, with no host synchronisation. What it returns is overwritten by
    its next replay. The default CUDA generator is registered with each graph, so that a replay draws anew from it and
    advances it as `fn` would. A graph replays the networks it recorded: reset them in place, never by assignment.

    A graph also keeps every number `fn` read while it was recorded. So what `fn` reads without taking it is watched
    (`reads`): the plain values in its closure, the fields of a dataclass there (args) and its optimizers'
    hyperparameters (lr, betas, ...); a replay after one of them changed stops, naming it: a value that changes goes
    in as a tensor, which a graph reads anew at each replay (an optimizer's lr: a tensor changed in place)."""

    def __init__(self, fn, warmup: int = 3, max_graphs: int = 8):
        self.fn, self.warmup, self.max_graphs = fn, warmup, max_graphs
        self.calls, self.graphs, self.inputs, self.outputs, self.recorded, self.fingerprints = {}, {}, {}, {}, {}, {}

    def closure(self) -> dict:
        """{name: value} of the variables `fn` reads from the function that defined it (main's: args, optimizers, ...)."""
        code, cells = getattr(self.fn, "__code__", None), getattr(self.fn, "__closure__", None) or ()
        found = {}
        for name, cell in zip(code.co_freevars if code else (), cells):
            try:
                found[name] = cell.cell_contents
            except ValueError:  # a cell not yet filled
                pass
        return found

    def reads(self) -> dict:
        """{name: value} of what `fn` reads that is not an argument and that a graph keeps as recorded: the plain values
        in its closure, the fields of a dataclass there (args), its optimizers' hyperparameters (lr, betas, ...), and
        which object each other variable there is."""
        found = {}
        for name, value in self.closure().items():
            if isinstance(value, torch.optim.Optimizer):
                for i, group in enumerate(value.param_groups):
                    found.update({f"{name}.param_groups[{i}]['{k}']": v for k, v in group.items() if isinstance(v, PLAIN)})
            elif dataclasses.is_dataclass(value) and not isinstance(value, type):
                found.update({f"{name}.{k}": v for k, v in vars(value).items() if isinstance(v, PLAIN)})
            found[name] = value if isinstance(value, PLAIN) else f"the object {id(value):#x}"
        return found

    def fingerprint(self) -> list:
        """reads() in a form that compares quickly (each replay does): containers copied, compared by identity within."""
        values = []
        for value in self.closure().values():
            if isinstance(value, torch.optim.Optimizer):
                values.append([dict(group) for group in value.param_groups])
            elif dataclasses.is_dataclass(value) and not isinstance(value, type):
                values.append(dict(vars(value)))
            values.append(value if isinstance(value, PLAIN) else id(value))
        return values

    def check_reads(self, key: tuple):
        """Stops a replay of the graph recorded for `key` if something it read as a constant has changed since."""
        if self.fingerprint() == self.fingerprints[key]:
            return
        now, then = self.reads(), self.recorded[key]
        name = next((n for n in {**then, **now} if now.get(n) != then.get(n)), "a value in its closure")
        raise ValueError(
            f"CudaGraph({getattr(self.fn, '__name__', self.fn)}): `{name}` was {then.get(name)!r} when the graph was "
            f"recorded and is {now.get(name)!r} now; a graph replays the values it recorded: make a value that changes a "
            "tensor, changed in place (an optimizer's lr: torch.tensor(lr, device=...), then .fill_(new_lr)), which the "
            "graph reads anew at each replay"
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
            self.recorded[key], self.fingerprints[key] = self.reads(), self.fingerprint()
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
