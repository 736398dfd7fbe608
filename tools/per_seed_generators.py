"""A diagnostic for many-seed runs: `td3` or `oparl` with --num-seeds N, every training draw (replay indices,
exploration and target-policy noise) taken from a generator of its own seed instead of the process's one
generator. The initial weights are drawn as the many-seed process draws them. Nothing else changes, so
comparing its runs with ordinary many-seed runs of the same seeds asks whether sharing the generator matters:

    python tools/per_seed_generators.py td3 --env-id dm_control/cartpole-swingup-v0 --seed 1 --num-seeds 3 \
        --total-timesteps 100000 --run-name "dm_control-cartpole-swingup-v0__td3_x3g__{seed}__100000"

It is not a way to train: its runs cannot be resumed (the generators are not checkpointed, so it refuses
--resume and --checkpoint-frequency), and its generators are CPU ones. SAC is refused: its evaluations draw
too, which a single-seed run takes from the generator it trains with.
"""

import importlib
import os
import sys

import torch

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


def fail(message: str):
    sys.exit(f"per_seed_generators.py: {message}")


def main(argv: list):
    if not argv or argv[0] not in ("td3", "oparl"):
        fail("give td3 or oparl first, then the script's flags (SAC's evaluations draw too: not supported)")
    module = importlib.import_module(f"{argv[0]}_continuous_action")
    args = module.parse_args(argv[1:])
    if args.resume or args.checkpoint_frequency:
        fail("--resume and --checkpoint-frequency are not supported: the per-seed generators are not checkpointed")
    n = args.num_seeds
    generators = [torch.Generator().manual_seed(seed) for seed in range(args.seed, args.seed + n)]
    randint, normal = torch.randint, torch.normal

    def per_seed(name, shape):
        if shape[0] != n:
            raise RuntimeError(f"a {name} draw of shape {tuple(shape)} has no seeds dimension; this tool needs updating")

    def seeds_randint(high, size, **kwargs):
        per_seed("randint", size)
        return torch.stack([randint(high, tuple(size[1:]), generator=g, **kwargs) for g in generators])

    def seeds_normal(mean, std):
        per_seed("normal", std.shape)
        return torch.stack([normal(mean, std[k], generator=g) for k, g in enumerate(generators)])

    def seeds_randn_like(t):
        per_seed("randn_like", t.shape)
        return torch.stack([torch.randn(t.shape[1:], generator=g, dtype=t.dtype, device=t.device) for g in generators])

    torch.randint, torch.normal, torch.randn_like = seeds_randint, seeds_normal, seeds_randn_like
    return module.main(args)


if __name__ == "__main__":
    main(sys.argv[1:])
