"""What keeps a training step's arithmetic safe and fast: the NaN guard, --bf16, --cudagraphs, and a copy to the GPU
that does not wait for it."""

import torch


class NonFiniteError(Exception):
    """A loss became NaN or infinite; raised before the optimizer step it would have poisoned."""


def check_finite(value: torch.Tensor, name: str):
    """Raises NonFiniteError if any of `value` (a loss, one per seed) is not finite."""
    # a graph cannot stop on a value: under --cudagraphs the loop checks what it logs
    if value.is_cuda and torch.cuda.is_current_stream_capturing():
        return
    if not torch.isfinite(value).all():
        raise NonFiniteError(name)


def bf16_autocast(device: torch.device, enabled: bool):
    """--bf16: the matmuls of one training step in bfloat16. Autocast's cache of cast weights is off:
    an optimizer updates weights in place within the step, and a cached cast would keep the old values."""
    return torch.autocast(device.type, torch.bfloat16, enabled=enabled, cache_enabled=False)


class CudaGraph:
    """--cudagraphs: `update = CudaGraph(update)` runs `update(batch, policy_step)` as a CUDA graph, one graph per
    value of the arguments that are not tensors. The first `warmup` calls of each run eagerly on a side stream (they
    allocate the gradients and optimizer states the graph will reuse), the next one records the graph, and from then
    on a call copies its tensors (a tensor, or a NamedTuple of them such as a Batch) into the graph's own inputs and
    replays it: one launch instead of hundreds of small kernels, with no host synchronisation. What it returns is
    overwritten by its next replay. The default CUDA generator is registered with each graph, so that a replay draws
    anew from it and advances it as `fn` would."""

    def __init__(self, fn, warmup: int = 3):
        self.fn, self.warmup = fn, warmup
        self.calls, self.graphs, self.inputs, self.outputs = {}, {}, {}, {}

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
        if key in self.graphs:
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
            self.graphs[key] = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graphs[key]):  # records the kernels without running them
                self.outputs[key] = self.fn(*self.inputs[key])
        self.graphs[key].replay()
        return self.outputs[key]


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
