"""What each speed lever of the scripts buys, timed in isolation on the TD3/OPARL shapes.

Each row times the textbook way of doing a piece of a training step (as CleanRL does it, unless
said otherwise) against the way the scripts do it, on the same inputs, alternating the two and
taking the median over blocks. Shapes: Hopper-v4 (11-dim observations, 3-dim actions), batch 256,
256-unit layers; one torch thread unless OMP_NUM_THREADS says otherwise.

    python tools/speed/levers.py [--repeats 7] [--calls 50]
"""

import argparse
import os
import statistics
import sys
import time

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
import torch  # noqa: E402
import torch.nn as nn  # noqa: E402
import torch.nn.functional as F  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import oparl_continuous_action as oparl  # noqa: E402
import td3_continuous_action as td3  # noqa: E402
from rl_utils import ReplayBuffer  # noqa: E402

OBS, ACT, BATCH = 11, 3, 256


def mlp_critic():  # CleanRL's QNetwork
    return nn.Sequential(nn.Linear(OBS + ACT, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, 1))


class BatchedEnsemble(nn.Module):
    """N critics with each layer's weights stacked into one [N, in, out] tensor, one batched matmul per layer (what the
    scripts' QEnsemble was before it became a loop over QNetworks)."""

    def __init__(self, n: int):
        super().__init__()
        self.w1, self.b1 = nn.Parameter(torch.randn(n, OBS + ACT, 256) * 0.1), nn.Parameter(torch.zeros(n, 1, 256))
        self.w2, self.b2 = nn.Parameter(torch.randn(n, 256, 256) * 0.06), nn.Parameter(torch.zeros(n, 1, 256))
        self.w3, self.b3 = nn.Parameter(torch.randn(n, 256) * 0.06), nn.Parameter(torch.zeros(n, 1))

    def forward(self, obs, actions):
        x = torch.cat([obs, actions], -1).expand(len(self.w1), -1, -1).contiguous()
        x = F.relu(torch.baddbmm(self.b1, x, self.w1))
        x = F.relu(torch.baddbmm(self.b2, x, self.w2))
        return (x * self.w3[:, None]).sum(-1) + self.b3


def timed(fn, calls):
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls * 1e3


