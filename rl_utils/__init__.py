"""The machinery the algorithm scripts import, as CleanRL's scripts import `cleanrl_utils`. Nothing here changes
what an algorithm computes; every line of an algorithm stays in its own script.

    cli          Args from the command line, checked: one-line errors for bad input (`parse_args`, `fail`)
    envs         Gymnasium MuJoCo and DeepMind Control tasks as flat float32 envs (`make_env`), one per seed side
                 by side (`SeedEnvs`), and the deterministic evaluation loop (`evaluate`)
    buffers      the replay buffer of the off-policy scripts (`ReplayBuffer`, `Batch`)
    seeds        several seeds in one process (--num-seeds): one seed's networks stacked (`stack_seeds`) and a
                 function written for one seed run for all of them at once (`per_seed`)
    numerics     the NaN guard (`check_finite`), --bf16 (`bf16_autocast`), --cudagraphs (`CudaGraph`), `to_device`
    checkpoints  what a checkpoint holds and how a run continues from it, exactly (`snapshot`, `restore`)
    run          a process's runs (`Run`): run folders, TensorBoard and --track, the progress bar, evaluations,
                 checkpoints and --resume, the NaN stop, --save-model
"""

from rl_utils.buffers import Batch, ReplayBuffer
from rl_utils.cli import fail, parse_args
from rl_utils.envs import SeedEnvs, evaluate, make_env
from rl_utils.numerics import CudaGraph, bf16_autocast, check_finite, to_device
from rl_utils.run import Run
from rl_utils.seeds import per_seed, stack_seeds

__all__ = [
    "Batch",
    "CudaGraph",
    "ReplayBuffer",
    "Run",
    "SeedEnvs",
    "bf16_autocast",
    "check_finite",
    "evaluate",
    "fail",
    "make_env",
    "parse_args",
    "per_seed",
    "stack_seeds",
    "to_device",
]
