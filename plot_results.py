"""Turn runs into the paper's figures and table.

    python plot_results.py runs --out results/new                             # TensorBoard logs under runs/
    python plot_results.py results/main/eval_series.csv --out results/main    # or the CSV this script writes
    python plot_results.py results/main/eval_series.csv runs --finished-only --out results/main   # both, merged
    python plot_results.py results/main/eval_series.csv runs/*__oparl__*__100000 --finished-only --out results/main
                                                                   # run folders picked by name, as benchmark.sh names them
    python plot_results.py results/dmc_1m/eval_series.csv --up-to 500000 --prefix at500k_ --out /tmp/dmc1m
                                                                   # an unfinished sweep read at one step its runs reached

Writes into --out:
  {prefix}curves.png        eval/episodic_return per env, one line per algorithm: mean over seeds of
                            each run's curve smoothed over --smoothing evaluations (default 10), shaded
                            +- half a sample std (ddof 1; the paper's Figure 2 style)
  {prefix}table.md          mean +- sample std (ddof 1) of the final evaluation per algorithm and env (best in bold), an
                            average row, OPARL's improvement over each baseline, every run's final
                            evaluation per seed, the IQM, median, mean and optimality gap of normalised
                            scores with 95% CIs, the probability of improvement of OPARL over each baseline
                            (and of each OPARL variant over OPARL) with its CI, and (unless --no-paper) the
                            paper's Table 1 numbers beside ours
  {prefix}iqm.png           interquartile mean of normalised scores (DMC return / 1000) over all runs of
                            the DMC tasks every algorithm has finished, with 95% stratified bootstrap confidence intervals
  {prefix}profiles.png      performance profiles: the fraction of those runs above each normalised score, with 95% CIs

The statistics are rliable's ("Deep RL at the edge of the statistical precipice", Agarwal et al. 2021),
with a fixed bootstrap seed: the same runs give byte-identical files.
  final_returns.csv         one row per run read (all of them, whatever --algos/--env-ids select):
                            algo, env_id, seed, steps, final_return
  eval_series.csv           every evaluation of every run read: algo, env_id, seed, step, episodic_return (and
                            seeds_per_process, where a run trained several seeds a process)

An algorithm is named by its script (exp_name without `_continuous_action`); runs of one script with
different hyperparameters (an ablation) get the differing flags appended, e.g. `oparl (q_num=2)`. Flags that
do not change what a run learns (NOT_ALGORITHM: --cuda, --cudagraphs, --num-seeds, ...) name nothing; table.md
lists the runs that trained several seeds a process. A run found twice keeps its longer record, with a warning
where the two records differ.
"""

import argparse
import csv
import dataclasses
import os
import sys
import zlib
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

TAG = "eval/episodic_return"
PAPER_TABLE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "paper", "paper_table1.csv")
PAPER_CLAIMS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "paper", "paper_mujoco_claims.csv")
# hyperparameters that do not change what a run learns, or that identify it rather than its algorithm
NOT_ALGORITHM = {
    "seed",
    "env_id",
    "exp_name",
    "run_name",
    "resume",
    "checkpoint_frequency",
    "track",
    "wandb_project_name",
    "wandb_entity",
    "capture_video",
    "save_model",
    "cuda",
    "cudagraphs",  # replays the same update: a seed's --cudagraphs run learns as its eager one (tests/test_cudagraphs.py)
    "num_seeds",  # a seed of a group runs the one-seed update (tests/test_many_seeds.py); kept as Run.seeds_per_process
    "torch_deterministic",
}
SMOOTHING = 10  # evaluations: 50k steps of a 1M-step run at one evaluation per 5000
BOOTSTRAP_REPS = 2000
BOOTSTRAP_SEED = 0
# rliable's aggregate metrics of normalised scores, in the table's order (the optimality gap: the mean shortfall below 1)
METRICS = ("iqm", "median", "mean", "optimality gap")


def fail(message: str):
    raise SystemExit(f"error: {message}")


def warn(message: str):
    print(f"warning: {message}", file=sys.stderr)


@dataclass
class Run:
    algo: str
    env_id: str
    seed: int
    steps: np.ndarray
    returns: np.ndarray
    source: str
    seeds_per_process: int = 1  # the run's --num-seeds: the tables say which runs trained in a group


def parse_hyperparameters(text: str) -> dict:
    """The `|param|value|` table the scripts write as TensorBoard text."""
    params = {}
    for line in text.splitlines()[2:]:
        cells = line.strip().strip("|").split("|")
        if len(cells) == 2:
            params[cells[0]] = cells[1]
    return params


