"""Would a sweep's processes fit one GPU? `benchmark.sh --gpu` asks this before it starts anything, and stops with
its one-line answer when they would not.

    bash benchmark.sh --gpu ... --dry-run | grep -v '^#' | python tools/gpu_fit.py --workers 16

Each line on stdin is one process's training command, as `benchmark.sh --dry-run` prints it. A process's GPU memory
is estimated as

    CONTEXT_MIB                                  the CUDA context (less under MPS, which shares one)
    + per seed: replay rows x (2 obs_dim + action_dim + 2) x 4 bytes, rows = min(--buffer-size, --total-timesteps)
    + per seed: NETWORKS_MIB                     networks, gradients, Adam's moments, target networks, a batch's
                                                 activations and the recorded graphs

and the `--workers` largest processes are taken to run at once. The GPU's free memory is nvidia-smi's (the first
GPU), or --free-mib. Exit status 1, with one line on stderr, when they would not fit; 0 with a summary otherwise.
"""

import argparse
import importlib
import os
import shlex
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

CONTEXT_MIB = 600
NETWORKS_MIB = 150
_DIMS = {}


def dims(env_id: str) -> tuple:
    """(obs_dim, action_dim) of a task, from the scripts' own environment layer."""
    if env_id not in _DIMS:
        from rl_utils import make_env

        os.environ.setdefault("MUJOCO_GL", "disable")
        env = make_env(env_id, seed=0)
        _DIMS[env_id] = (env.observation_space.shape[0], env.action_space.shape[0])
        env.close()
    return _DIMS[env_id]


def process_mib(command: list) -> tuple:
    """(estimated MiB, a description) of one training command: python SCRIPT --flag value ..."""
    from rl_utils.cli import parse_args

    script = os.path.basename(command[1]).removesuffix(".py")
    module = importlib.import_module(script)
    flags = [flag for flag in command[2:] if flag != "--cudagraphs"]  # parsed here without a GPU
    resume = flags.index("--resume") if "--resume" in flags else None
    if resume is not None:
        del flags[resume : resume + 2]
    args = parse_args(module.Args, None, flags)
    seeds = getattr(args, "num_seeds", 1)
    obs_dim, action_dim = dims(args.env_id)
    rows = min(getattr(args, "buffer_size", 0), args.total_timesteps)
    buffer_mib = rows * (2 * obs_dim + action_dim + 2) * 4 / 2**20
    mib = CONTEXT_MIB + seeds * (buffer_mib + NETWORKS_MIB)
    what = f"{script} on {args.env_id}, {seeds} seed(s) x ({rows:,}-row replay buffer of {buffer_mib:,.0f} MiB + networks)"
    return mib, what


def free_mib() -> float:
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=memory.free", "--format=csv,noheader,nounits"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (FileNotFoundError, subprocess.CalledProcessError) as e:
        sys.exit(f"error: no GPU memory reading from nvidia-smi ({type(e).__name__}); give --free-mib")
    return float(out.split()[0])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, required=True, help="processes at a time")
    parser.add_argument("--free-mib", type=float, help="the GPU's free memory (default: nvidia-smi's)")
    args = parser.parse_args(argv)
    commands = [shlex.split(line) for line in sys.stdin if line.strip() and not line.startswith("#")]
    if not commands:
        print("gpu_fit: no process to start")
        return
    sizes = sorted((process_mib(command) for command in commands), reverse=True)
    at_once = sizes[: args.workers]
    need = sum(mib for mib, _ in at_once)
    free = args.free_mib if args.free_mib is not None else free_mib()
    summary = (
        f"{len(at_once)} process(es) at once need about {need / 1024:,.1f} GiB of GPU memory (the largest: "
        f"{sizes[0][1]}, {sizes[0][0] / 1024:,.1f} GiB); the GPU has {free / 1024:,.1f} GiB free"
    )
    if need > free:
        sys.exit(f"error: {summary}: run fewer at once (--workers) or fewer seeds a process (--seeds-per-process)")
    print(f"gpu_fit: {summary}")


if __name__ == "__main__":
    main()