def compare(before, after, repeats, calls):
    for fn in (before, after):
        timed(fn, 5)  # warm-up
    times = {0: [], 1: []}
    for _ in range(repeats):
        for i, fn in enumerate((before, after)):
            times[i].append(timed(fn, calls))
    return statistics.median(times[0]), statistics.median(times[1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--calls", type=int, default=50)
    args = parser.parse_args(argv)
    torch.manual_seed(0)
    obs, actions, y = torch.randn(BATCH, OBS), torch.rand(BATCH, ACT) * 2 - 1, torch.randn(BATCH)
    space = td3.gym.spaces.Box(-1.0, 1.0, (ACT,), np.float32)
    actor, optimistic = td3.Actor(OBS, space), td3.Actor(OBS, space)
    rows = []

    def row(name, per_step, before, after, note=""):
        b, a = compare(before, after, args.repeats, args.calls)
        rows.append((name, b, a, per_step * (b - a), note))
        print(f"{name}: {b:.3f} -> {a:.3f} ms", file=sys.stderr, flush=True)

    for n in (2, 5):  # critic update: forward and backward of every member
        ensemble, batched = td3.QEnsemble(OBS, ACT, num_q=n), BatchedEnsemble(n)

        def loop(ensemble=ensemble):
            ((ensemble(obs, actions) - y) ** 2).mean(1).sum().backward()

        def hand_batched(batched=batched):
            ((batched(obs, actions) - y) ** 2).mean(1).sum().backward()

        row(
            f"critic forward+backward, {n} critics: a loop over QNetworks (kept) -> one hand-batched ensemble",
            1,
            loop,
            hand_batched,
        )

    ensemble = td3.QEnsemble(OBS, ACT, num_q=2)

    def actor_loss(frozen):
        ensemble.requires_grad_(not frozen)
        (-ensemble[0](obs, actor(obs)).mean()).backward()
        ensemble.requires_grad_(True)
        ensemble.zero_grad(set_to_none=True)

    row(
        "TD3 actor loss: gradients into the critic's weights too -> the critics frozen (requires_grad off)",
        0.5,
        lambda: actor_loss(False),
        lambda: actor_loss(True),
    )

    ensemble5 = oparl.QEnsemble(OBS, ACT, num_q=5).requires_grad_(False)

    def two_passes():
        (-ensemble5(obs, actor(obs)).min(0).values.mean() - ensemble5(obs, optimistic(obs)).max(0).values.mean()).backward()

    def one_pass():
        q_pes, q_opt = ensemble5(torch.cat([obs, obs]), torch.cat([actor(obs), optimistic(obs)])).chunk(2, dim=1)
        (-q_pes.min(0).values.mean() - q_opt.max(0).values.mean()).backward()

    row("OPARL's two actor losses: two ensemble passes -> one pass on both batches", 0.5, two_passes, one_pass)

    nets = [td3.Actor(OBS, space), td3.QEnsemble(OBS, ACT, num_q=2)]
    targets = [td3.Actor(OBS, space), td3.QEnsemble(OBS, ACT, num_q=2)]
    separate_nets = [td3.Actor(OBS, space), mlp_critic(), mlp_critic()]
    separate_targets = [td3.Actor(OBS, space), mlp_critic(), mlp_critic()]

    @torch.no_grad()
    def loop_update():  # CleanRL: one Python statement per parameter
        for net, target in zip(separate_nets, separate_targets):
            for param, target_param in zip(net.parameters(), target.parameters()):
                target_param.data.copy_(0.005 * param.data + (1 - 0.005) * target_param.data)

    row(
        "TD3 target networks: a loop over parameters -> one _foreach_lerp_",
        0.5,
        loop_update,
        lambda: td3.soft_update(targets, nets, 0.005),
    )

    for n in (2, 5):
        critics = td3.QEnsemble(OBS, ACT, num_q=n)
        ((critics(obs, actions) - y) ** 2).mean().backward()
        default_adam = torch.optim.Adam(critics.parameters(), lr=3e-4)
        fused_adam = torch.optim.Adam(critics.parameters(), lr=3e-4, fused=True)
        row(
            f"Adam step on {n} critics: default (foreach) -> fused",
            1,
            default_adam.step,
            fused_adam.step,
            "changes the float rounding slightly",
        )

    capacity = 100_000
    rb = ReplayBuffer(capacity, OBS, ACT, 1, torch.device("cpu"))  # one seed's
    numpy_fields = [np.random.randn(capacity, d).astype(np.float32) for d in (OBS, ACT, OBS, 1, 1)]
    rb.storage.normal_()
    rb.size = capacity

    def numpy_sample():  # SB3's ReplayBuffer: numpy arrays, one fancy index and one tensor copy per field
        idx = np.random.randint(0, capacity, BATCH)
        return [torch.as_tensor(f[idx]) for f in numpy_fields]

    def tensor_sample():  # ours: draw the rows, one gather
        return rb.sample(BATCH)

    row("replay sample: numpy arrays per field -> one gather from one tensor", 1, numpy_sample, tensor_sample)

    a, b = torch.randn(256, 256), torch.randn(256, 256)
    rates = {}
    for dtype in (torch.float32, torch.bfloat16):
        x, w = a.to(dtype), b.to(dtype)
        rates[dtype] = 2 * 256**3 / statistics.median(timed(lambda: x @ w, 200) for _ in range(args.repeats)) / 1e6
    print(
        f"\n{torch.get_num_threads()} thread(s), batch {BATCH}, Hopper-v4 shapes, median of {args.repeats} blocks of {args.calls} calls"
    )
    print(
        f"a 256x256x256 matmul runs at {rates[torch.float32]:.0f} GFLOP/s in float32, {rates[torch.bfloat16]:.0f} in bfloat16\n"
    )
    print("| lever | before (ms) | after (ms) | saved per training step (ms) | note |")
    print("|---|---|---|---|---|")
    for name, before, after, saved, note in rows:
        print(f"| {name} | {before:.3f} | {after:.3f} | {saved:.3f} | {note} |")


if __name__ == "__main__":
    main()