def algorithm_names(configs: list) -> list:
    """Short names for runs' configs: the script's name, plus the flags that tell its variants apart."""
    by_script = defaultdict(set)
    for exp_name, config in configs:
        by_script[exp_name].add(config)
    names = []
    for exp_name, config in configs:
        base = exp_name.removesuffix("_continuous_action")
        variants = by_script[exp_name]
        if len(variants) == 1:
            names.append(base)
            continue
        differing = sorted({k for c in variants for k, v in c if any(dict(other).get(k) != v for other in variants)})
        names.append(f"{base} ({', '.join(f'{k}={dict(config).get(k)}' for k in differing)})")
    return names


def read_tensorboard(root: str, finished_only: bool = False, tag: str = TAG) -> list:
    """Every run under `root` that logged `tag`, its series as (steps, values)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    if not os.path.isdir(root):
        fail(f"{root}: no such folder (give a folder of TensorBoard runs, e.g. runs, or an eval_series.csv)")
    run_dirs = sorted(d for d, _, files in os.walk(root) if any(f.startswith("events.out.tfevents") for f in files))
    if not run_dirs:
        fail(f"{root} holds no TensorBoard runs (no events.out.tfevents.* files below it)")
    if finished_only:  # benchmark.sh marks a finished run with DONE
        unfinished = [d for d in run_dirs if not os.path.exists(os.path.join(d, "DONE"))]
        if unfinished:
            print(f"leaving out {len(unfinished)} unfinished run(s) (no DONE marker) under {root}")
        run_dirs = [d for d in run_dirs if d not in unfinished]
        if not run_dirs:  # one run folder among several sources, say, still running
            return []
    found, configs, without_eval = [], [], []
    for run_dir in run_dirs:
        acc = EventAccumulator(run_dir, size_guidance={"scalars": 0, "tensors": 0})
        acc.Reload()
        if tag not in acc.Tags()["scalars"] or "hyperparameters/text_summary" not in acc.Tags()["tensors"]:
            without_eval.append(run_dir)
            continue
        params = parse_hyperparameters(acc.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode())
        events = acc.Scalars(tag)
        found.append((params, np.array([e.step for e in events]), np.array([e.value for e in events]), run_dir))
        configs.append((params["exp_name"], tuple(sorted((k, v) for k, v in params.items() if k not in NOT_ALGORITHM))))
    if without_eval:
        warn(f"{len(without_eval)} run(s) have no {tag} and are left out: {', '.join(without_eval)}")
    if not found:
        fail(f"no run under {root} logged {tag}")
    names = algorithm_names(configs)
    return [
        Run(name, p["env_id"], int(p["seed"]), steps, returns, d, int(p.get("num_seeds", 1)))
        for name, (p, steps, returns, d) in zip(names, found)
    ]


def same_record(a: Run, b: Run) -> bool:
    """Whether two records of a run agree wherever both have an evaluation (one may be longer: a resumed run)."""
    common, ia, ib = np.intersect1d(a.steps, b.steps, return_indices=True)
    return len(common) > 0 and np.allclose(a.returns[ia], b.returns[ib], atol=1e-3)


def read_csv(path: str) -> list:
    series, group = defaultdict(list), {}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = {"algo", "env_id", "seed", "step", "episodic_return"} - set(reader.fieldnames or [])
        if missing:
            fail(f"{path} lacks the column(s) {', '.join(sorted(missing))} (expected the eval_series.csv this script writes)")
        for row in reader:
            key = (row["algo"], row["env_id"], int(row["seed"]))
            series[key].append((int(row["step"]), float(row["episodic_return"])))
            group[key] = int(row.get("seeds_per_process") or 1)  # a column written only where a run trained in a group
    if not series:
        fail(f"{path} holds no evaluations")
    runs = []
    for (algo, env_id, seed), points in series.items():
        points.sort()
        steps, returns = np.array([s for s, _ in points]), np.array([r for _, r in points])
        runs.append(Run(algo, env_id, seed, steps, returns, path, group[(algo, env_id, seed)]))
    return runs


def interval_estimates(scores, func, reps: int = BOOTSTRAP_REPS):
    """rliable's point estimate of `func` and its 95% stratified bootstrap percentile interval: each task's runs
    are resampled with replacement. `scores` is a runs x tasks matrix, or a pair of them for a comparison of two
    algorithms (each resampled on its own). rliable draws its resamples from NumPy's global generator, not from
    the random_state it takes, so that generator is seeded here: the same scores give the same interval."""
    from rliable import library as rly

    np.random.seed(BOOTSTRAP_SEED)
    points, intervals = rly.get_interval_estimates({"x": scores}, func, reps=reps)
    return np.atleast_1d(points["x"]), intervals["x"]


def aggregate_metrics(scores: np.ndarray) -> np.ndarray:
    from rliable import metrics

    return np.array([getattr(metrics, f"aggregate_{name.replace(' ', '_')}")(scores) for name in METRICS])


def sample_std(curves: np.ndarray) -> np.ndarray:
    """The sample standard deviation (ddof 1) over runs at each step, ignoring NaNs; 0 where one run has a value."""
    count = np.sum(~np.isnan(curves), 0)
    centred = np.where(np.isnan(curves), 0.0, curves - np.nanmean(curves, 0))
    return np.sqrt(np.sum(centred**2, 0) / np.maximum(count - 1, 1))


def smooth(values: np.ndarray, window: int = SMOOTHING) -> np.ndarray:
    """Trailing moving average; the first points average what there is."""
    sums = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    return (sums[idx] - sums[np.maximum(idx - window, 0)]) / np.minimum(idx, window)


def algo_order(algos) -> list:
    return sorted(algos, key=lambda a: (not a.startswith("oparl"), a != "oparl", a))


# the paper's systems keep one colour in every figure
PAPER_COLORS = {"oparl": "C0", "td3": "C1", "sac": "C2", "ppo": "C3", "rnd": "C4", "ebd": "C5", "redq": "C6"}
# every other name (an ablation, a variant, a new script) is given one of these by its name, the same in every
# figure; two names that draw the same one in a figure are told apart by taking the next free one
OTHER_COLORS = ["C7", "C8", "C9", "black", "#843c39", "#6b6ecf", "#637939"]  # fmt: skip


def colors_of(algos: list) -> dict:
    colors = {a: PAPER_COLORS[a] for a in algos if a in PAPER_COLORS}
    for algo in sorted(a for a in algos if a not in PAPER_COLORS):
        free = [c for c in OTHER_COLORS if c not in colors.values()]
        if not free:
            colors[algo] = "gray"
            continue
        start = zlib.crc32(algo.encode()) % len(OTHER_COLORS)
        colors[algo] = next(c for c in OTHER_COLORS[start:] + OTHER_COLORS[:start] if c in free)
    return colors


def complete_runs(runs: list) -> dict:
    """{(algo, env): [runs]} holding the runs that reached their group's last evaluation step; warns about the others."""
    groups = defaultdict(list)
    for run in runs:
        groups[(run.algo, run.env_id)].append(run)
    complete = {}
    for key, group in groups.items():
        last = max(r.steps[-1] for r in group)
        short = [r for r in group if r.steps[-1] < last]
        if short:
            cut = ", ".join(f"seed {r.seed} (at {r.steps[-1]})" for r in sorted(short, key=lambda r: r.seed))
            warn(f"{key[0]} on {key[1]}: run(s) cut short before step {last}, left out of the table and IQM: {cut}")
        complete[key] = [r for r in group if r.steps[-1] == last]
    return complete


