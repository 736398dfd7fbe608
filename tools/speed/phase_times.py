"""Where a training step's time goes, by phase, timed by the clock: on a GPU as on a CPU.

Runs one of the off-policy scripts (td3, sac, oparl, redq) in this process with its phases wrapped in timers:
acting, the environment step, storing the transition, replay sampling, the update (under --cudagraphs: the graph's
replay and its input copies, TD3's two graphs (with and without the actor) averaged, REDQ's one graph of its 20
critic updates, actor and alpha; eager: the TD target, the critic, actor and alpha updates (each its loss and its
optimizer step), the target networks), logging, checkpoints and evaluation. Acting is the copy of the observations
to the device and the actor's action. On a GPU every timer synchronises the device when its phase starts and ends,
so the kernels a phase launched are charged to it: without that, a graph's replay returns at once and its GPU time
shows up as waiting in the next step's acting (which is all py-spy, tools/speed/profile_run.py, can see). The
synchronisations remove what little overlap of host and GPU the loop has and cost a few microseconds each (the
tool prints how many a step made and what an idle one costs), so the total is a synchronised step, slower than
tools/speed/throughput.py's rates: compare phases within a table, and rates with throughput.py. --no-sync times the
same phases without synchronising (the host's view); with --no-sync --blocking-copy acting copies the
observations to the GPU as it did before commit e4d8b37 (from pageable memory, which waits for the GPU to finish
what is queued, a replaying update included), so that the two can be compared on one machine: compare their whole
step, since the wait moves between phases (acting's copy, or the action's copy back in "rest of the loop").
Time inside a phase's inner phases is charged to the inner ones (each row is exclusive); evaluation is charged
whole; "rest of the loop" is what no phase holds: Python, the progress bar, copying the actions to the host,
and any GPU work left unsynchronised by then. The first
--warmup-updates training steps (the first updates and, with --cudagraphs, the recordings) are not timed, nor is
anything from the last evaluation on. For example:

    python tools/speed/phase_times.py td3 --env-id Hopper-v4 --cudagraphs --learning-starts 500 --total-timesteps 3000
    python tools/speed/phase_times.py oparl --env-id Hopper-v4 --learning-starts 500 --total-timesteps 1500 --csv phases.csv

Everything after the script's short name (and this tool's own flags: --warmup-updates N, --csv PATH, --no-sync,
--blocking-copy)
is passed to the script; the run goes to a throw-away folder, with one torch thread unless OMP_NUM_THREADS says
otherwise. `python tools/speed/phase_times.py --summary phases.csv [more.csv ...]` reads what --csv wrote and prints each
run's whole step (the sum of its phases) by script and flags, their mean, and, where a script has runs with and
without --blocking-copy under the same flags, the difference of the means.
"""

