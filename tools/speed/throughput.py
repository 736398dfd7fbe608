"""Training steps per second of whole scripts, start-up cost removed.

Each entry is timed as the difference between a run of L steps (all random: start-up, environment
creation, the random phase) and a run of L + T steps (the same plus T training steps), so the
figure is T / (time(L + T) - time(L)). Entries are alternated within every repeat, after one
untimed warm-up run each, and the median over repeats is reported.

An entry is one of our scripts by short name (`td3`, `sac`, `oparl`, `redq`, `ppo`, `rnd`, `ebd`), any script path, or a whole
command prefix, each optionally followed by its own flags and optionally prefixed by `mkl-avx512:` to run
it through tools/mkl_avx512.sh (MKL's AVX-512 kernels on AMD CPUs), e.g.

    python tools/speed/throughput.py td3 sac oparl "oparl --bf16" --env-id Hopper-v4 --threads 1
    python tools/speed/throughput.py oparl "mkl-avx512:oparl"   # the same script with tools/mkl_avx512.sh
    python tools/speed/throughput.py oparl "oparl --num-seeds 2" "2x:oparl"   # 2 seeds in one process, 2 processes at once

With `--window`, every entry runs once per repeat for L + T steps, and its figure is read from the
`charts/SPS` that our scripts log for each window of 1000 steps (evaluations excluded), over the windows that
start `--warmup` training steps or more after learning starts: start-up, the random phase, the first
updates (and, with `--cudagraphs`, their recording) fall outside the timed windows, as in LeanRL's timing.
Each window is one sample (the median and range are over all windows of all repeats); one run costs one
process start instead of two, which is what a short GPU lease can afford. Another script (CleanRL's) is read
by the cumulative charts/SPS it logs (see logged_sps) and must log it under runs/ in its working folder.

    python tools/speed/throughput.py "oparl --cudagraphs" "oparl --cudagraphs --num-seeds 16" "8x:oparl --cudagraphs --num-seeds 16" \
        --cuda --window --env-id dm_control/cartpole-swingup-v0 --learning-starts 500 --steps 3500 --repeats 1 --csv scaling.csv

An entry "Kx:..." runs K copies at once (each copy's steps/s is reported; its agent-steps/s are K times that),
and an entry with `--num-seeds N` trains N seeds (agent-steps/s: N times its steps/s).
    PYTHONPATH=../cleanrl python tools/speed/throughput.py td3 "../cleanrl-venv/bin/python ../cleanrl/cleanrl/td3_continuous_action.py"

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

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
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
    """Runs the entry (all its copies at once) in workdir and returns the wall time in seconds."""
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
        # stderr into a file, not a pipe: a pipe nobody reads while the run goes on blocks a run that writes more than
        # the pipe holds (64 KiB), as dm-control under NumPy 2.5 does with a DeprecationWarning at every step
        log = tempfile.TemporaryFile(mode="w+", dir=workdir)  # noqa: SIM115 (closed once read, below)
        runs.append((subprocess.Popen(prefix + run_flags, cwd=workdir, env=env, stdout=subprocess.DEVNULL, stderr=log), log))
    results = [(run.wait(), log) for run, log in runs]
    elapsed = time.perf_counter() - start
    for returncode, log in results:
        log.seek(0)
        stderr = log.read().strip()
        log.close()
        if returncode != 0:
            sys.exit(f"error: {entry!r} failed ({returncode}): {stderr.splitlines()[-1] if stderr else 'no output'}")
    return elapsed


def logged_sps(workdir: str, cumulative: bool = False) -> dict:
    """{window end step: [the steps/s of each run folder under workdir/runs over the 1000 steps before it]}.

    Our scripts log charts/SPS per 1000-step window (one folder per seed, each with its process's rate). Other
    scripts, CleanRL's, log charts/SPS since their loop started (cumulative=True): a window's rate is then read
    from the events' wall-clock times, 1000 / (time(end) - time(end - 1000)), which the integer SPS does not blur."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    windows = {}
    runs_dir = os.path.join(workdir, "runs")
    folders = sorted(root for root, _, files in os.walk(runs_dir) if any(f.startswith("events.out.tfevents") for f in files))
    for folder in folders:  # nested too: CleanRL names a run after its env id, "/" included
        acc = EventAccumulator(folder, size_guidance={"scalars": 0})
        acc.Reload()
        events = acc.Scalars("charts/SPS") if "charts/SPS" in acc.Tags()["scalars"] else []
        if not cumulative:
            for event in events:
                windows.setdefault(event.step + 1, []).append(event.value)
            continue
        seconds = {e.step: e.wall_time for e in events if e.step % 1000 == 0}
        for step, t in sorted(seconds.items()):
            if step + 1000 in seconds and seconds[step + 1000] > t:
                windows.setdefault(step + 1000, []).append(1000 / (seconds[step + 1000] - t))
    return windows


def window_run(entry: str, args, workdir: str) -> tuple[list, float]:
    """One run of L + T steps; [(window end, steps/s of a process, agent-steps/s of all its seeds)] for the timed
    windows, and the wall time. A process's seeds all log its rate, so the agent-steps/s are the sum over folders.
    Our scripts are recognised by their short names (td3, oparl, ...); any other entry is read as CleanRL's."""
    ours = command_of(copies_of(entry)[1])[1]
    rundir = tempfile.mkdtemp(dir=workdir)
    # CleanRL's loop logs step s only if it runs s + 1 steps, and only steps after learning starts
    steps = args.learning_starts + args.steps + (0 if ours else 1)
    took = timed_run(entry, args.env_id, steps, args.learning_starts, args.threads, rundir, args.cuda)
    timed = timed_windows(logged_sps(rundir, cumulative=not ours), args.learning_starts + args.warmup, agents_of(entry))
    if not timed:
        sys.exit(f"error: {entry!r} logged no timed window of charts/SPS (see --window's help)")
    return timed, took


def timed_windows(windows: dict, first: int, seeds: int) -> list:
    """[(window end, steps/s of the process, agent-steps/s of all its seeds)] of the windows {end: [steps/s of each
    seed's folder]} that start at step `first` or later and that every one of the process's seeds logged."""
    timed = []
    for end, values in sorted(windows.items()):
        if end - 1000 >= first and len(values) == seeds:
            timed.append((end, statistics.mean(values), sum(values)))
    return timed


def summary(sps: dict, baseline: str) -> list:
    """[(entry, median steps/s, lowest, highest, median / the baseline's median, median agent-steps/s)]."""
    reference = statistics.median(sps[baseline])
    rows = []
    for entry, values in sps.items():
        median = statistics.median(values)
        rows.append((entry, median, min(values), max(values), median / reference, median * agents_of(entry)))
    return rows


CSV_FIELDS = [
    "entry",
    "label",
    "env_id",
    "device",
    "copies",
    "seeds_per_copy",
    "repeat",
    "window_end",
    "steps_per_s",
    "agent_steps_per_s",
    "wall_s",
]


def write_rows(path: str, entry: str, args, device: str, rows: list):
    """Appends rows (repeat, window end or "", steps/s of a process, agent-steps/s, wall seconds of the run) to the CSV."""
    import csv

    copies = copies_of(entry)[0]
    new = not os.path.exists(path) or os.path.getsize(path) == 0
    with open(path, "a", newline="") as f:
        writer = csv.writer(f)
        if new:
            writer.writerow(CSV_FIELDS)
        for repeat, end, process, agents, took in rows:
            writer.writerow(
                [
                    entry,
                    args.label,
                    args.env_id,
                    device,
                    copies,
                    agents_of(entry) // copies,
                    repeat,
                    end,
                    f"{process:.2f}",
                    f"{agents:.1f}",
                    f"{took:.1f}",
                ]
            )


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def gpu_name() -> str:
    """The GPU's name: $GPU_NAME if set (tools/speed/gpu_common.sh asks nvidia-smi once for all its steps), else asked in a
    child process (a few seconds: a CUDA context held here would sit beside every timed run)."""
    if os.environ.get("GPU_NAME"):
        return os.environ["GPU_NAME"]
    ask = "import torch; print(torch.cuda.get_device_name() if torch.cuda.is_available() else 'no GPU found')"
    result = subprocess.run([sys.executable, "-c", ask], capture_output=True, text=True, check=False)
    return result.stdout.strip() or "no GPU found"


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
    parser.add_argument(
        "--window",
        action="store_true",
        help="one run of L + T steps per entry and repeat, timed by the charts/SPS of its 1000-step windows",
    )
    parser.add_argument("--warmup", type=int, default=500, help="with --window: training steps before the first timed window")
    parser.add_argument("--csv", default=None, help="append one row per timed run (--window: per window) to this CSV")
    parser.add_argument(
        "--label", default="", help="written in the CSV's label column: what the command line does not say (e.g. mps)"
    )
    args = parser.parse_args(argv)
    for name, value in [
        ("--steps", args.steps),
        ("--repeats", args.repeats),
        ("--threads", args.threads),
        ("--learning-starts", args.learning_starts),
    ]:
        if value <= 0:
            parser.error(f"{name} must be > 0, got {value}")
    if args.warmup < 0:
        parser.error(f"--warmup must be >= 0, got {args.warmup}")
    first_window = -(-(args.learning_starts + args.warmup) // 1000) * 1000  # windows are steps [1000 k, 1000 (k + 1))
    if args.window and first_window + 1000 > args.learning_starts + args.steps:
        parser.error(
            f"--window times 1000-step windows from step {first_window} on (--learning-starts + --warmup, rounded up): "
            f"--steps must be >= {first_window + 1000 - args.learning_starts}, got {args.steps}"
        )
    baseline = args.baseline or args.entries[0]
    if baseline not in args.entries:
        parser.error(f"--baseline {baseline!r} is not one of the entries {args.entries}")

    sps = {entry: [] for entry in args.entries}
    device = gpu_name() if args.cuda else cpu_name()
    with tempfile.TemporaryDirectory() as workdir:
        for entry in [] if args.window else args.entries:  # warm-up: file caches, first imports
            took = timed_run(entry, args.env_id, args.learning_starts, args.learning_starts, args.threads, workdir, args.cuda)
            # as each entry ends: a slow entry shows at once, a stuck one by its missing line
            print(f"warm-up {entry}: {took:.1f} s", file=sys.stderr, flush=True)
        for repeat in range(args.repeats):
            for entry in args.entries:
                if args.window:
                    timed, took = window_run(entry, args, workdir)
                    sps[entry] += [process for _, process, _ in timed]
                    rows = [(repeat + 1, end, process, agents, took) for end, process, agents in timed]
                    shown = ", ".join(f"{process:.1f}" for _, process, _ in timed)
                    print(
                        f"repeat {repeat + 1}/{args.repeats} {entry}: {shown} steps/s ({took:.1f} s)",
                        file=sys.stderr,
                        flush=True,
                    )
                else:
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
                    rows = [(repeat + 1, "", sps[entry][-1], sps[entry][-1] * agents_of(entry), long)]
                    print(
                        f"repeat {repeat + 1}/{args.repeats} {entry}: {sps[entry][-1]:.1f} steps/s",
                        file=sys.stderr,
                        flush=True,
                    )
                if args.csv:
                    write_rows(args.csv, entry, args, device, rows)

    how = (
        f"median of the 1000-step windows from step {first_window} on, {args.repeats} run(s) each"
        if args.window
        else f"median of {args.repeats}"
    )
    print(
        f"\n{args.env_id}, {args.threads} thread(s), {args.steps} training steps after {args.learning_starts} random ones, {how}; {device}\n"
    )
    print(f"| entry | steps/s (median) | range | vs `{baseline}` | agent-steps/s (steps/s x seeds at once) |")
    print("|---|---|---|---|---|")
    for entry, median, lowest, highest, ratio, agents in summary(sps, baseline):
        print(f"| `{entry}` | {median:.1f} | {lowest:.1f}-{highest:.1f} | {ratio:.2f}x | {agents:.1f} |")


if __name__ == "__main__":
    main()