def runs_up_to(runs: list, step: int) -> list:
    """--up-to: each run's evaluations up to `step`, of the runs that have reached it; warns about the others."""
    reached = [r for r in runs if r.steps[-1] >= step]
    if not reached:
        fail(f"--up-to {step}: no run has reached step {step} (the furthest is at {max(r.steps[-1] for r in runs)})")
    short = sorted((r for r in runs if r.steps[-1] < step), key=run_order)
    if short:
        cut = ", ".join(f"{r.algo} on {r.env_id} seed {r.seed} (at {r.steps[-1]})" for r in short)
        warn(f"--up-to {step}: left out, not there yet: {cut}")
    return [dataclasses.replace(r, steps=r.steps[r.steps <= step], returns=r.returns[r.steps <= step]) for r in reached]


def run_order(run: Run) -> tuple:
    return run.env_id, run.algo, run.seed


def plot_curves(runs: list, path: str, window: int = SMOOTHING):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs = sorted({r.env_id for r in runs})
    algos = algo_order({r.algo for r in runs})
    cols = min(3, len(envs))
    rows = -(-len(envs) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False)
    colors = colors_of(algos)
    for ax, env in zip(axes.flat, envs):
        for algo in algos:
            group = [r for r in runs if r.env_id == env and r.algo == algo]
            if not group:
                continue
            steps = np.unique(np.concatenate([r.steps for r in group]))
            curves = np.full((len(group), len(steps)), np.nan)
            for i, r in enumerate(group):  # each run on the common grid; NaN where a run stopped early
                curves[i, np.searchsorted(steps, r.steps)] = smooth(r.returns, window)
            mean, std = np.nanmean(curves, 0), sample_std(curves)
            ax.plot(steps, mean, color=colors[algo], label=f"{algo} ({len(group)} seed{'s' if len(group) > 1 else ''})")
            ax.fill_between(steps, mean - std / 2, mean + std / 2, color=colors[algo], alpha=0.2)
        ax.set_title(env.removeprefix("dm_control/"))
        ax.set_xlabel("environment steps")
        ax.set_ylabel("evaluation return")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax in list(axes.flat)[len(envs) :]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def score_scales(runs: list, random_scores: dict) -> dict:
    """{task: (zero, one)}, a normalised score being (return - zero) / (one - zero). DMC tasks: 0 and 1000
    (a reward in [0, 1] per step, 1000 steps). Other tasks only with a random-policy score: that score,
    and the best evaluation return any run read reached on the task (MuJoCo returns have no common scale)."""
    scales = {}
    for env in sorted({r.env_id for r in runs}):
        if env.startswith("dm_control/"):
            scales[env] = (0.0, 1000.0)
        elif env in random_scores:
            scales[env] = (random_scores[env], max(float(r.returns.max()) for r in runs if r.env_id == env))
    return scales


