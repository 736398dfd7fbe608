"""Welch's t-test between two algorithms' final returns, task by task, from a final_returns.csv that
plot_results.py wrote (one row per run: algo, env_id, seed, steps, final_return).

    python tools/welch.py results/many_seeds/final_returns.csv td3_x3 td3
    python tools/welch.py results/many_seeds/final_returns.csv td3_x3 td3_1x+td3       # pools two algorithms' runs
    python tools/welch.py results/many_seeds/eval_series.csv td3_x3 td3_1x --steps 50000 100000

prints a markdown table: each task both algorithms ran, the runs of each, their mean and standard deviation,
the difference of the means, Welch's t, its degrees of freedom, the two-sided p-value (unequal variances), in
how many of the (a run, b run) pairs a's run is higher (a tie counts for neither; with 3 runs each and no
ties, 9/9 happens one time in twenty for two equal algorithms), and the 95% confidence interval of the
difference: the differences the runs do not rule out, which a p-value alone does not say.
With an eval_series.csv (plot_results.py's: algo, env_id, seed, step, episodic_return) and --steps LO HI, a
run's value is the mean of its evaluations from step LO to step HI (both included) instead of its final one.
With three runs a side the test only sees large differences; a high p-value is no evidence of equality.

With --paired, runs are matched by seed instead (a paired t-test on the differences, seed by seed): for two
arms whose run k starts from the same draws, as a many-seed process's seed k and the single-seed run k do. A
pooled 'b+c' then takes each seed from the first of b, c that ran it.

    python tools/welch.py results/many_seeds/final_returns.csv td3_n3 td3+td3_1x --paired
"""

import argparse
import csv
import sys
from collections import defaultdict

import numpy as np
from scipy import stats


def pool(runs: dict, name: str) -> dict:
    """Adds the algorithm `name`, 'a+b' for the runs of a and b together, task by task."""
    parts = name.split("+")
    if len(parts) > 1:
        for env_id in {env for algo, env in runs if algo in parts}:
            runs[name, env_id] = [r for part in parts for r in runs.get((part, env_id), [])]
    return runs


def by_seed(path: str, steps=None) -> dict:
    """{(algo, env_id): {seed: final return, or the mean of its evaluations with LO <= step <= HI}}."""
    values = defaultdict(lambda: defaultdict(list))
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            if steps is None:
                values[row["algo"], row["env_id"]][row["seed"]].append(float(row["final_return"]))
            elif steps[0] <= int(float(row["step"])) <= steps[1]:
                values[row["algo"], row["env_id"]][row["seed"]].append(float(row["episodic_return"]))
    return {key: {seed: float(np.mean(v)) for seed, v in seeds.items()} for key, seeds in values.items()}


def paired_table(runs: dict, a: str, b: str) -> list:
    """One row per task: (env_id, pairs, mean of a, mean of b, mean and std of a - b, t, p, pairs where a is higher,
    and the 95% confidence interval of the mean difference, low and high)."""
    rows = []
    for env_id in sorted({env for algo, env in runs if algo == a}):
        b_runs = {}
        for part in reversed(b.split("+")):  # the first part that ran a seed gives it
            b_runs.update(runs.get((part, env_id), {}))
        seeds = sorted(set(runs[a, env_id]) & set(b_runs), key=lambda s: (len(s), s))
        if len(seeds) < 2:
            continue
        x, y = np.array([runs[a, env_id][s] for s in seeds]), np.array([b_runs[s] for s in seeds])
        test = stats.ttest_rel(x, y)
        d, ci = x - y, test.confidence_interval(0.95)
        higher = int((d > 0).sum())
        rows.append(
            (env_id, len(seeds), x.mean(), y.mean(), d.mean(), d.std(ddof=1), *map(float, test), higher, *map(float, ci))
        )
    return rows