import collections
import csv
import functools
import importlib.util
import os
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCRIPTS = ("td3", "sac", "oparl", "redq")  # the scripts with a replay buffer
# (phase, where, the function's name); absent ones are skipped. Where: None for the script's module, whose main looks
# these names up among its globals (replaced there, they are what main calls), or the rl_utils module ("module") or
# class ("module:Class") that defines them (a method replaced in its class is every script's)
PHASES = [
    ("acting", None, "to_device"),  # the observations' copy to the device, before the actor's action
    ("acting", None, "noisy_action"),
    ("acting", None, "optimistic_action"),
    ("storing the transition", "rl_utils.buffers:ReplayBuffer", "add"),
    ("replay sampling", "rl_utils.buffers:ReplayBuffer", "sample"),
    ("update: graph replay and input copies", "rl_utils.gpu:CudaGraph", "__call__"),
    ("update: TD target", None, "td_target"),
    ("update: critic", None, "critic_loss"),
    ("update: actor(s)", None, "policy_loss"),
    ("update: actor(s)", None, "policy_losses"),
    ("update: alpha", None, "alpha_loss_fn"),
    ("update: target networks", None, "soft_update"),
    ("logging", "rl_utils.run:Run", "log"),
    ("checkpoints", "rl_utils.checkpoints", "write_checkpoints"),
    ("checkpoints", "rl_utils.checkpoints", "snapshot"),  # the state a checkpoint holds, taken before it is written
    ("checkpoints", "rl_utils.seeds", "split_seeds"),
    ("evaluation", None, "evaluate"),
]
# a loss's optimizer step, the script's optimize(loss, name, *optimizers), is charged to that loss's update, by name
OPTIMIZED = {"qf_loss": "update: critic", "actor_loss": "update: actor(s)", "alpha_loss": "update: alpha"}
# functions that are part of a phase whose other function counts its calls: acting's copy, the optimizer steps
UNCOUNTED = {"to_device", "optimize"}
ENV_PHASES = [("environment step", "step"), ("environment reset", "reset")]
WHOLE = "evaluation"  # charged whole: the environment steps and actions inside it are not split out
# the table's rows: the loop's phases in the loop's order, then the update's parts and the rest
ORDER = list(dict.fromkeys(["acting", "environment step", "environment reset"] + [p for p, _, _ in PHASES]))


