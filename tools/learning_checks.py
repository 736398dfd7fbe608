"""The learning checks of tests/test_learning.py on more seeds than the test's one: each evaluation's 10 episode
returns, and whether each seed passes the check (the best median episode of the last three evaluations above the
threshold) and the final mean alone. Another CPU trains another run from the same seed, so the seeds here stand in
for the runs other CPUs would train (docs/tests.md#learning-checks).

    python tools/learning_checks.py oparl td3 sac --seeds 1 2 3 4 5 6 7 8 --out results/learning_checks/returns.csv
    python tools/learning_checks.py --summary results/learning_checks/returns.csv    # the table again, from the file

--extra-steps N trains the off-policy scripts N steps past each budget (the steps before are the same), and the
summary gives the check at every evaluation from the budget on, as if the budget ended there; the PPO family anneals
its learning rate over the run, so its budget is tried by changing BUDGETS. Each run takes one thread; --workers runs
several side by side.
"""

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "tests"))
sys.path.insert(0, REPO)


def budgets() -> dict:
    from conftest import SCRIPTS, declared
    from test_learning import BUDGETS

    return {script: declared(BUDGETS, script) for script in SCRIPTS if declared(BUDGETS, script)}


def run_one(script: str, seed: int, extra_steps: int, out: str):
    """One seed's run, its evaluations appended to `out` as rows: script, seed, step, return_1, ..., return_10."""
    import torch

    from test_learning import learning_run

    torch.set_num_threads(1)
    total = budgets()[script][1] + extra_steps
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        evaluations = learning_run(script, seed, total)
    with open(out, "a", newline="") as f:
        csv.writer(f).writerows([script, seed, step, *(f"{x:.4f}" for x in returns)] for step, returns in evaluations)


def read(path: str) -> dict:
    """{(script, seed): [(step, returns), ...]} from a file of rows as run_one writes them."""
    runs = {}
    with open(path) as f:
        for row in csv.reader(f):
            runs.setdefault((row[0], int(row[1])), []).append((int(row[2]), np.array(row[3:], dtype=float)))
    return runs


def summary(runs: dict) -> str:
    """Per script and budget (the test's, and each evaluation after it): the seeds the check passes, and those the
    final mean alone (the check before) would pass."""
    from test_learning import EVALUATIONS, passes

    lines = [
        "| check | steps | seeds | passes the check (best median of the last 3) | its lowest seed | final mean above the "
        "threshold | its lowest seed |"
    ]
    lines.append("|---|---|---|---|---|---|---|")
    for script, (env_id, total, learning_starts, _, threshold) in budgets().items():
        seeds = sorted(seed for s, seed in runs if s == script)
        if not seeds:
            continue
        # a budget ends at an evaluation: the test's and those after it (the off-policy scripts' longer runs), and the
        # end of each run (the PPO family's run is its budget: its learning rate anneals over it)
        ends = {runs[(script, seed)][-1][0] for seed in seeds}
        if learning_starts:
            ends |= {step for seed in seeds for step, _ in runs[(script, seed)] if step >= total}
        for end in sorted(ends):
            cut = {seed: [e for e in runs[(script, seed)] if e[0] <= end] for seed in seeds}
            cut = {seed: e for seed, e in cut.items() if e and e[-1][0] == end and len(e) >= EVALUATIONS}
            best = {seed: max(float(np.median(r)) for _, r in e[-EVALUATIONS:]) for seed, e in cut.items()}
            final = {seed: float(e[-1][1].mean()) for seed, e in cut.items()}
            check = [seed for seed, e in cut.items() if passes(e, threshold)]
            name = f"{script}, {env_id}, > {threshold:g}" + (" (the test's budget)" if end == total else "")
            low, low_final = min(best, key=best.get), min(final, key=final.get)
            lines.append(
                f"| {name} | {end} | {len(cut)} | {len(check)} of {len(cut)} | {best[low]:.1f} (seed {low}) | "
                f"{sum(v > threshold for v in final.values())} of {len(cut)} | {final[low_final]:.1f} (seed {low_final}) |"
            )
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scripts", nargs="*", help="scripts by short name (oparl, td3, ...): those with a learning check")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 7, 8])
    parser.add_argument("--extra-steps", type=int, default=0, help="steps past each budget")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", help="the CSV the runs' evaluations are appended to")
    parser.add_argument("--summary", metavar="CSV", help="print the table of a CSV this tool wrote, and stop")
    parser.add_argument("--one", nargs=2, metavar=("SCRIPT", "SEED"), help=argparse.SUPPRESS)  # a worker's run
    args = parser.parse_args(argv)
    if args.summary:
        if not os.path.isfile(args.summary):
            parser.error(f"--summary: no such file {args.summary}")
        print(summary(read(args.summary)))
        return
    known = budgets()
    if args.extra_steps < 0:
        parser.error("--extra-steps must be >= 0")
    annealed = [script for script in args.scripts if script in known and not known[script][2]]
    if args.extra_steps and annealed:
        parser.error(
            f"--extra-steps: {', '.join(annealed)} anneal(s) the learning rate over the run, so a longer run trains "
            "otherwise from its start: try another budget in BUDGETS (tests/test_learning.py) instead"
        )
    if not args.out:
        parser.error("--out CSV is needed to run")
    if args.one:
        run_one(args.one[0], int(args.one[1]), args.extra_steps, os.path.abspath(args.out))
        return
    for script in args.scripts:
        if script not in known:
            parser.error(f"{script} has no learning check (those with one: {', '.join(known)})")
    if not args.scripts:
        parser.error("name the scripts to run (those with a learning check: " + ", ".join(known) + ")")
    out = os.path.abspath(args.out)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    jobs = [(script, seed) for script in args.scripts for seed in args.seeds]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    running, failed = [], []
    for script, seed in jobs:  # each run writes a file of its own; they are appended to --out in order at the end
        while sum(process.poll() is None for _, process in running) >= args.workers:
            time.sleep(1)
        flags = ["--one", script, str(seed), "--extra-steps", str(args.extra_steps), "--out", f"{out}.{script}_{seed}"]
        running.append(((script, seed), subprocess.Popen([sys.executable, os.path.abspath(__file__), *flags], env=env)))
    with open(out, "a") as merged:
        for (script, seed), process in running:
            part = f"{out}.{script}_{seed}"
            if process.wait() != 0 or not os.path.isfile(part):
                failed.append(f"{script} seed {seed}")
                continue
            with open(part) as f:
                merged.write(f.read())
            os.remove(part)
    if failed:
        sys.exit(f"error: {', '.join(failed)} failed (their output is above); the others are in {args.out}")
    print(summary(read(out)))


if __name__ == "__main__":
    main()
