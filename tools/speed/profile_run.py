"""Where the time of a real training run goes, by phase of the training step.

Samples a whole run with py-spy (`pip install py-spy`) and attributes every sample to the innermost
phase it is in: replay sampling, the TD target, the rest of the critic update, the actor update(s),
the entropy update, target-network updates, acting, the environment step, storing the transition,
evaluation, logging, and start-up. An update is its loss function and the optimizer step on that loss
(the script's `optimize(loss, "name", ...)`, told apart by the line of the script that calls it). For example:

    python tools/speed/profile_run.py td3 --env-id Hopper-v4 --learning-starts 1000 --total-timesteps 6000
    python tools/speed/profile_run.py oparl --env-id Hopper-v4 --learning-starts 1000 --total-timesteps 4000

Everything after the script's short name is passed to it; the run goes to a throw-away folder, with
one torch thread unless OMP_NUM_THREADS says otherwise.
"""

import ast
import collections
import functools
import os
import shutil
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCRIPT = "_continuous_action.py"  # how the scripts' file names end
# (phase, function names as py-spy reports them); the innermost match in a stack wins. `optimize "qf_loss"`: the
# script's optimize(loss, "qf_loss", ...), the optimizer step of that loss (see script_calls)
PHASES = [
    ("replay sampling", {"ReplayBuffer.sample"}),
    ("TD target", {"td_target"}),
    ("critic update (forward, backward, Adam)", {"critic_loss", 'optimize "qf_loss"'}),
    ("actor update(s)", {"policy_loss", "policy_losses", 'optimize "actor_loss"'}),
    ("entropy (alpha) update", {"alpha_loss_fn", 'optimize "alpha_loss"'}),
    ("target networks (Polyak)", {"soft_update"}),
    ("evaluation", {"evaluate"}),
    # acting, below torch.no_grad's decorate_context; random actions, below a list comprehension's frame
    ("acting (actor forward, noise)", {"noisy_action", "optimistic_action", "Box.sample"}),
    ("storing the transition", {"ReplayBuffer.add"}),
    (
        "environment step",
        {"EpisodeRecord.step", "Wrapper.step", "TimeLimit.step", "OrderEnforcing.step", "PassiveEnvChecker.step"},
    ),
    (
        "environment reset",
        {"EpisodeRecord.reset", "Wrapper.reset", "TimeLimit.reset", "OrderEnforcing.reset", "PassiveEnvChecker.reset"},
    ),
    ("checkpoints", {"write_checkpoint", "write_checkpoints", "snapshot", "split_seeds"}),
    ("--cudagraphs: graph replay and its input copies", {"CudaGraph.__call__"}),  # warm-up calls: the phases above
    ("logging (TensorBoard)", {"SummaryWriter.add_scalar", "SummaryWriter.add_text"}),
]
STARTUP = {  # directly below main: building the run, its envs, networks, optimizers, buffer and logs
    "Run.__init__",
    "Run.start",
    "SeedEnvs.__init__",
    "stack_seeds",
    "Optimizer.__init__",
    "Adam.__init__",
    "make_env",
    "SummaryWriter.__init__",
    "Module.to",
    "QEnsemble.__init__",
    "Actor.__init__",
    "ReplayBuffer.__init__",
}


def location(frame: str) -> tuple:
    """(file name, line) of a py-spy frame "name (path/file.py:line)"."""
    path, _, line = frame.rpartition(" (")[2].rstrip(")").rpartition(":")
    return os.path.basename(path), int(line) if line.isdigit() else None


PER_SEED = {"per_seed", "per_seed.<locals>.run", "to_device"}  # a per-seed call's frames, and its observations' copy


