"""Training steps per second of whole scripts, start-up cost removed.

Each entry is timed as the difference between a run of L steps (all random: start-up, environment
creation, the random phase) and a run of L + T steps (the same plus T training steps), so the
figure is T / (time(L + T) - time(L)). Entries are alternated within every repeat, after one
untimed warm-up run each, and the median over repeats is reported.

An entry is one of our scripts by short name (`td3`, `sac`, `oparl`, `redq`, `ppo`, `rnd`, `ebd`), any script path, or a whole
command prefix, each optionally followed by its own flags and optionally prefixed by `mkl-avx512:` to run
it through tools/mkl_avx512.sh (MKL's AVX-512 kernels on AMD CPUs), e.g.

    python tools/throughput.py td3 sac oparl "oparl --bf16" --env-id Hopper-v4 --threads 1
    python tools/throughput.py oparl "mkl-avx512:oparl"   # the same script with tools/mkl_avx512.sh
    python tools/throughput.py oparl "oparl --num-seeds 2" "2x:oparl"   # 2 seeds in one process, 2 processes at once

An entry "Kx:..." runs K copies at once (each copy's steps/s is reported; its agent-steps/s are K times that),
and an entry with `--num-seeds N` trains N seeds (agent-steps/s: N times its steps/s).
    PYTHONPATH=../cleanrl python tools/throughput.py td3 "../cleanrl-venv/bin/python ../cleanrl/cleanrl/td3_continuous_action.py"

Every entry gets `--env-id E --total-timesteps N --learning-starts L --seed 1 --no-cuda` (no
`--learning-starts` for a script without one, such as PPO, whose L steps are then ordinary ones;
with `--cuda`, no `--no-cuda`: the entries run on the GPU, e.g. "td3 --cudagraphs");
our own scripts also get a single evaluation episode at the end and a throw-away run folder.
"""

import argparse
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OURS = {f.removesuffix("_continuous_action.py") for f in os.listdir(REPO) if f.endswith("_continuous_action.py")}
MKL_AVX512 = "mkl-avx512:"  # an entry's prefix: run it through tools/mkl_avx512.sh


def command_of(entry: str) -> tuple[list, bool]:
    """The command prefix for an entry, and whether it is one of this repository's scripts."""
    wrapper = []
    if entry.startswith(MKL_AVX512):
        wrapper, entry = ["bash", os.path.join(REPO, "tools", "mkl_avx512.sh")], entry.removeprefix(MKL_AVX512)
    # the runs start in a scratch folder: paths given relative to here must not change meaning there
    words = [
        os.path.abspath(w) if not os.path.isabs(w) and os.path.sep in w and os.path.exists(w) else w
        for w in shlex.split(entry)
    ]
    if not words:
        sys.exit(f"error: an entry names no script or command (got {MKL_AVX512 if wrapper else ''}{entry!r})")
    if words[0] in OURS:
        return wrapper + [sys.executable, os.path.join(REPO, f"{words[0]}_continuous_action.py"), *words[1:]], True
    if words[0].endswith(".py"):
        return wrapper + [sys.executable, *words], False
    return wrapper + words, False


def has_random_phase(prefix: list) -> bool:
    """Whether the entry's script takes --learning-starts (PPO, on-policy, has no random phase)."""
    script = next((word for word in prefix if word.endswith(".py")), None)
    if script is None:
        return True
    with open(script) as f:
        return "learning_starts:" in f.read()


def copies_of(entry: str) -> tuple[int, str]:
    """An entry "Kx:..." runs K copies of the rest at once (K single-seed processes beside each other)."""
    head, _, rest = entry.partition("x:")
    return (int(head), rest) if head.isdigit() and rest else (1, entry)


def agents_of(entry: str) -> int:
    """Seeds trained at once by an entry: its copies times its --num-seeds."""
    copies, entry = copies_of(entry)
    words = shlex.split(entry.removeprefix(MKL_AVX512))
    return copies * (int(words[words.index("--num-seeds") + 1]) if "--num-seeds" in words[:-1] else 1)