def normalised_scores(complete: dict, algo: str, envs: set, scales: dict) -> list:
    """Per task in `envs` (sorted), the normalised final returns of `algo`'s runs, by seed."""
    return [
        (np.array([r.returns[-1] for r in sorted(group, key=lambda r: r.seed)]) - scales[env][0])
        / (scales[env][1] - scales[env][0])
        for (a, env), group in sorted(complete.items())
        if a == algo and env in envs
    ]


def score_matrix(scores_by_task: list, algo: str) -> np.ndarray:
    """runs x tasks, as rliable takes scores. Where tasks have different numbers of runs, each keeps its
    lowest seeds, as many as the task with the fewest has."""
    runs = min(len(s) for s in scores_by_task)
    if any(len(s) > runs for s in scores_by_task):
        warn(f"{algo}: tasks with different numbers of runs; the statistics keep the {runs} lowest seeds of each task")
    return np.stack([s[:runs] for s in scores_by_task], axis=1)


def aggregate(complete: dict, algos: list, scales: dict, reps: int = BOOTSTRAP_REPS) -> tuple:
    """Over the normalisable tasks that every algorithm with such runs has finished (so that the algorithms are
    compared on the same tasks): ({algo: {metric: (value, low, high), "tasks": n, "runs": n}}, {algo: runs x tasks})."""
    per_algo = [{env for (b, env) in complete if b == a and env in scales} for a in algos]
    per_algo = [envs for envs in per_algo if envs]
    shared = set.intersection(*per_algo) if per_algo else set()
    left_out = set().union(*per_algo) - shared
    if left_out:
        kind = "DMC tasks" if all(e.startswith("dm_control/") for e in scales) else "normalised tasks"
        warn(
            f"IQM only over the {kind} every algorithm has finished ({len(shared)}); left out: {', '.join(sorted(e.removeprefix('dm_control/') for e in left_out))}"
        )
    stats, matrices = {}, {}
    for algo in algos:
        scores = normalised_scores(complete, algo, shared, scales)
        if scores:
            matrices[algo] = score_matrix(scores, algo)
            points, intervals = interval_estimates(matrices[algo], aggregate_metrics, reps)
            stats[algo] = {name: (points[i], *intervals[:, i]) for i, name in enumerate(METRICS)}
            stats[algo].update(tasks=matrices[algo].shape[1], runs=matrices[algo].size)
    return stats, matrices


def improvement_pairs(algos: list) -> list:
    """(X, Y) pairs whose P(X > Y) the table gives: OPARL over each baseline, each OPARL variant over OPARL."""
    if "oparl" not in algos:
        return []
    variants = [a for a in algos if a.startswith("oparl") and a != "oparl"]
    return [("oparl", a) for a in algos if not a.startswith("oparl")] + [(a, "oparl") for a in variants]


def probabilities_of_improvement(matrices: dict, reps: int = BOOTSTRAP_REPS) -> dict:
    """{(X, Y): (P(X > Y), low, high)}: the probability that a run of X scores above a run of Y on the same task
    (ties count half), averaged over the tasks, with its interval (rliable)."""
    from rliable import metrics

    result = {}
    for x, y in improvement_pairs(list(matrices)):
        point, interval = interval_estimates((matrices[x], matrices[y]), metrics.probability_of_improvement, reps)
        result[(x, y)] = (float(point[0]), *map(float, interval[:, 0]))
    return result