@functools.cache
def script_calls() -> dict:
    """{(script file, line): what the line calls}, for the frames py-spy reports below it: for optimize(loss,
    "qf_loss", ...), 'optimize "qf_loss"' (an optimizer step, named by its loss); for per_seed(fn)(...), fn's name
    (the frames of rl_utils.per_seed that run fn for every seed are fn's, as is acting's copy to the device)."""
    calls = {}
    for file in sorted(f for f in os.listdir(REPO) if f.endswith(SCRIPT)):
        with open(os.path.join(REPO, file)) as f:
            tree = ast.parse(f.read())
        for node in ast.walk(tree):
            func = node.func if isinstance(node, ast.Call) else None
            if isinstance(func, ast.Name) and func.id == "optimize" and len(node.args) > 1:
                name = f'optimize "{ast.literal_eval(node.args[1])}"'
            elif isinstance(func, ast.Call) and isinstance(func.func, ast.Name) and func.func.id == "per_seed":
                name = ast.unparse(func.args[0])
            else:
                continue
            calls.update({(file, line): name for line in range(node.lineno, node.end_lineno + 1)})
    return calls


def phase_of(stack: list, calls: dict | None = None) -> str:
    """The phase of a sample's stack (py-spy's frames, outermost first); `calls`: script_calls()'s."""
    calls = script_calls() if calls is None else calls
    names = [frame.split(" (")[0] for frame in stack]
    for k in range(1, len(names)):  # a frame named by what its caller's line calls
        call = calls.get(location(stack[k - 1]), "")
        optimizes = call.startswith("optimize ")
        if (names[k] == "optimize" and optimizes) or (names[k] in PER_SEED and call and not optimizes):
            names[k] = call
    mains = [k for k, (name, frame) in enumerate(zip(names, stack)) if name == "main" and SCRIPT + ":" in frame]
    if not mains:
        return "start-up and imports"
    below_main = names[mains[-1] + 1 :]
    if below_main and below_main[0] in STARTUP:
        return "start-up and imports"
    for name in reversed(below_main):  # innermost first
        for phase, phase_names in PHASES:
            if name in phase_names:
                return phase
    return "rest of the loop (Python, conversions, progress bar)"


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    scripts = sorted(f.removesuffix(SCRIPT) for f in os.listdir(REPO) if f.endswith(SCRIPT))
    if argv and argv[0] in {"-h", "--help"}:
        sys.exit(__doc__)
    if not argv or argv[0] not in scripts:
        sys.exit(f"error: usage: python tools/speed/profile_run.py {{{','.join(scripts)}}} [script flags]")
    if shutil.which("py-spy") is None:
        sys.exit("error: py-spy not found: pip install py-spy")
    script = os.path.join(REPO, f"{argv[0]}_continuous_action.py")
    with tempfile.TemporaryDirectory() as workdir:
        raw = os.path.join(workdir, "profile.txt")
        env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
        cmd = [
            "py-spy",
            "record",
            "--format",
            "raw",
            "--rate",
            "200",
            "--output",
            raw,
            "--",
            sys.executable,
            script,
            *argv[1:],
            "--run-name",
            "profile",
        ]
        result = subprocess.run(cmd, cwd=workdir, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if result.returncode != 0:
            sys.exit(
                f"error: the profiled run failed: {result.stderr.strip().splitlines()[-1] if result.stderr.strip() else result.returncode}"
            )
        samples = collections.Counter()
        with open(raw) as f:
            for line in f:
                stack, count = line.rstrip().rsplit(" ", 1)
                frames = stack.split(";")
                if any(f.startswith(("_bootstrap", "Thread.run", "_AsyncWriterThread", "TMonitor")) for f in frames):
                    continue  # idle background threads (TensorBoard's writer, tqdm's monitor)
                samples[phase_of(frames)] += int(count)
    total = sum(samples.values())
    training = total - samples["start-up and imports"] - samples["evaluation"]
    print(f"{argv[0]} {' '.join(argv[1:])}: {total} samples at 200/s")
    print("| phase | share of all samples | share of the training loop |")
    print("|---|---|---|")
    for phase in [p for p, _ in PHASES] + [
        "rest of the loop (Python, conversions, progress bar)",
        "start-up and imports",
    ]:
        if samples[phase]:
            in_loop = "" if phase in ("start-up and imports", "evaluation") else f"{100 * samples[phase] / training:.1f}%"
            print(f"| {phase} | {100 * samples[phase] / total:.1f}% | {in_loop} |")


if __name__ == "__main__":
    main()