def welch_table(runs: dict, a: str, b: str) -> list:
    """One row per task both ran: (env_id, n_a, mean_a, std_a, n_b, mean_b, std_b, t, df, p, above, low, high), `above`
    the number of (a run, b run) pairs in which a's run is higher (all n_a * n_b of them: a's every run above b's
    every one), low and high the 95% confidence interval of mean_a - mean_b (Welch's)."""
    rows = []
    for env_id in sorted({env for algo, env in runs if algo == a} & {env for algo, env in runs if algo == b}):
        x, y = np.array(runs[a, env_id]), np.array(runs[b, env_id])
        if len(x) < 2 or len(y) < 2:
            continue
        test = stats.ttest_ind(x, y, equal_var=False)
        (t, p), ci = test, test.confidence_interval(0.95)
        vx, vy = x.var(ddof=1) / len(x), y.var(ddof=1) / len(y)
        df = (vx + vy) ** 2 / (vx**2 / (len(x) - 1) + vy**2 / (len(y) - 1)) if vx + vy > 0 else float("nan")
        above = int((x[:, None] > y[None, :]).sum())
        stats_ = (float(t), df, float(p), above, float(ci.low), float(ci.high))
        rows.append((env_id, len(x), x.mean(), x.std(ddof=1), len(y), y.mean(), y.std(ddof=1), *stats_))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "final_returns", help="a final_returns.csv (or, with --steps, an eval_series.csv) written by plot_results.py"
    )
    parser.add_argument("a", help="an algorithm as the CSV names it")
    parser.add_argument("b", help="the algorithm it is compared with")
    parser.add_argument("--steps", nargs=2, type=int, metavar=("LO", "HI"), help="with an eval_series.csv: the window")
    parser.add_argument("--paired", action="store_true", help="match runs by seed: a paired t-test")
    args = parser.parse_args(argv)
    kind = "eval_series.csv" if args.steps else "final_returns.csv"
    if args.steps and args.steps[0] > args.steps[1]:
        sys.exit(f"error: --steps {args.steps[0]} {args.steps[1]}: LO is above HI")
    try:
        seeds = by_seed(args.final_returns, args.steps)  # one value per run: its final return or its window's mean
    except (OSError, KeyError, ValueError) as e:
        sys.exit(f"error: {args.final_returns} is not a readable {kind} ({type(e).__name__}: {e})")
    runs = {key: list(values.values()) for key, values in seeds.items()}
    algos = sorted({algo for algo, _ in runs})
    for name in (args.a, args.b):
        missing = [part for part in name.split("+") if part not in algos]
        if missing:
            window = " in that --steps window" if args.steps else ""
            sys.exit(f"error: no runs of {missing[0]!r} in {args.final_returns}{window}; it has {', '.join(algos)}")
        pool(runs, name)
    if args.paired:
        return print_paired(args, seeds)
    rows = welch_table(runs, args.a, args.b)
    if not rows:
        sys.exit(f"error: no task with at least two runs of both {args.a!r} and {args.b!r}")
    print(
        f"| task | {args.a} (n, mean +- std) | {args.b} (n, mean +- std) | difference | Welch t | df | p | {args.a} above (ties: neither)"
        " | 95% CI of the difference |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for env_id, na, ma, sa, nb, mb, sb, t, df, p, above, low, high in rows:
        print(
            f"| {env_id} | {na}, {ma:.1f} +- {sa:.1f} | {nb}, {mb:.1f} +- {sb:.1f} | {ma - mb:+.1f} | {t:.2f} | {df:.1f} | {p:.3f}"
            f" | {above}/{na * nb} | {low:+.1f} to {high:+.1f} |"
        )
    return rows


def print_paired(args, runs: dict) -> list:
    rows = paired_table(runs, args.a, args.b)
    if not rows:
        sys.exit(f"error: no task with at least two seeds that both {args.a!r} and {args.b!r} ran")
    print(
        f"| task | seeds | {args.a} mean | {args.b} mean | difference (mean +- std over seeds) | paired t | p | {args.a} higher"
        " | 95% CI of the difference |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for env_id, n, ma, mb, md, sd, t, p, higher, low, high in rows:
        cells = (
            f"{n} | {ma:.1f} | {mb:.1f} | {md:+.1f} +- {sd:.1f} | {t:.2f} | {p:.3f} | {higher}/{n} | {low:+.1f} to {high:+.1f}"
        )
        print(f"| {env_id} | {cells} |")
    return rows


if __name__ == "__main__":
    main()
