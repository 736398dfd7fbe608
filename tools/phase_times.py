"""Where a training step's time goes, by phase, timed by the clock: on a GPU as on a CPU.

Runs one of the off-policy scripts (td3, sac, oparl, redq) in this process with its phases wrapped in timers:
acting, the environment step, storing the transition, replay sampling, the update (under --cudagraphs: the graph's
replay and its input copies; eager: the TD target, the critic, actor and alpha updates and the target networks),
logging, checkpoints and evaluation. On a GPU every timer synchronises the device when its phase starts and ends,
so the kernels a phase launched are charged to it: without that, a graph's replay returns at once and its GPU time
shows up as waiting in the next step's acting (which is all py-spy, tools/profile_run.py, can see). The
synchronisations cost a few microseconds each and remove the little overlap the loop has; the table says how
many a step makes. Time spent inside a phase's inner phases is charged to the inner ones (each row is exclusive);
evaluation is charged whole. The first --warmup-updates training steps (the first updates and, with --cudagraphs,
the recordings) are not timed. For example:

    python tools/phase_times.py td3 --env-id Hopper-v4 --cudagraphs --learning-starts 500 --total-timesteps 3000
    python tools/phase_times.py oparl --env-id Hopper-v4 --learning-starts 500 --total-timesteps 1500 --csv phases.csv

Everything after the script's short name (and this tool's own flags) is passed to the script; the run goes to a
throw-away folder, with one torch thread unless OMP_NUM_THREADS says otherwise.
"""

import collections
import csv
import functools
import importlib.util
import os
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = ("td3", "sac", "oparl", "redq")  # the scripts with a replay buffer
# (phase, where: a class name of the script or None for the module, the function's name); absent ones are skipped
PHASES = [
    ("acting", None, "noisy_action"),
    ("acting", None, "optimistic_action"),
    ("storing the transition", "ReplayBuffer", "add"),
    ("replay sampling", "ReplayBuffer", "sample"),
    ("update: graph replay and input copies", "CudaGraph", "__call__"),
    ("update: TD target", None, "td_target"),
    ("update: critic", None, "update_critic"),
    ("update: actor(s)", None, "update_actor"),
    ("update: actor(s)", None, "update_actors"),
    ("update: alpha", None, "update_alpha"),
    ("update: target networks", None, "soft_update"),
    ("logging", None, "log_scalars"),
    ("checkpoints", None, "write_checkpoints"),
    ("evaluation", None, "evaluate"),
]
ENV_PHASES = [("environment step", "step"), ("environment reset", "reset")]
WHOLE = "evaluation"  # charged whole: the environment steps and actions inside it are not split out
LOOP_ORDER = (
    ["acting"] + [p for p, _ in ENV_PHASES] + ["storing the transition", "replay sampling"]
)  # rows, in the loop's order
ORDER = list(dict.fromkeys(LOOP_ORDER + [p for p, _, _ in PHASES]))


