"""Where the time of a real training run goes, by phase of the training step.

Samples a whole run with py-spy (`pip install py-spy`) and attributes every sample to the innermost
phase it is in: replay sampling, the TD target, the rest of the critic update, the actor update(s),
the entropy update, target-network updates, acting, the environment step, storing the transition,
evaluation, logging, and start-up. For example:

    python tools/profile_run.py td3 --env-id Hopper-v4 --learning-starts 1000 --total-timesteps 6000
    python tools/profile_run.py oparl --env-id Hopper-v4 --learning-starts 1000 --total-timesteps 4000

Everything after the script's short name is passed to it; the run goes to a throw-away folder, with
one torch thread unless OMP_NUM_THREADS says otherwise.
"""

import collections
import os
import shutil
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# (phase, function names as py-spy reports them); the innermost match in a stack wins
PHASES = [
    ("replay sampling", {"ReplayBuffer.sample"}),
    ("TD target", {"td_target"}),
    ("critic update (forward, backward, Adam)", {"update_critic"}),
    ("actor update(s)", {"update_actor", "update_actors"}),
    ("entropy (alpha) update", {"update_alpha"}),
    ("target networks (Polyak)", {"soft_update"}),
    ("evaluation", {"evaluate"}),
    # acting, below torch.no_grad's decorate_context; random actions, below a list comprehension's frame
    ("acting (actor forward, noise)", {"noisy_action", "optimistic_action", "Box.sample"}),
    ("storing the transition", {"ReplayBuffer.add"}),
    ("environment step", {"Wrapper.step", "TimeLimit.step", "OrderEnforcing.step", "PassiveEnvChecker.step"}),
    ("environment reset", {"Wrapper.reset", "TimeLimit.reset", "OrderEnforcing.reset", "PassiveEnvChecker.reset"}),
    ("checkpoints", {"write_checkpoint"}),
    ("--cudagraphs: graph replay and its input copies", {"CudaGraph.__call__"}),  # warm-up calls: the phases above
    ("logging (TensorBoard)", {"SummaryWriter.add_scalar", "SummaryWriter.add_text"}),
]
STARTUP = {
    "Optimizer.__init__",
    "Adam.__init__",
    "make_env",
    "SummaryWriter.__init__",
    "Module.to",
    "QEnsemble.__init__",
    "Actor.__init__",
    "ReplayBuffer.__init__",
}


def phase_of(stack: list) -> str:
    names = [frame.split(" (")[0] for frame in stack]
    if "main" not in names:
        return "start-up and imports"
    below_main = names[len(names) - 1 - names[::-1].index("main") + 1 :]
    if below_main and below_main[0] in STARTUP:
        return "start-up and imports"
    for name in reversed(below_main):  # innermost first
        for phase, phase_names in PHASES:
            if name in phase_names:
                return phase
    return "rest of the loop (Python, conversions, progress bar)"


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    scripts = sorted(f.removesuffix("_continuous_action.py") for f in os.listdir(REPO) if f.endswith("_continuous_action.py"))
    if argv and argv[0] in {"-h", "--help"}:
        sys.exit(__doc__)
    if not argv or argv[0] not in scripts:
        sys.exit(f"error: usage: python tools/profile_run.py {{{','.join(scripts)}}} [script flags]")
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