def performance_profiles(matrices: dict, reps: int = BOOTSTRAP_REPS) -> tuple:
    """Thresholds tau, and per algorithm the fraction of its runs scoring above each tau with its 95%
    interval ({algo: (fraction, low, high)}), as rliable's create_performance_profile."""
    from rliable import library as rly

    everything = np.concatenate([m.ravel() for m in matrices.values()])
    taus = np.linspace(min(0.0, everything.min()), max(1.0, everything.max()), 101)
    profiles = {}
    for algo, scores in matrices.items():
        np.random.seed(BOOTSTRAP_SEED)
        fraction, interval = rly.create_performance_profile({algo: scores}, taus, reps=reps)
        profiles[algo] = (fraction[algo], *interval[algo])
    return taus, profiles


def normalisation_text(scales: dict) -> str:
    others = "(return - random policy) / (best seen - random policy)"
    if all(env.startswith("dm_control/") for env in scales):
        return "DMC return / 1000"
    return others if not any(env.startswith("dm_control/") for env in scales) else f"DMC return / 1000; other tasks {others}"


def plot_iqm(stats: dict, path: str, normalisation: str = "DMC return / 1000"):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    algos = algo_order(stats)
    colors = colors_of(algos)
    fig, ax = plt.subplots(figsize=(6, 0.6 * len(algos) + 1.2))
    for i, algo in enumerate(algos):
        value, low, high = stats[algo]["iqm"]
        ax.plot([low, high], [i, i], color=colors[algo], linewidth=6, alpha=0.5, solid_capstyle="butt")
        ax.plot([value], [i], "|", color="black", markersize=16)
    ax.set_yticks(range(len(algos)), [f"{a}\n{stats[a]['runs']} runs, {stats[a]['tasks']} tasks" for a in algos])
    ax.set_ylim(len(algos) - 0.5, -0.5)
    scale_lines = normalisation.replace("; ", "\n")  # one line per kind of task
    ax.set_xlabel(f"IQM of normalised score\n{scale_lines}\nline: 95% stratified bootstrap confidence interval")
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")  # widen the image to a label longer than the axes
    plt.close(fig)


def plot_profiles(taus: np.ndarray, profiles: dict, path: str, normalisation: str = "DMC return / 1000"):
    """Performance profiles: the fraction of runs whose normalised score exceeds each threshold, shaded 95% CI."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    algos = algo_order(profiles)
    colors = colors_of(algos)
    fig, ax = plt.subplots(figsize=(6, 4))
    for algo in algos:
        fraction, low, high = profiles[algo]
        ax.plot(taus, fraction, color=colors[algo], label=algo, linewidth=2)
        ax.fill_between(taus, low, high, color=colors[algo], alpha=0.2, linewidth=0)
    scale_lines = normalisation.replace("; ", "\n")
    ax.set_xlabel(f"normalised score threshold tau\n{scale_lines}")
    ax.set_ylabel("fraction of runs with score > tau")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Performance profiles (95% stratified bootstrap CI)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def read_paper_table(path: str) -> dict:
    with open(path, newline="") as f:
        return {row["env_id"]: row for row in csv.DictReader(f)}


def read_paper_claims(path: str) -> dict:
    """{(env_id, baseline): improvement in %}: the paper's stated gains of OPARL over a baseline."""
    with open(path, newline="") as f:
        return {(row["env_id"], row["baseline"]): float(row["improvement_pct"]) for row in csv.DictReader(f)}


def read_random_scores(path: str) -> dict:
    if not os.path.isfile(path):
        fail(f"--random-scores {path}: no such file (tools/random_scores.py writes one)")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if not {"env_id", "random_return"} <= set(reader.fieldnames or []):
            fail(f"--random-scores {path}: needs the columns env_id and random_return")
        return {row["env_id"]: float(row["random_return"]) for row in reader}