class PhaseTimer:
    """Wraps functions in exclusive wall-clock timers: a call's time minus its timed inner calls' goes to its phase.
    `sync` runs at every phase's start and end (torch.cuda.synchronize on a GPU)."""

    def __init__(self, sync=lambda: None):
        self.sync = sync
        self.seconds, self.calls = collections.Counter(), collections.Counter()
        self.stack = []  # [phase, seconds of timed inner calls] of the calls in progress
        self.syncs = 0

    def reset(self):
        self.seconds.clear()
        self.calls.clear()
        self.syncs = 0

    def wrap(self, phase: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if self.stack and self.stack[-1][0] == WHOLE:
                return fn(*args, **kwargs)
            self.sync()
            self.syncs += 1
            start = time.perf_counter()
            self.stack.append([phase, 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                self.sync()
                self.syncs += 1
                elapsed = time.perf_counter() - start
                _, inner = self.stack.pop()
                self.seconds[phase] += elapsed - inner
                self.calls[phase] += 1
                if self.stack:
                    self.stack[-1][1] += elapsed

        return timed


def cuda_sync():
    import torch

    if torch.cuda.is_available() and torch.cuda.is_initialized() and not torch.cuda.is_current_stream_capturing():
        torch.cuda.synchronize()  # (a sync inside a graph's recording would end it)


def instrument(module, timer: PhaseTimer, warmup_updates: int) -> dict:
    """Wraps the script's phases in the timer; the clock starts (and every count resets) when the first training
    step after the first warmup_updates starts, at its acting. Returns the clock: its start and the timed steps."""
    clock = {"start": None, "steps": 0, "samples": 0}
    for phase, owner, name in PHASES:
        target = module if owner is None else getattr(module, owner, None)
        if target is not None and hasattr(target, name):
            setattr(target, name, timer.wrap(phase, getattr(target, name)))
    for name in ("noisy_action", "optimistic_action"):  # the first of a training step's phases
        if hasattr(module, name):
            setattr(module, name, start_clock_before(getattr(module, name), timer, clock, warmup_updates))
    sample = module.ReplayBuffer.sample

    @functools.wraps(sample)
    def counted_sample(*args, **kwargs):  # one call per training step
        clock["samples"] += 1
        if clock["start"] is not None:
            clock["steps"] += 1
        return sample(*args, **kwargs)

    module.ReplayBuffer.sample = counted_sample
    make_env, wrapped = module.make_env, set()

    @functools.wraps(make_env)
    def timed_make_env(*args, **kwargs):
        env = make_env(*args, **kwargs)
        cls = type(env)
        if cls not in wrapped:  # the class of the outermost wrapper, once
            wrapped.add(cls)
            for phase, name in ENV_PHASES:
                setattr(cls, name, timer.wrap(phase, getattr(cls, name)))
        return env

    module.make_env = timed_make_env
    return clock


def start_clock_before(act, timer: PhaseTimer, clock: dict, warmup_updates: int):
    """act, which first resets the timer and starts the clock when warmup_updates training steps have passed."""

    @functools.wraps(act)
    def acting(*args, **kwargs):
        if clock["start"] is None and clock["samples"] >= warmup_updates:
            timer.reset()
            clock["start"] = time.perf_counter()
        return act(*args, **kwargs)

    return acting


def table(timer: PhaseTimer, clock: dict, wall: float) -> list:
    """Rows (phase, ms per training step, share of the loop's time, calls per step); the loop's time excludes
    evaluation, and "rest of the loop" is what no phase holds (Python, conversions, the progress bar)."""
    steps = clock["steps"]
    loop = wall - timer.seconds[WHOLE]
    rows = [(p, timer.seconds[p], timer.calls[p]) for p in ORDER if p != WHOLE and timer.calls[p]]
    rows.append(("rest of the loop", loop - sum(s for _, s, _ in rows), steps))
    return [(p, 1000 * s / steps, 100 * s / loop, c / steps) for p, s, c in rows]


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in {"-h", "--help"}:
        sys.exit(__doc__)
    own = {"--warmup-updates": 200, "--csv": None}
    script_argv = []
    rest = argv[1:]
    while rest:
        word = rest.pop(0)
        if word in own:
            if not rest:
                sys.exit(f"error: {word} needs a value")
            own[word] = rest.pop(0)
        else:
            script_argv.append(word)
    if argv[0] not in SCRIPTS:
        sys.exit(
            f"error: usage: python tools/phase_times.py {{{','.join(SCRIPTS)}}} [--warmup-updates N] [--csv PATH] [flags]"
        )
    try:
        warmup = int(own["--warmup-updates"])
        assert warmup >= 0
    except (ValueError, AssertionError):
        sys.exit(f"error: --warmup-updates must be an integer >= 0, got {own['--warmup-updates']}")
    csv_path = os.path.abspath(own["--csv"]) if own["--csv"] else None
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.path.insert(0, REPO)
    name = f"{argv[0]}_continuous_action"
    spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    import torch

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    timer = PhaseTimer(cuda_sync)
    clock = instrument(module, timer, warmup)
    args = module.parse_args(script_argv)
    with tempfile.TemporaryDirectory() as workdir:
        here = os.getcwd()
        os.chdir(workdir)
        try:
            module.main(args)
        finally:
            os.chdir(here)
    wall = time.perf_counter() - clock["start"] if clock["start"] is not None else 0.0
    if not clock["steps"]:
        sys.exit(f"error: no training step after the {warmup} warm-up ones: give more --total-timesteps")
    rows = table(timer, clock, wall)
    device = torch.cuda.get_device_name() if torch.cuda.is_initialized() else "cpu"
    per_step = sum(ms for _, ms, _, _ in rows)
    flags = " ".join(script_argv)
    print(f"{argv[0]} {flags}: {clock['steps']} training steps timed on {device}, {per_step:.3f} ms a step")
    print(f"({1000 / per_step:.1f} steps/s with {timer.syncs / clock['steps']:.1f} timer synchronisations a step)")
    print("| phase | ms per training step | share of the loop | calls per step |")
    print("|---|---|---|---|")
    for phase, ms, share, calls in rows:
        print(f"| {phase} | {ms:.3f} | {share:.1f}% | {calls:.2f} |")
    if timer.calls[WHOLE]:
        print(f"evaluation (not in the loop's time): {timer.seconds[WHOLE]:.2f} s in {timer.calls[WHOLE]} calls")
    if csv_path:
        new = not os.path.exists(csv_path)
        with open(csv_path, "a", newline="") as f:
            writer = csv.writer(f)
            if new:
                writer.writerow(
                    ["script", "flags", "device", "timed_steps", "phase", "ms_per_step", "share", "calls_per_step"]
                )
            for phase, ms, share, calls in rows:
                writer.writerow([argv[0], flags, device, clock["steps"], phase, f"{ms:.4f}", f"{share:.2f}", f"{calls:.3f}"])


if __name__ == "__main__":
    main()