def timed_run(
    entry: str, env_id: str, steps: int, learning_starts: int, threads: int, workdir: str, cuda: bool = False
) -> float:
    copies, entry = copies_of(entry)
    prefix, ours = command_of(entry)
    flags = ["--env-id", env_id, "--total-timesteps", str(steps), "--seed", "1"] + ([] if cuda else ["--no-cuda"])
    if has_random_phase(prefix):
        flags += ["--learning-starts", str(learning_starts)]
    if ours:
        seeds = "_{seed}" if "--num-seeds" in entry else ""  # a run of several seeds names a folder per seed
        flags += ["--eval-frequency", str(10**9), "--eval-episodes", "1", "--run-name", f"throughput_{time.time_ns()}{seeds}"]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    if env.get("PYTHONPATH"):  # likewise for the entries' imports (e.g. PYTHONPATH=../cleanrl)
        env["PYTHONPATH"] = os.pathsep.join(os.path.abspath(p) for p in env["PYTHONPATH"].split(os.pathsep) if p)
    start = time.perf_counter()
    runs = []
    for copy in range(copies):  # each copy its own run folder
        run_flags = [f + f"_{copy}" if f.startswith("throughput_") else f for f in flags] if copies > 1 else flags
        runs.append(
            subprocess.Popen(
                prefix + run_flags, cwd=workdir, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
            )
        )
    results = [(run.wait(), run.stderr.read()) for run in runs]
    elapsed = time.perf_counter() - start
    for returncode, stderr in results:
        if returncode != 0:
            sys.exit(
                f"error: {entry!r} failed ({returncode}): {stderr.strip().splitlines()[-1] if stderr.strip() else 'no output'}"
            )
    return elapsed


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def gpu_name() -> str:
    import torch

    return torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU found"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "entries",
        nargs="+",
        help="a short name (td3, sac, oparl, redq, ppo, rnd, ebd) | path/to/script.py | 'command prefix', each with optional flags",
    )
    parser.add_argument("--env-id", default="Hopper-v4")
    parser.add_argument("--learning-starts", type=int, default=1000, help="L: random steps before training")
    parser.add_argument("--steps", type=int, default=2000, help="T: training steps timed")
    parser.add_argument("--threads", type=int, default=1, help="torch/BLAS threads per run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--baseline", default=None, help="the entry the ratios are relative to (default: the first)")
    parser.add_argument("--cuda", action="store_true", help="let every entry use the GPU (no --no-cuda)")
    args = parser.parse_args(argv)
    for name, value in [
        ("--steps", args.steps),
        ("--repeats", args.repeats),
        ("--threads", args.threads),
        ("--learning-starts", args.learning_starts),
    ]:
        if value <= 0:
            parser.error(f"{name} must be > 0, got {value}")
    baseline = args.baseline or args.entries[0]
    if baseline not in args.entries:
        parser.error(f"--baseline {baseline!r} is not one of the entries {args.entries}")

    sps = {entry: [] for entry in args.entries}
    with tempfile.TemporaryDirectory() as workdir:
        for entry in args.entries:  # warm-up: file caches, first imports
            took = timed_run(entry, args.env_id, args.learning_starts, args.learning_starts, args.threads, workdir, args.cuda)
            # as each entry ends: a slow entry shows at once, a stuck one by its missing line
            print(f"warm-up {entry}: {took:.1f} s", file=sys.stderr, flush=True)
        for repeat in range(args.repeats):
            for entry in args.entries:
                short = timed_run(
                    entry, args.env_id, args.learning_starts, args.learning_starts, args.threads, workdir, args.cuda
                )
                long = timed_run(
                    entry,
                    args.env_id,
                    args.learning_starts + args.steps,
                    args.learning_starts,
                    args.threads,
                    workdir,
                    args.cuda,
                )
                sps[entry].append(args.steps / (long - short))
                print(f"repeat {repeat + 1}/{args.repeats} {entry}: {sps[entry][-1]:.1f} steps/s", file=sys.stderr, flush=True)

    reference = statistics.median(sps[baseline])
    device = gpu_name() if args.cuda else cpu_name()
    print(
        f"\n{args.env_id}, {args.threads} thread(s), {args.steps} training steps after {args.learning_starts} random ones, median of {args.repeats}; {device}\n"
    )
    print(f"| entry | steps/s (median) | range | vs `{baseline}` | agent-steps/s (steps/s x seeds at once) |")
    print("|---|---|---|---|---|")
    for entry, values in sps.items():
        median = statistics.median(values)
        agents = f"{median * agents_of(entry):.1f}"
        print(f"| `{entry}` | {median:.1f} | {min(values):.1f}-{max(values):.1f} | {median / reference:.2f}x | {agents} |")


if __name__ == "__main__":
    main()
