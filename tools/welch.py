"""Welch's t-test between two algorithms' final returns, task by task, from a final_returns.csv that
plot_results.py wrote (one row per run: algo, env_id, seed, steps, final_return).

    python tools/welch.py results/many_seeds/final_returns.csv "td3 (num_seeds=3)" td3

prints a markdown table: each task both algorithms ran, the runs of each, their mean and standard deviation,
the difference of the means, Welch's t, its degrees of freedom and the two-sided p-value (unequal variances).
With three runs a side the test only sees large differences; a high p-value is no evidence of equality.
"""

import argparse
import csv
import sys
from collections import defaultdict

import numpy as np
from scipy import stats


def finals(path: str) -> dict:
    """{(algo, env_id): [final return of each run]}."""
    runs = defaultdict(list)
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            runs[row["algo"], row["env_id"]].append(float(row["final_return"]))
    return runs


def welch_table(runs: dict, a: str, b: str) -> list:
    """One row per task both ran: (env_id, n_a, mean_a, std_a, n_b, mean_b, std_b, t, df, p)."""
    rows = []
    for env_id in sorted({env for algo, env in runs if algo == a} & {env for algo, env in runs if algo == b}):
        x, y = np.array(runs[a, env_id]), np.array(runs[b, env_id])
        if len(x) < 2 or len(y) < 2:
            continue
        t, p = stats.ttest_ind(x, y, equal_var=False)
        vx, vy = x.var(ddof=1) / len(x), y.var(ddof=1) / len(y)
        df = (vx + vy) ** 2 / (vx**2 / (len(x) - 1) + vy**2 / (len(y) - 1)) if vx + vy > 0 else float("nan")
        rows.append((env_id, len(x), x.mean(), x.std(ddof=1), len(y), y.mean(), y.std(ddof=1), float(t), df, float(p)))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("final_returns", help="a final_returns.csv written by plot_results.py")
    parser.add_argument("a", help="an algorithm as the CSV names it")
    parser.add_argument("b", help="the algorithm it is compared with")
    args = parser.parse_args(argv)
    try:
        runs = finals(args.final_returns)
    except (OSError, KeyError, ValueError) as e:
        sys.exit(f"error: {args.final_returns} is not a readable final_returns.csv ({type(e).__name__}: {e})")
    algos = sorted({algo for algo, _ in runs})
    for name in (args.a, args.b):
        if name not in algos:
            sys.exit(f"error: no runs of {name!r} in {args.final_returns}; it has {', '.join(algos)}")
    rows = welch_table(runs, args.a, args.b)
    if not rows:
        sys.exit(f"error: no task with at least two runs of both {args.a!r} and {args.b!r}")
    print(f"| task | {args.a} (n, mean +- std) | {args.b} (n, mean +- std) | difference | Welch t | df | p |")
    print("|---|---|---|---|---|---|---|")
    for env_id, na, ma, sa, nb, mb, sb, t, df, p in rows:
        print(
            f"| {env_id} | {na}, {ma:.1f} +- {sa:.1f} | {nb}, {mb:.1f} +- {sb:.1f} | {ma - mb:+.1f} | {t:.2f} | {df:.1f} | {p:.3f} |"
        )
    return rows


if __name__ == "__main__":
    main()
