"""What a training step computes in: the NaN guard (`check_finite`, which raises `NonFiniteError` before an optimizer
step a non-finite loss would poison, and with several seeds stops a loss that mixes them on its first steps),
--bf16's matmuls (`bf16_autocast`), and networks that take no gradient for a while (`frozen`)."""

import contextlib

import torch

from rl_utils.seeds import check_apart, record_checked


class NonFiniteError(Exception):
    """A loss became NaN or infinite; raised before the optimizer step it would have poisoned."""


def check_finite(value: torch.Tensor, name: str):
    """Raises NonFiniteError if any of `value` (a loss, one per seed) is not finite. With several seeds, on a loss's
    first steps, also stops a loss whose seeds are not apart (rl_utils.seeds.check_apart)."""
    # a graph cannot stop on a value: under --cudagraphs the loop checks what it logs
    if value.is_cuda and torch.cuda.is_current_stream_capturing():
        return
    if not torch.isfinite(value).all():
        raise NonFiniteError(name)
    check_apart(value, name)
    record_checked(value)


def bf16_autocast(device: torch.device, enabled: bool):
    """--bf16: the matmuls of one training step in bfloat16. Autocast's cache of cast weights is off:
    an optimizer updates weights in place within the step, and a cached cast would keep the old values."""
    return torch.autocast(device.type, torch.bfloat16, enabled=enabled, cache_enabled=False)


@contextlib.contextmanager
def frozen(*networks):
    """Within the block, no gradient is computed for the networks' parameters (an actor's loss through the critics:
    SpinningUp's freeze); afterwards each parameter's requires_grad is what it was (a part frozen for good stays so)."""
    params = [p for net in networks for p in net.parameters()]
    before = [p.requires_grad for p in params]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, requires_grad in zip(params, before):
            p.requires_grad_(requires_grad)
