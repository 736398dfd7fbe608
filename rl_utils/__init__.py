"""The machinery the algorithm scripts import, as CleanRL's scripts import `cleanrl_utils`. Every line of an algorithm
stays in its own script; what this changes in what a run computes is its switches' (--bf16, --num-seeds, whose seeds
draw other noise than single-seed runs) and says so where they are. One module a job:

    cli          Args from the command line, checked (`parse_args`; `positive`, `at_least`, `within` for a
                 script's own `check_args`)
    errors       a one-line stop on bad input (`fail`), and a refusal raised in a run that prints as one (`refusal`)
    envs         Gymnasium MuJoCo and DeepMind Control tasks as flat float32 envs (`make_env`), one per seed side
                 by side (`SeedEnvs`), the deterministic evaluation loop (`evaluate`), and --save-model's record of
                 how the evaluated policy acts (`policy_probe`)
    buffers      the replay buffer of the off-policy scripts (`ReplayBuffer`, `Batch`)
    seeds        several seeds in one process (--num-seeds): one seed's networks stacked (`stack_seeds`), a function
                 written for one seed run for all of them at once (`per_seed`), each seed's cut of a checkpoint, and
                 gradient clipping and nn.init made per seed on stacked parameters
    numerics     the NaN guard (`check_finite`), --bf16 (`bf16_autocast`), a network's gradients off a while (`frozen`)
    gpu          --cudagraphs (`CudaGraph`) and copies to the GPU that do not wait for it (`to_device`)
    checkpoints  what a checkpoint holds and how a run continues from it, exactly (`snapshot`, `restore`), the envs'
                 episodes included (`EpisodeRecord`, which make_env puts around every env)
    logs         what a run reports: TensorBoard and --track, the progress bar, evaluations, the training speed
    run          a process's runs (`Run`): their folders, --resume, checkpoints when due, the NaN stop, --save-model,
                 and that main checkpoints every network and optimizer it holds, the same objects throughout
"""

from rl_utils.buffers import Batch, ReplayBuffer
from rl_utils.cli import at_least, parse_args, positive, within
from rl_utils.envs import SeedEnvs, evaluate, make_env
from rl_utils.errors import fail
from rl_utils.gpu import CudaGraph, to_device
from rl_utils.numerics import bf16_autocast, check_finite, frozen
from rl_utils.run import Run
from rl_utils.seeds import per_seed, stack_seeds

__all__ = [
    "Batch",
    "CudaGraph",
    "ReplayBuffer",
    "Run",
    "SeedEnvs",
    "at_least",
    "bf16_autocast",
    "check_finite",
    "evaluate",
    "fail",
    "frozen",
    "make_env",
    "parse_args",
    "per_seed",
    "positive",
    "stack_seeds",
    "to_device",
    "within",
]
