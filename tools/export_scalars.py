"""Any TensorBoard scalar of finished runs as one CSV (algo, env_id, seed, step, value), so that a figure
quoted from a tag other than eval/episodic_return has a committed source, e.g.

    python tools/export_scalars.py runs/MountainCarContinuous-v0__rnd__* runs/MountainCarContinuous-v0__ebd__* \
        --tag charts/intrinsic_reward --out results/exploration/intrinsic_reward.csv

Runs are named as plot_results.py names them (the script, plus the flags that tell variants apart).
"""

import argparse
import csv
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import plot_results  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sources", nargs="+", help="run folders, or folders of them")
    parser.add_argument("--tag", required=True, help="the scalar, e.g. charts/intrinsic_reward")
    parser.add_argument("--out", required=True, help="the CSV to write")
    args = parser.parse_args(argv)
    runs = [run for source in args.sources for run in plot_results.read_tensorboard(source, finished_only=True, tag=args.tag)]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["algo", "env_id", "seed", "step", "value"])
        for run in sorted(runs, key=lambda r: (r.algo, r.env_id, r.seed)):
            writer.writerows(
                (run.algo, run.env_id, run.seed, int(step), f"{value:.6g}") for step, value in zip(run.steps, run.returns)
            )
    print(f"{len(runs)} runs' {args.tag} -> {args.out}")


if __name__ == "__main__":
    main()