def write_table(
    complete: dict,
    stats: dict,
    paper: dict,
    path: str,
    claims: dict = None,
    scales: dict = None,
    improvements: dict = None,
    reps: int = BOOTSTRAP_REPS,
    up_to: int = None,
):
    algos = algo_order({a for a, _ in complete})
    envs = sorted({e for _, e in complete})
    cell = {key: np.array([r.returns[-1] for r in group]) for key, group in complete.items() if group}
    steps = {key: int(group[0].steps[-1]) for key, group in complete.items() if group}
    budgets = sorted(set(steps.values()))
    paper = {env: row for env, row in paper.items() if env in envs}  # Table 1 has no MuJoCo rows
    paper_algos = [a for a in ("oparl", "redq", "sac", "td3") if any(f"{a}_mean" in row for row in paper.values())]
    lines = [
        f"Final evaluation return (mean +- sample std over seeds, ddof 1; seeds per cell in parentheses) at "
        f"{' / '.join(map(str, budgets))} steps."
    ]
    if up_to is not None:  # "final" is the last evaluation up to that step: the runs may have gone further
        lines[0] = lines[0].replace("Final evaluation return", f"Last evaluation return up to step {up_to} (--up-to)", 1)
    if len(budgets) > 1:  # an unfinished sweep, or a shorter arm: every comparison below sets unequal budgets side by side
        short = sorted((e, a) for (a, e), s in steps.items() if s < budgets[-1])
        lines.append(
            "Runs of different lengths: "
            + "; ".join(f"{a} on {e.removeprefix('dm_control/')} at {steps[(a, e)]}" for e, a in short)
            + f", the others at {budgets[-1]}. The average row, OPARL's percentages, the aggregate metrics and P(X > Y) "
            "compare them as if their budgets were equal."
        )
    grouped = sorted((a, e) for (a, e), group in complete.items() if any(r.seeds_per_process > 1 for r in group))
    if grouped:
        lines.append(
            "Trained several seeds a process (`--num-seeds`), the others one: "
            + "; ".join(
                f"{a} on {e.removeprefix('dm_control/')} seeds "
                + ", ".join(f"{r.seed} ({r.seeds_per_process})" for r in complete[(a, e)] if r.seeds_per_process > 1)
                for a, e in grouped
            )
            + " (seeds a process in parentheses)."
        )
    if paper:
        lines.append(
            "Columns marked *paper* are the paper's Table 1 (1M steps, +- its standard deviation over 10 trials), copied for "
            "reference: a different budget."
        )
    lines.append("")
    header = ["task", *algos, *(f"{a} *paper*" for a in paper_algos)]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for env in envs:
        means = {a: cell[(a, env)].mean() for a in algos if (a, env) in cell}
        best = max(means.values()) if means else None
        row = [env.removeprefix("dm_control/")]
        for a in algos:
            if (a, env) not in cell:
                row.append("")
                continue
            values = cell[(a, env)]
            text = f"{means[a]:.1f} +- {values.std(ddof=1):.1f} ({len(values)})" if len(values) > 1 else f"{means[a]:.1f} (1)"
            if len(budgets) > 1:
                text += f" at {steps[(a, env)]}"
            row.append(f"**{text}**" if means[a] == best and len(means) > 1 else text)
        for a in paper_algos:
            p = paper.get(env, {})
            row.append(f"{float(p[f'{a}_mean']):.1f} +- {float(p[f'{a}_std']):.1f}" if p.get(f"{a}_mean") else "")
        lines.append("| " + " | ".join(row) + " |")
    shared = [e for e in envs if all((a, e) in cell for a in algos)]
    averages = {a: np.mean([cell[(a, e)].mean() for e in shared]) for a in algos} if shared else {}
    if averages:
        row = [f"average ({len(shared)} tasks)"] + [f"{averages[a]:.1f}" for a in algos]
        for a in paper_algos:
            values = [float(paper[e][f"{a}_mean"]) for e in shared if e in paper]
            row.append(f"{np.mean(values):.1f}" if len(values) == len(shared) else "")
        lines.append("| " + " | ".join(row) + " |")
    if "oparl" in averages:
        lines.append("")
        for a in algos:
            if a != "oparl":
                lines.append(f"- OPARL vs {a}: {100 * (averages['oparl'] / averages[a] - 1):+.1f}% on the average row")
    seeds = sorted({r.seed for group in complete.values() for r in group})
    lines += [
        "",
        "Final evaluation return per seed:" if up_to is None else f"Last evaluation return up to step {up_to} per seed:",
        "",
        "| task | algorithm | " + " | ".join(f"seed {s}" for s in seeds) + " |",
        "|---|---|" + "---|" * len(seeds),
    ]
    for env in envs:
        for a in algos:
            by_seed = {r.seed: r.returns[-1] for r in complete.get((a, env), [])}
            if by_seed:
                lines.append(
                    f"| {env.removeprefix('dm_control/')} | {a} | "
                    + " | ".join(f"{by_seed[s]:.1f}" if s in by_seed else "" for s in seeds)
                    + " |"
                )
    baselines = [a for a in algos if a != "oparl"]
    if "oparl" in algos and baselines:
        claims = {key: value for key, value in (claims or {}).items() if key[0] in envs}
        lines += [
            "",
            "OPARL's final return against each baseline's, per task: OPARL mean / baseline mean - 1 (n/a where the baseline's mean is not positive)"
            + ("; the paper's claim, at 1M steps, in parentheses:" if claims else ":"),
            "",
        ]
        lines += ["| task | " + " | ".join(f"vs {b}" for b in baselines) + " |", "|---|" + "---|" * len(baselines)]
        for env in envs:
            if ("oparl", env) not in cell:
                continue
            row = []
            for b in baselines:
                text = (
                    f"{100 * (cell[('oparl', env)].mean() / cell[(b, env)].mean() - 1):+.1f}%"
                    if (b, env) in cell and cell[(b, env)].mean() > 0
                    else ("n/a" if (b, env) in cell else "")
                )
                row.append(text + (f" (paper: {claims[(env, b)]:+.2f}%)" if (env, b) in claims else ""))
            lines.append(f"| {env.removeprefix('dm_control/')} | " + " | ".join(row) + " |")
    if stats:
        scales = scales or {}
        normalisation = normalisation_text({env: scales[env] for env in envs if env in scales})
        kind = "DMC tasks" if normalisation == "DMC return / 1000" else "normalised tasks"
        lines += [
            "",
            f"Aggregate metrics of normalised scores ({normalisation}) over all runs of the {kind} every algorithm has finished, 95% stratified bootstrap CI:",
            "",
        ]
        lines += [
            "| algorithm | IQM | 95% CI | median | 95% CI | mean | 95% CI | optimality gap | 95% CI | tasks | runs |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for a in algo_order(stats):
            cells = [f"{value:.3f} | [{low:.3f}, {high:.3f}]" for value, low, high in (stats[a][m] for m in METRICS)]
            lines.append(f"| {a} | {' | '.join(cells)} | {stats[a]['tasks']} | {stats[a]['runs']} |")
        if improvements:
            lines += [
                "",
                "Probability of improvement P(X > Y): the chance that a run of X scores above a run of Y on the same task (ties "
                "count half), averaged over the same tasks, 95% stratified bootstrap CI:",
                "",
                "| X | Y | P(X > Y) | 95% CI |",
                "|---|---|---|---|",
            ]
            for (x, y), (p, low, high) in improvements.items():
                lines.append(f"| {x} | {y} | {p:.3f} | [{low:.3f}, {high:.3f}] |")
        lines += [
            "",
            "rliable's definitions: the IQM is the mean of the middle half of all runs' scores, the median and the mean are "
            "those of the per-task mean scores, the optimality gap is the mean shortfall of the runs' scores below 1. "
            f"Intervals: {reps} stratified bootstrap resamples, NumPy seed {BOOTSTRAP_SEED}.",
        ]
        scaled = [env for env in envs if env in scales and not env.startswith("dm_control/")]
        if scaled:
            lines += [
                "",
                "The scale of each task's normalised score (0: the random policy, 1: the best evaluation return of any run read):",
                "",
            ]
            lines += ["| task | random policy | best seen |", "|---|---|---|"] + [
                f"| {env} | {scales[env][0]:.1f} | {scales[env][1]:.1f} |" for env in scaled
            ]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def write_csvs(runs: list, series_path: str, final_path: str):
    runs = sorted(runs, key=lambda r: (r.algo, r.env_id, r.seed))
    with open(series_path, "w", newline="") as f:
        writer = csv.writer(f)
        grouped = any(r.seeds_per_process > 1 for r in runs)  # the column only where a run trained in a group
        writer.writerow(["algo", "env_id", "seed", "step", "episodic_return", *(["seeds_per_process"] if grouped else [])])
        for r in runs:
            writer.writerows(
                (r.algo, r.env_id, r.seed, int(s), f"{v:.4f}", *([r.seeds_per_process] if grouped else []))
                for s, v in zip(r.steps, r.returns)
            )
    with open(final_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["algo", "env_id", "seed", "steps", "final_return"])
        writer.writerows((r.algo, r.env_id, r.seed, int(r.steps[-1]), f"{r.returns[-1]:.4f}") for r in runs)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "sources",
        nargs="+",
        help="folders of TensorBoard runs (e.g. runs) and/or eval_series.csv files written by this script; a run found twice keeps its longer record (a warning if they differ)",
    )
    parser.add_argument("--out", default="results", help="output folder")
    parser.add_argument(
        "--prefix",
        default="",
        help="prefix of the figures' and table.md's names, e.g. ablation_ (the CSVs, of every run read, keep theirs)",
    )
    parser.add_argument("--algos", nargs="+", help="only these algorithms (names as in the table)")
    parser.add_argument("--env-ids", nargs="+", help="only these environments")
    parser.add_argument(
        "--paper-table", default=PAPER_TABLE, help="the paper's Table 1 as CSV (default: paper/paper_table1.csv)"
    )
    parser.add_argument(
        "--paper-claims",
        default=PAPER_CLAIMS,
        help="the paper's stated gains of OPARL over each baseline, as CSV (default: paper/paper_mujoco_claims.csv)",
    )
    parser.add_argument("--no-paper", action="store_true", help="leave out the paper's numbers")
    parser.add_argument(
        "--random-scores",
        help="CSV of env_id,random_return (tools/random_scores.py): normalise those non-DMC tasks from the random policy (0) to the best evaluation seen (1) for the IQM",
    )
    parser.add_argument(
        "--smoothing",
        type=int,
        default=SMOOTHING,
        help="trailing window of the curves, in evaluations (1: raw curves); the table and IQM use the raw final evaluation",
    )
    parser.add_argument("--finished-only", action="store_true", help="from runs folders, only runs benchmark.sh marked DONE")
    parser.add_argument(
        "--up-to",
        type=int,
        metavar="STEP",
        help="read the runs at STEP: the table, IQM and curves from each run's evaluations up to STEP, the runs that have not reached it left out (an unfinished sweep compared where its runs all are); the CSVs keep every evaluation",
    )
    parser.add_argument(
        "--bootstrap-reps",
        type=int,
        default=BOOTSTRAP_REPS,
        help=f"stratified bootstrap resamples behind every interval (default {BOOTSTRAP_REPS}); the committed results use the default",
    )
    args = parser.parse_args(argv)
    if args.smoothing < 1:
        fail(f"--smoothing must be a whole number of evaluations >= 1 (1 draws the raw curves), got {args.smoothing}")
    if args.up_to is not None and args.up_to < 0:
        fail(f"--up-to must be a step >= 0, got {args.up_to}")
    if args.bootstrap_reps < 100:
        fail(f"--bootstrap-reps must be >= 100 (a 95% interval needs the tails of many resamples), got {args.bootstrap_reps}")

    merged = {}
    for source in args.sources:
        found = (
            read_csv(source)
            if os.path.isfile(source) and source.endswith(".csv")
            else read_tensorboard(source, args.finished_only)
        )
        for run in found:
            key = (run.algo, run.env_id, run.seed)
            earlier = merged.setdefault(key, run)
            if earlier is not run:  # found twice: the longer record stays
                merged[key] = run if len(run.steps) > len(earlier.steps) else earlier
                if not same_record(run, earlier):
                    warn(
                        f"two different runs of {run.algo} on {run.env_id} seed {run.seed} ({earlier.source}, {run.source}): kept {merged[key].source}"
                    )
    if not merged:
        fail(f"no finished run (with a DONE marker) in {', '.join(args.sources)}")
    runs = all_runs = list(merged.values())
    for name, wanted, key in [("--algos", args.algos, "algo"), ("--env-ids", args.env_ids, "env_id")]:
        if wanted:
            unknown = set(wanted) - {getattr(r, key) for r in runs}
            if unknown:
                fail(
                    f"{name}: {', '.join(sorted(unknown))} not found; the runs have {', '.join(sorted({getattr(r, key) for r in runs}))}"
                )
            runs = [r for r in runs if getattr(r, key) in wanted]
    if args.up_to is not None:
        runs = runs_up_to(runs, args.up_to)
    paper = {} if args.no_paper or not os.path.isfile(args.paper_table) else read_paper_table(args.paper_table)
    claims = {} if args.no_paper or not os.path.isfile(args.paper_claims) else read_paper_claims(args.paper_claims)
    scales = score_scales(all_runs, read_random_scores(args.random_scores) if args.random_scores else {})

    os.makedirs(args.out, exist_ok=True)
    out = lambda name: os.path.join(args.out, args.prefix + name)  # noqa: E731
    complete = complete_runs(runs)
    stats, matrices = aggregate(complete, algo_order({a for a, _ in complete}), scales, args.bootstrap_reps)
    improvements = probabilities_of_improvement(matrices, args.bootstrap_reps)
    plot_curves(runs, out("curves.png"), args.smoothing)
    write_table(complete, stats, paper, out("table.md"), claims, scales, improvements, args.bootstrap_reps, args.up_to)
    figures = ["curves.png"]
    if stats:
        normalisation = normalisation_text({env: scales[env] for _, env in complete if env in scales})
        plot_iqm(stats, out("iqm.png"), normalisation)
        plot_profiles(*performance_profiles(matrices, args.bootstrap_reps), out("profiles.png"), normalisation)
        figures += ["iqm.png", "profiles.png"]
    else:
        print(
            "no normalisable task among the runs, so no IQM plot (DMC returns are normalised by 1000; give --random-scores for other tasks)"
        )
    write_csvs(all_runs, os.path.join(args.out, "eval_series.csv"), os.path.join(args.out, "final_returns.csv"))
    written = [out(name) for name in [figures[0], "table.md", *figures[1:]]]
    written += [os.path.join(args.out, name) for name in ("eval_series.csv", "final_returns.csv")]
    print(
        f"{len(runs)} runs of {len({r.algo for r in runs})} algorithm(s) on {len({r.env_id for r in runs})} env(s) -> {', '.join(written)}"
    )


if __name__ == "__main__":
    main()
