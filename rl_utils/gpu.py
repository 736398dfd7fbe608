"""The GPU's own machinery: --cudagraphs (`CudaGraph`: a training update recorded once and replayed) and copies to
the GPU that do not wait for it (`to_device`)."""

import torch


class CudaGraph:
    """--cudagraphs: `update = CudaGraph(update)` runs `update(batch, policy_step)` as a CUDA graph, one graph per
    value of the arguments that are not tensors (at most `max_graphs` values: a number that changes at every call is
    passed as a tensor). The first `warmup` calls of each value run eagerly on a side stream (they allocate the
    gradients and optimizer states the graph will reuse), the next one records the graph, and from then on a call
    copies its tensors (a tensor, or a NamedTuple of them such as a Batch) into the graph's own inputs and replays it:
    one launch instead of hundreds of small kernels, with no host synchronisation. What it returns is overwritten by
    its next replay. The default CUDA generator is registered with each graph, so that a replay draws anew from it and
    advances it as `fn` would. A graph replays the networks it recorded: reset them in place, never by assignment."""

    def __init__(self, fn, warmup: int = 3, max_graphs: int = 8):
        self.fn, self.warmup, self.max_graphs = fn, warmup, max_graphs
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
        if key not in self.calls and len(self.calls) == self.max_graphs:  # a number that changes at every call
            raise ValueError(
                f"CudaGraph({getattr(self.fn, '__name__', self.fn)}): its arguments that are not tensors took "
                f"{self.max_graphs + 1} different values ({', '.join(map(str, [*self.calls, key][-3:]))}, ...); each value "
                f"runs {self.warmup} calls eagerly and then records a graph of its own: pass a number that changes from "
                "call to call as a tensor (torch.tensor(x, device=...)), which the graph reads anew at each replay"
            )
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