class PhaseTimer:
    """Wraps functions in exclusive wall-clock timers: a call's time minus its timed inner calls' goes to its phase.
    `sync` runs at every phase's start and end (torch.cuda.synchronize on a GPU) and says whether it synchronised;
    `syncs` counts the synchronisations made."""

    def __init__(self, sync=lambda: False):
        self.sync = sync
        self.seconds, self.calls = collections.Counter(), collections.Counter()
        self.stack = []  # [phase, seconds of timed inner calls] of the calls in progress
        self.syncs = 0

    def reset(self):
        self.seconds.clear()
        self.calls.clear()
        self.syncs = 0

    def wrap(self, phase: str, fn, count: bool = True):
        """fn, timed as part of `phase`; each call counts as one of the phase's calls if `count`."""

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if self.stack and self.stack[-1][0] == WHOLE:
                return fn(*args, **kwargs)
            self.syncs += bool(self.sync())  # before the clock: it waits for work of the phases before
            start = time.perf_counter()
            self.stack.append([phase, 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                self.syncs += bool(self.sync())
                elapsed = time.perf_counter() - start
                _, inner = self.stack.pop()
                self.seconds[phase] += elapsed - inner
                self.calls[phase] += count
                if self.stack:
                    self.stack[-1][1] += elapsed

        return timed


def cuda_sync() -> bool:
    import torch

    if torch.cuda.is_available() and torch.cuda.is_initialized() and not torch.cuda.is_current_stream_capturing():
        torch.cuda.synchronize()  # (a sync inside a graph's recording would end it)
        return True
    return False


def idle_sync_cost(repeats: int = 1000) -> float:
    """Seconds one torch.cuda.synchronize() takes with nothing queued."""
    import torch

    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / repeats


def owner_of(module, where):
    """What PHASES' `where` names: the script's module (None), an rl_utils module or one of its classes."""
    if where is None:
        return module
    path, _, cls = where.partition(":")
    owner = importlib.import_module(path)
    return getattr(owner, cls, None) if cls else owner


def instrument(module, timer: PhaseTimer, warmup_updates: int) -> dict:
    """Wraps the script's phases in the timer; the clock starts (and every count resets) when the first training
    step after the first warmup_updates starts, at its acting, and every evaluation that starts after that marks
    where the timed loop may end (the last one's mark is the run's). Returns the clock.

    The script calls its acting and loss functions through rl_utils.per_seed (for several seeds, torch.func.vmap over
    them): `per_seed(fn)` of a timed fn is timed whole, so that a phase is charged what running it for every seed
    costs, as when the functions took every seed's tensors themselves."""
    clock = {"start": None, "steps": 0, "samples": 0, "mark": None}
    timed = {}  # a function as the script now finds it -> (how it was wrapped, the function itself)
    for phase, where, name in PHASES:
        target = owner_of(module, where)
        if target is None or not hasattr(target, name):
            continue

        def wrapped(fn, phase=phase, count=name not in UNCOUNTED, acting=phase == "acting" and where is None):
            fn = timer.wrap(phase, fn, count=count)
            # acting is the first of a training step's phases
            return start_clock_before(fn, timer, clock, warmup_updates) if acting else fn

        original = getattr(target, name)
        setattr(target, name, wrapped(original))
        timed[getattr(target, name)] = (wrapped, original)
    per_seed = getattr(module, "per_seed", None)
    if per_seed is not None:

        @functools.wraps(per_seed)
        def timed_per_seed(fn):
            if fn in timed:
                wrapped, original = timed[fn]
                return wrapped(per_seed(original))
            return per_seed(fn)

        module.per_seed = timed_per_seed
    optimize = getattr(module, "optimize", None)
    if optimize is not None:
        steps = {loss: timer.wrap(phase, optimize, count=False) for loss, phase in OPTIMIZED.items()}

        @functools.wraps(optimize)
        def timed_optimize(loss, name, *optimizers):  # the step of an unnamed loss is not timed
            return steps.get(name, optimize)(loss, name, *optimizers)

        module.optimize = timed_optimize
    from rl_utils.buffers import ReplayBuffer

    sample = ReplayBuffer.sample

    @functools.wraps(sample)
    def counted_sample(*args, **kwargs):  # one call per training step
        clock["samples"] += 1
        if clock["start"] is not None:
            clock["steps"] += 1
        return sample(*args, **kwargs)

    ReplayBuffer.sample = counted_sample
    evaluate = module.evaluate

    @functools.wraps(evaluate)
    def marked_evaluate(*args, **kwargs):
        if clock["start"] is not None:
            clock["mark"] = snapshot(timer, clock)
        return evaluate(*args, **kwargs)

    module.evaluate = marked_evaluate
    import rl_utils.envs

    make_env, env_classes = rl_utils.envs.make_env, set()

    @functools.wraps(make_env)
    def timed_make_env(*args, **kwargs):
        env = make_env(*args, **kwargs)
        cls = type(env)
        if cls not in env_classes:  # the class of the outermost wrapper, once
            env_classes.add(cls)
            for phase, name in ENV_PHASES:
                setattr(cls, name, timer.wrap(phase, getattr(cls, name)))
        return env

    rl_utils.envs.make_env = timed_make_env  # where SeedEnvs looks it up
    if hasattr(module, "make_env"):
        module.make_env = timed_make_env
    return clock


def start_clock_before(act, timer: PhaseTimer, clock: dict, warmup_updates: int):
    """act, which first resets the timer and starts the clock when warmup_updates training steps have passed (at the
    first of acting's functions a step calls, outside every phase: the evaluations' copies to the device are not
    acting)."""

    @functools.wraps(act)
    def acting(*args, **kwargs):
        if clock["start"] is None and clock["samples"] >= warmup_updates and not timer.stack:
            timer.reset()
            clock["start"] = time.perf_counter()
        return act(*args, **kwargs)

    return acting


def snapshot(timer: PhaseTimer, clock: dict) -> dict:
    """The timed loop so far: its wall time, the timer's seconds, calls and synchronisations, the training steps."""
    wall = time.perf_counter() - clock["start"]
    return {
        "wall": wall,
        "seconds": timer.seconds.copy(),
        "calls": timer.calls.copy(),
        "syncs": timer.syncs,
        "steps": clock["steps"],
    }


LAST = "rest of the loop"  # what no phase holds: the last row of every table, and of every run that --csv writes
BLOCKING = "(--blocking-copy)"  # what a --blocking-copy run's flags end with


def with_blocking(flags: str) -> str:
    """A run's flags as a --blocking-copy run of them is labelled."""
    return f"{flags} {BLOCKING}" if flags else BLOCKING


def table(mark: dict) -> list:
    """Rows (phase, ms per training step, share of the loop's time, calls per step) of a snapshot; the loop's time
    excludes the evaluations in it, and "rest of the loop" is what no phase holds."""
    steps, seconds, calls = mark["steps"], mark["seconds"], mark["calls"]
    loop = mark["wall"] - seconds[WHOLE]
    rows = [(p, seconds[p], calls[p]) for p in ORDER if p != WHOLE and calls[p]]
    rows.append((LAST, loop - sum(s for _, s, _ in rows), steps))
    return [(p, 1000 * s / steps, 100 * s / loop, c / steps) for p, s, c in rows]


def parse(argv: list) -> tuple:
    """(script, warm-up updates, CSV path or None, whether to synchronise, whether acting's copy blocks, the
    script's own flags)."""
    if not argv or argv[0] in {"-h", "--help"}:
        sys.exit(__doc__)
    if argv[0] not in SCRIPTS:
        sys.exit(
            f"error: usage: python tools/speed/phase_times.py {{{','.join(SCRIPTS)}}} [--warmup-updates N] [--csv PATH] "
            "[--no-sync] [--blocking-copy] [flags]"
        )
    own, sync, blocking, script_argv, rest = {"--warmup-updates": "200", "--csv": None}, True, False, [], argv[1:]
    while rest:
        word = rest.pop(0)
        if word == "--no-sync":
            sync = False
        elif word == "--blocking-copy":
            blocking = True
        elif word in own:
            if not rest:
                sys.exit(f"error: {word} needs a value")
            own[word] = rest.pop(0)
        else:
            script_argv.append(word)
    if blocking and sync:
        sys.exit("error: --blocking-copy changes only what the host waits for: give --no-sync with it")
    warmup = own["--warmup-updates"]
    if not warmup.isdigit():
        sys.exit(f"error: --warmup-updates must be an integer >= 0, got {warmup}")
    return argv[0], int(warmup), os.path.abspath(own["--csv"]) if own["--csv"] else None, sync, blocking, script_argv


def runs_of(paths: list) -> list:
    """The runs in phases CSVs, in order, as ((script, flags, device, threads, synchronised, timed steps), ms a whole
    step): a run's rows are consecutive within one file and end with its "rest of the loop" row."""
    runs = []
    for path in paths:
        try:
            with open(path, newline="") as f:
                rows = list(csv.DictReader(f))
        except (OSError, UnicodeDecodeError) as e:
            sys.exit(f"error: cannot read {path}: {getattr(e, 'strerror', None) or e}")
        if rows and not set(CSV_FIELDS) <= set(rows[0]):
            sys.exit(f"error: {path} is not a CSV that tools/speed/phase_times.py --csv wrote")
        run = None
        for line, row in enumerate(rows, start=2):
            key = tuple(row[field] for field in ("script", "flags", "device", "threads", "synchronised", "timed_steps"))
            if run is not None and run[0] != key:
                sys.exit(f"error: {path} line {line}: a run's rows end before its '{LAST}' row (a cut-off run?)")
            try:
                ms = float(row["ms_per_step"])
            except (TypeError, ValueError):
                sys.exit(f"error: {path} line {line}: not a phase row ({row['ms_per_step']!r} ms)")
            run = [key, (run[1] if run else 0.0) + ms]
            if row["phase"] == LAST:
                runs.append(tuple(run))
                run = None
        if run is not None:
            sys.exit(f"error: {path} ends inside a run (no '{LAST}' row): a cut-off run?")
    return runs


def summary(paths: list) -> None:
    """Prints every run's whole step by (script, flags), the mean, and the mean's change from --blocking-copy."""
    groups = collections.defaultdict(list)
    for key, ms in runs_of(paths):
        groups[key].append(ms)
    if not groups:
        sys.exit("error: no rows in " + " ".join(paths))
    print(
        "| script | flags | device | threads | synchronised | timed steps | ms a step, each run | mean | vs --blocking-copy |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    means = {key: sum(values) / len(values) for key, values in groups.items()}
    for (script, flags, *rest), values in groups.items():
        mean, before = means[(script, flags, *rest)], means.get((script, with_blocking(flags), *rest))
        change = "" if before is None else f"{mean - before:+.3f} ({mean / before - 1:+.1%})"
        each = ", ".join(f"{v:.3f}" for v in values)
        print(f"| {' | '.join([script, flags, *rest])} | {each} | {mean:.3f} | {change} |")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--summary"]:
        if len(argv) < 2:
            sys.exit("error: --summary needs the CSV files that --csv wrote")
        return summary(argv[1:])
    script, warmup, csv_path, sync, blocking, script_argv = parse(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.path.insert(0, REPO)
    from rl_utils import parse_args

    name = f"{script}_continuous_action"
    spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    import torch

    if blocking:  # acting's copy of the observations as before commit e4d8b37: from pageable memory, waiting for the GPU
        module.to_device = lambda x, device: torch.as_tensor(x, device=device)
    threads = int(os.environ["OMP_NUM_THREADS"])
    torch.set_num_threads(threads)
    timer = PhaseTimer(cuda_sync) if sync else PhaseTimer()
    clock = instrument(module, timer, warmup)
    args = parse_args(module.Args, getattr(module, "check_args", None), script_argv)  # as the script's __main__
    with tempfile.TemporaryDirectory() as workdir:
        here = os.getcwd()
        os.chdir(workdir)
        try:
            module.main(args)
        finally:
            os.chdir(here)
    mark = clock["mark"] or (snapshot(timer, clock) if clock["start"] is not None else None)
    if mark is None or not mark["steps"]:
        sys.exit(f"error: no training step after the {warmup} warm-up ones: give more --total-timesteps")
    rows = table(mark)
    on_gpu = torch.cuda.is_initialized()
    device = torch.cuda.get_device_name() if on_gpu else "cpu"
    flags = with_blocking(" ".join(script_argv)) if blocking else " ".join(script_argv)  # the CSV rows' label
    per_step, steps = sum(ms for _, ms, _, _ in rows), mark["steps"]
    how = "synchronised at every phase's start and end" if sync and on_gpu else "not synchronised"
    print(f"{script} {flags}: {steps} training steps timed on {device} ({threads} thread(s)), {per_step:.3f} ms a step")
    print(f"({how}: {mark['syncs'] / steps:.1f} device synchronisations a step", end="")
    print(f", an idle one {idle_sync_cost() * 1e6:.1f} us)" if on_gpu else ")")
    print("| phase | ms per training step | share of the loop | calls per step |")
    print("|---|---|---|---|")
    for phase, ms, share, calls in rows:
        print(f"| {phase} | {ms:.3f} | {share:.1f}% | {calls:.2f} |")
    if mark["calls"][WHOLE]:
        print(f"evaluation (not in the loop's time): {mark['seconds'][WHOLE]:.2f} s in {mark['calls'][WHOLE]} calls")
    if csv_path:
        new = not os.path.exists(csv_path)
        with open(csv_path, "a", newline="") as f:
            writer = csv.writer(f)
            if new:
                writer.writerow(CSV_FIELDS)
            for phase, ms, share, calls in rows:
                values = [script, flags, device, threads, sync and on_gpu, steps, phase, f"{ms:.4f}", f"{share:.2f}"]
                writer.writerow([*values, f"{calls:.3f}"])


CSV_FIELDS = [
    "script",
    "flags",
    "device",
    "threads",
    "synchronised",
    "timed_steps",
    "phase",
    "ms_per_step",
    "share",
    "calls_per_step",
]

if __name__ == "__main__":
    main()
