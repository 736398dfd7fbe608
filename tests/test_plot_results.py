"""plot_results.py on synthetic TensorBoard logs with known values."""

import os
import time

import numpy as np
import pytest
from torch.utils.tensorboard import SummaryWriter

import plot_results as pr

DMC_A, DMC_B = "dm_control/cartpole-swingup-v0", "dm_control/walker-walk-v0"


def plot(argv: list):
    """plot_results.py's command line with 200 bootstrap resamples (the default's 2000 take seconds per call)."""
    pr.main(argv if "--bootstrap-reps" in argv else [*argv, "--bootstrap-reps", "200"])


def write_run(root, exp_name, env_id, seed, returns, every=5000, **params):
    """A run folder as the scripts write it: the hyperparameter table and eval/episodic_return."""
    run_dir = os.path.join(
        root, f"{env_id.replace('/', '-')}__{exp_name}__{seed}__{'_'.join(f'{k}{v}' for k, v in params.items())}"
    )
    writer = SummaryWriter(run_dir)
    table = {
        "exp_name": exp_name,
        "seed": seed,
        "env_id": env_id,
        "run_name": os.path.basename(run_dir),
        "gamma": 0.99,
        **params,
    }
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in table.items()))
    for i, value in enumerate(returns):
        writer.add_scalar("eval/episodic_return", value, i * every)
    writer.close()
    return run_dir


@pytest.fixture
def sweep(tmp_path):
    root = str(tmp_path / "runs")
    # final returns: oparl [100, 200, 300] on A, td3 [50, 50, 50] on A; on B oparl [900, 900, 900], td3 [600, 700, 800]
    for seed, (oa, ta, ob, tb) in enumerate([(100, 50, 900, 600), (200, 50, 900, 700), (300, 50, 900, 800)], start=1):
        write_run(root, "oparl_continuous_action", DMC_A, seed, [0, 10, oa])
        write_run(root, "td3_continuous_action", DMC_A, seed, [0, 20, ta])
        write_run(root, "oparl_continuous_action", DMC_B, seed, [0, 30, ob])
        write_run(root, "td3_continuous_action", DMC_B, seed, [0, 40, tb])
    return root


def test_table_has_mean_std_best_average_and_improvement(sweep, tmp_path):
    out = str(tmp_path / "out")
    plot([sweep, "--out", out, "--no-paper"])
    table = open(os.path.join(out, "table.md")).read()
    # the sample standard deviation (ddof 1): 100 for 100, 200, 300 (the population's would be 81.6)
    assert "| cartpole-swingup-v0 | **200.0 +- 100.0 (3)** | 50.0 +- 0.0 (3) |" in table
    assert "| walker-walk-v0 | **900.0 +- 0.0 (3)** | 700.0 +- 100.0 (3) |" in table
    assert "mean +- sample std over seeds, ddof 1" in table
    assert "| average (2 tasks) | 550.0 | 375.0 |" in table
    assert "OPARL vs td3: +46.7% on the average row" in table
    for name in ("curves.png", "iqm.png", "eval_series.csv", "final_returns.csv"):
        assert os.path.getsize(os.path.join(out, name)) > 0


def test_one_seed_gets_no_spread_and_the_curves_band_is_the_sample_std(tmp_path):
    root = str(tmp_path / "runs")
    write_run(root, "td3_continuous_action", DMC_A, 1, [0, 10, 40])
    plot([root, "--out", str(tmp_path / "out"), "--no-paper"])
    assert "| cartpole-swingup-v0 | 40.0 (1) |" in open(tmp_path / "out" / "table.md").read()
    curves = np.array([[1.0, 2.0, np.nan], [3.0, 5.0, 7.0]])  # the third step reached by one run alone
    np.testing.assert_allclose(pr.sample_std(curves), [np.sqrt(2), np.sqrt(4.5), 0.0])


def test_final_returns_csv_has_one_row_per_run(sweep, tmp_path):
    out = str(tmp_path / "out")
    plot([sweep, "--out", out, "--no-paper"])
    rows = open(os.path.join(out, "final_returns.csv")).read().splitlines()
    assert rows[0] == "algo,env_id,seed,steps,final_return" and len(rows) == 13
    assert "oparl,dm_control/cartpole-swingup-v0,3,10000,300.0000" in rows


def test_the_csv_alone_regenerates_every_file(sweep, tmp_path):
    first, second = str(tmp_path / "first"), str(tmp_path / "second")
    plot([sweep, "--out", first])
    plot([os.path.join(first, "eval_series.csv"), "--out", second])
    for name in ("table.md", "eval_series.csv", "final_returns.csv"):
        assert open(os.path.join(first, name)).read() == open(os.path.join(second, name)).read()


def test_paper_columns_come_from_the_paper_table(sweep, tmp_path):
    out = str(tmp_path / "out")
    plot([sweep, "--out", out])
    table = open(os.path.join(out, "table.md")).read()
    assert "oparl *paper*" in table and "874.6 +- 7.5" in table and "975.3 +- 2.9" in table
    assert "the paper's Table 1" in table


def iqm_by_hand(scores) -> float:
    """The mean of the middle half, a quarter cut from each end (as the IQM this script computed before rliable)."""
    x = np.sort(np.ravel(scores))
    cut = int(0.25 * len(x))
    return float(x[cut : len(x) - cut].mean())


def test_rliables_iqm_is_the_mean_of_the_middle_half():
    for scores in ([0.1, 0.2, 0.3, 0.4], [5.0, 0.0, 1.0, 2.0, 3.0, 4.0, 100.0, -50.0], [1.0, 2.0, 3.0, 4.0, 5.0]):
        iqm = pr.aggregate_metrics(np.array(scores)[:, None])[pr.METRICS.index("iqm")]
        assert iqm == pytest.approx(iqm_by_hand(scores))
    assert iqm_by_hand([5.0, 0.0, 1.0, 2.0, 3.0, 4.0, 100.0, -50.0]) == pytest.approx(2.5)  # middle four: 1, 2, 3, 4


def test_iqm_of_the_committed_main_results_is_unchanged_by_rliable():
    """The IQM point estimates of results/main equal those of the hand-written NumPy this script used before."""
    runs = pr.read_csv(os.path.join(os.path.dirname(pr.__file__), "results", "main", "eval_series.csv"))
    complete = pr.complete_runs(runs)
    algos = pr.algo_order({a for a, _ in complete})
    stats, matrices = pr.aggregate(complete, algos, pr.score_scales(runs, {}), reps=100)
    assert set(stats) == {"oparl", "td3", "sac"}
    for algo in algos:
        assert matrices[algo].shape == (3, 18)  # 3 seeds x Table 1's 18 DMC tasks (Hopper-v4 has no normalisation here)
        assert stats[algo]["iqm"][0] == pytest.approx(iqm_by_hand(matrices[algo]), abs=1e-12)
    # the values the README and docs/results.md give
    assert [round(stats[a]["iqm"][0], 3) for a in ("oparl", "td3", "sac")] == [0.367, 0.363, 0.668]


def test_bootstrap_ci_of_two_runs_spans_both_by_hand():
    # one task, runs [0, 1]: resamples {0,0}, {0,1}, {1,0}, {1,1} -> IQM 0, .5, .5, 1 with probability 1/4 each
    points, intervals = pr.interval_estimates(np.array([[0.0], [1.0]]), pr.aggregate_metrics, reps=4000)
    assert points[0] == 0.5 and tuple(intervals[:, 0]) == (0.0, 1.0)


def test_bootstrap_is_stratified_by_task():
    # within each task the runs agree, so resampling within tasks never changes the pooled scores
    scores = np.array([[0.2, 0.8, 0.5]] * 3)
    points, intervals = pr.interval_estimates(scores, pr.aggregate_metrics)
    np.testing.assert_array_equal(intervals, np.stack([points, points]))


def test_the_bootstrap_is_seeded():
    scores = np.random.default_rng(1).random((3, 4))
    np.random.seed(123)  # whatever state the global generator is in
    first = pr.interval_estimates(scores, pr.aggregate_metrics)[1]
    np.random.random(7)
    np.testing.assert_array_equal(pr.interval_estimates(scores, pr.aggregate_metrics)[1], first)


def test_probability_of_improvement_of_identical_and_dominating_algorithms():
    rng = np.random.default_rng(0)
    a, better = rng.random((3, 5)), rng.random((3, 5)) + 2.0
    matrices = {"oparl": a, "td3": a.copy(), "sac": better, "oparl_variant": a - 5.0}
    result = pr.probabilities_of_improvement(matrices, reps=200)
    p, low, high = result[("oparl", "td3")]
    assert p == 0.5 and low < 0.5 < high and low == pytest.approx(1 - high, abs=0.05)  # identical: 0.5, resampled either way
    assert result[("oparl", "sac")] == (0.0, 0.0, 0.0)  # every run of sac above every run of oparl
    assert result[("oparl_variant", "oparl")] == (0.0, 0.0, 0.0)  # a variant is compared against OPARL
    assert set(result) == {("oparl", "td3"), ("oparl", "sac"), ("oparl_variant", "oparl")}
    half = pr.probabilities_of_improvement({"oparl": np.array([[1.0], [3.0]]), "td3": np.array([[2.0], [2.0]])}, reps=200)
    assert half[("oparl", "td3")][0] == 0.5  # one of two OPARL runs above both TD3 runs


def test_probability_of_improvement_rows_in_the_table(sweep, tmp_path):
    out = str(tmp_path / "out")
    plot([sweep, "--out", out, "--no-paper", "--bootstrap-reps", "200"])
    table = open(os.path.join(out, "table.md")).read()
    # cartpole: oparl 100, 200, 300 against td3 50, 50, 50: 1; walker: 900 x3 against 600, 700, 800: 1
    assert "| oparl | td3 | 1.000 | [1.000, 1.000] |" in table
    assert "Intervals: 200 stratified bootstrap resamples" in table
    assert os.path.getsize(os.path.join(out, "profiles.png")) > 0


def test_performance_profile_is_the_fraction_of_runs_above_each_threshold():
    taus, profiles = pr.performance_profiles({"oparl": np.array([[0.1, 0.5], [0.3, 0.9]])}, reps=200)
    assert taus[0] == 0.0 and taus[-1] == 1.0
    fraction = profiles["oparl"][0]
    assert fraction[np.searchsorted(taus, 0.2)] == 0.75 and fraction[np.searchsorted(taus, 0.6)] == 0.25
    assert (np.diff(fraction) <= 0).all()


def test_iqm_rows_in_the_table(sweep, tmp_path):
    out = str(tmp_path / "out")
    plot([sweep, "--out", out, "--no-paper"])
    table = open(os.path.join(out, "table.md")).read()
    # oparl scores: .1 .2 .3 .9 .9 .9 -> middle half .3 .9 .9 (int(0.25*6) = 1 cut each end: .2 .3 .9 .9)
    assert f"| oparl | {np.mean([0.2, 0.3, 0.9, 0.9]):.3f} |" in table


def test_smoothing_is_a_trailing_window():
    np.testing.assert_allclose(pr.smooth(np.array([1.0, 2.0, 3.0, 4.0]), window=2), [1.0, 1.5, 2.5, 3.5])
    np.testing.assert_allclose(pr.smooth(np.arange(12.0))[-1], np.mean(np.arange(2.0, 12.0)))


def test_iqm_compares_algorithms_on_the_same_tasks(sweep, tmp_path, capsys):
    # a third task that only oparl has finished must not enter oparl's IQM
    for seed in (1, 2, 3):
        write_run(sweep, "oparl_continuous_action", "dm_control/finger-spin-v0", seed, [0, 0])
    out = str(tmp_path / "out")
    plot([sweep, "--out", out, "--no-paper"])
    assert "IQM only over the DMC tasks every algorithm has finished (2); left out: finger-spin-v0" in capsys.readouterr().err
    table = open(os.path.join(out, "table.md")).read()
    assert f"| oparl | {np.mean([0.2, 0.3, 0.9, 0.9]):.3f} |" in table and "| 2 | 6 |" in table


def test_smoothing_window_is_a_flag(sweep, tmp_path, monkeypatch):
    windows = []
    real = pr.smooth
    monkeypatch.setattr(pr, "smooth", lambda values, window=pr.SMOOTHING: windows.append(window) or real(values, window))
    plot([sweep, "--out", str(tmp_path / "a"), "--no-paper", "--smoothing", "3"])
    assert windows and set(windows) == {3}
    with pytest.raises(SystemExit, match="--smoothing must be a whole number of evaluations >= 1"):
        plot([sweep, "--out", str(tmp_path / "b"), "--smoothing", "0"])


def test_variants_of_one_script_are_told_apart(tmp_path):
    root = str(tmp_path / "runs")
    for seed in (1, 2):
        write_run(root, "oparl_continuous_action", DMC_A, seed, [0, 100], q_num=5)
        write_run(root, "oparl_continuous_action", DMC_A, seed, [0, 50], q_num=2)
    runs = pr.read_tensorboard(root)
    assert sorted({r.algo for r in runs}) == ["oparl (q_num=2)", "oparl (q_num=5)"]


def test_a_seed_trained_in_a_group_counts_as_its_algorithm_and_the_table_says_so(tmp_path):
    # benchmark.sh --gpu trains seeds in groups (--num-seeds 2) that a sweep sets beside one-seed CPU runs
    root = str(tmp_path / "runs")
    write_run(root, "td3_continuous_action", DMC_A, 1, [0, 100], num_seeds=1)
    for seed in (2, 3):
        write_run(root, "td3_continuous_action", DMC_A, seed, [0, 50], num_seeds=2)
    runs = pr.read_tensorboard(root)
    assert [r.algo for r in runs] == ["td3"] * 3
    said = "Trained several seeds a process (`--num-seeds`), the others one: td3 on cartpole-swingup-v0 seeds 2 (2), 3 (2)"
    plot([root, "--no-paper", "--out", str(tmp_path / "out")])
    assert said in open(tmp_path / "out" / "table.md").read()
    # the CSV keeps it, so a folder regenerated from its eval_series.csv says it too
    plot([str(tmp_path / "out" / "eval_series.csv"), "--no-paper", "--out", str(tmp_path / "again")])
    assert said in open(tmp_path / "again" / "table.md").read()
    # and a table of one-seed runs neither says it nor gains the column
    one = str(tmp_path / "one")
    write_run(one, "td3_continuous_action", DMC_A, 1, [0, 100], num_seeds=1)
    plot([one, "--no-paper", "--out", str(tmp_path / "single")])
    assert "several seeds" not in open(tmp_path / "single" / "table.md").read()
    assert open(tmp_path / "single" / "eval_series.csv").readline().strip() == "algo,env_id,seed,step,episodic_return"


def test_two_different_records_of_one_run_are_warned_about(tmp_path, capsys):
    root = str(tmp_path / "runs")
    write_run(root, "td3_continuous_action", DMC_A, 1, [0, 100], num_seeds=1)
    write_run(root, "td3_continuous_action", DMC_A, 1, [0, 900], num_seeds=3)  # seed 1 again, in a group
    plot([root, "--no-paper", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert "warning: two different runs of td3 on dm_control/cartpole-swingup-v0 seed 1" in err
    # the same run read twice (its CSV and its folder, the folder's record longer: a resumed run) is no warning
    one = str(tmp_path / "one")
    run_dir = write_run(one, "td3_continuous_action", DMC_A, 1, [0, 100])
    plot([one, "--no-paper", "--out", str(tmp_path / "short")])
    # resumed as the scripts resume (rl_utils/logs.py): a later process, whose event file's name (its second) sorts after
    # the first's, with purge_step at the checkpoint. In one second the names would sort by a counter as text ("10" before
    # "9") and TensorBoard would read the two files the other way round.
    time.sleep(1.0)
    with SummaryWriter(run_dir, purge_step=5000) as writer:
        writer.add_scalar("eval/episodic_return", 100, 5000)
        writer.add_scalar("eval/episodic_return", 300, 10000)
    plot([str(tmp_path / "short" / "eval_series.csv"), one, "--no-paper", "--out", str(tmp_path / "long")])
    assert "two different runs" not in capsys.readouterr().err
    assert open(tmp_path / "long" / "final_returns.csv").read().splitlines()[1].endswith(",10000,300.0000")


def test_cut_short_runs_are_named_and_left_out_of_the_table(tmp_path, capsys):
    root = str(tmp_path / "runs")
    write_run(root, "td3_continuous_action", DMC_A, 1, [0, 10, 30])
    write_run(root, "td3_continuous_action", DMC_A, 2, [0, 20, 50])
    write_run(root, "td3_continuous_action", DMC_A, 3, [0, 15])
    out = str(tmp_path / "out")
    plot([root, "--out", out, "--no-paper"])
    err = capsys.readouterr().err
    assert "cut short before step 10000" in err and "seed 3 (at 5000)" in err
    table = open(os.path.join(out, "table.md")).read()
    assert "40.0 +- 14.1 (2)" in table  # the sample std of 30 and 50
    assert "Runs of different lengths" not in table  # every run in the table reached 10000


def test_a_table_of_runs_of_different_lengths_says_which_are_shorter(tmp_path):
    """An unfinished sweep: each algorithm's runs at its furthest step, and a line naming the shorter ones, since every
    comparison of the table then sets unequal budgets side by side."""
    root = str(tmp_path / "runs")
    for seed in (1, 2):
        write_run(root, "td3_continuous_action", DMC_A, seed, [0, 10, 30])
        write_run(root, "td3_continuous_action", DMC_B, seed, [0, 10, 30])
        write_run(root, "oparl_continuous_action", DMC_B, seed, [0, 10, 30])
    write_run(root, "oparl_continuous_action", DMC_A, 1, [0, 20])
    plot([root, "--out", str(tmp_path / "out"), "--no-paper"])
    lines = open(tmp_path / "out" / "table.md").read().splitlines()
    assert lines[0].endswith("at 5000 / 10000 steps.")
    assert lines[1].startswith("Runs of different lengths: oparl on cartpole-swingup-v0 at 5000, the others at 10000.")


@pytest.mark.parametrize(
    "setup, message",
    [
        (lambda root: None, "no such folder"),
        (lambda root: os.makedirs(root), "holds no TensorBoard runs"),
    ],
)
def test_missing_or_empty_runs_folder(setup, message, tmp_path):
    root = str(tmp_path / "runs")
    setup(root)
    with pytest.raises(SystemExit, match=message):
        plot([root, "--out", str(tmp_path / "out")])


def test_runs_without_evaluations_are_reported(tmp_path, capsys):
    root = str(tmp_path / "runs")
    writer = SummaryWriter(os.path.join(root, "no_eval"))
    writer.add_scalar("charts/SPS", 100.0, 0)
    writer.close()
    with pytest.raises(SystemExit, match="no run under .* logged eval/episodic_return"):
        plot([root, "--out", str(tmp_path / "out")])
    assert "have no eval/episodic_return and are left out" in capsys.readouterr().err


def test_foreign_csv_is_refused(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("a,b\n1,2\n")
    with pytest.raises(SystemExit, match="lacks the column"):
        plot([str(path), "--out", str(tmp_path / "out")])


def test_filters_name_what_exists(sweep, tmp_path):
    with pytest.raises(SystemExit, match="--algos: redq not found; the runs have oparl, td3"):
        plot([sweep, "--out", str(tmp_path / "out"), "--algos", "redq"])


def test_sources_merge_and_finished_only_skips_unmarked_runs(sweep, tmp_path, capsys):
    first = str(tmp_path / "first")
    plot([sweep, "--out", first, "--no-paper", "--env-ids", DMC_A])
    more = str(tmp_path / "more")
    done = write_run(more, "sac_continuous_action", DMC_A, 1, [0, 5, 7])
    open(os.path.join(done, "DONE"), "w").close()
    write_run(more, "sac_continuous_action", DMC_A, 2, [0, 5])  # still running: no DONE
    merged = str(tmp_path / "merged")
    plot([os.path.join(first, "eval_series.csv"), more, "--finished-only", "--out", merged, "--no-paper"])
    assert "leaving out 1 unfinished run(s)" in capsys.readouterr().out
    rows = open(os.path.join(merged, "final_returns.csv")).read().splitlines()
    assert len(rows) == 1 + 12 + 1 and "sac,dm_control/cartpole-swingup-v0,1,10000,7.0000" in rows


def test_selection_shapes_the_figures_but_the_csvs_keep_every_run(sweep, tmp_path):
    out = str(tmp_path / "out")
    plot([sweep, "--out", out, "--no-paper", "--algos", "td3", "--prefix", "td3_"])
    assert "oparl" not in open(os.path.join(out, "td3_table.md")).read()
    assert len(open(os.path.join(out, "final_returns.csv")).read().splitlines()) == 13
    assert not os.path.exists(os.path.join(out, "td3_final_returns.csv"))


def test_each_paper_system_keeps_its_colour_and_other_names_keep_one_of_their_own():
    assert pr.colors_of(["oparl", "rnd", "ebd"]) == {"oparl": "C0", "rnd": "C4", "ebd": "C5"}
    assert pr.colors_of(["ebd", "ppo", "td3"]) == {"ebd": "C5", "ppo": "C3", "td3": "C1"}
    # a new script or a variant: the same colour in every figure, none of the paper systems'
    alone = pr.colors_of(["ddpg"])["ddpg"]
    assert alone not in pr.PAPER_COLORS.values()
    assert pr.colors_of(["oparl", "td3", "sac", "ddpg"])["ddpg"] == alone == pr.colors_of(["ppo", "ddpg", "rnd"])["ddpg"]
    variants = ["oparl_optimistic_only", "oparl_pessimistic_only", "oparl_two_critics"]
    ablation = pr.colors_of(["oparl", *variants])
    assert len(set(ablation.values())) == 4 and ablation["oparl"] == "C0"
    assert all(pr.colors_of(["oparl", v])[v] == ablation[v] for v in variants)
    many = pr.colors_of([f"variant_{i}" for i in range(len(pr.OTHER_COLORS))])
    assert len(set(many.values())) == len(pr.OTHER_COLORS)  # two names never share a colour while one is free


def test_table_lists_every_final_return_per_seed(sweep, tmp_path):
    out = str(tmp_path / "out")
    plot([sweep, "--out", out, "--no-paper"])
    table = open(os.path.join(out, "table.md")).read()
    assert "| task | algorithm | seed 1 | seed 2 | seed 3 |" in table
    assert "| cartpole-swingup-v0 | oparl | 100.0 | 200.0 | 300.0 |" in table
    assert "| walker-walk-v0 | td3 | 600.0 | 700.0 | 800.0 |" in table


def test_run_folders_picked_one_by_one_merge_and_unfinished_ones_are_left_out(sweep, tmp_path, capsys):
    run_dirs = sorted(os.path.join(sweep, d) for d in os.listdir(sweep))
    for run_dir in run_dirs[:-1]:
        open(os.path.join(run_dir, "DONE"), "w").close()
    out = str(tmp_path / "out")
    plot([*run_dirs, "--finished-only", "--out", out, "--no-paper"])  # the last folder alone has no finished run
    assert len(open(os.path.join(out, "final_returns.csv")).read().splitlines()) == 1 + len(run_dirs) - 1
    with pytest.raises(SystemExit, match="no finished run"):
        plot([run_dirs[-1], "--finished-only", "--out", out, "--no-paper"])


@pytest.fixture
def mujoco_sweep(tmp_path):
    """Final returns on Ant-v4: oparl [300, 300], td3 [100, 200] (mean 150), ppo [-20, -10]; the best evaluation seen is 400."""
    root = str(tmp_path / "mujoco")
    for seed, (o, t, p) in enumerate([(300, 100, -20), (300, 200, -10)], start=1):
        write_run(root, "oparl_continuous_action", "Ant-v4", seed, [0, 400 if seed == 1 else 0, o])
        write_run(root, "td3_continuous_action", "Ant-v4", seed, [0, 50, t])
        write_run(root, "ppo_continuous_action", "Ant-v4", seed, [0, -5, p])
    scores = tmp_path / "random.csv"
    scores.write_text("env_id,random_return,episodes\nAnt-v4,-100.0,10\n")
    return root, str(scores)


def test_non_dmc_tasks_are_normalised_from_the_random_policy_to_the_best_seen(mujoco_sweep, tmp_path):
    root, scores = mujoco_sweep
    out = str(tmp_path / "out")
    plot([root, "--out", out, "--no-paper", "--random-scores", scores])
    table = open(os.path.join(out, "table.md")).read()
    # (300 + 100) / (400 + 100) = 0.8 for both oparl runs; td3 (100 + 100) / 500 = 0.4 and (200 + 100) / 500 = 0.6
    assert (
        "| oparl | 0.800 | [0.800, 0.800] | 0.800 | [0.800, 0.800] | 0.800 | [0.800, 0.800] | 0.200 | [0.200, 0.200] | 1 | 2 |"
        in table
    )
    assert "| td3 | 0.500 |" in table
    assert "(return - random policy) / (best seen - random policy)" in table
    assert "| Ant-v4 | -100.0 | 400.0 |" in table
    assert os.path.exists(os.path.join(out, "iqm.png"))


def test_without_random_scores_a_mujoco_task_gets_no_iqm(mujoco_sweep, tmp_path, capsys):
    root, _ = mujoco_sweep
    out = str(tmp_path / "out")
    plot([root, "--out", out, "--no-paper"])
    assert "Aggregate metrics" not in open(os.path.join(out, "table.md")).read()
    assert not os.path.exists(os.path.join(out, "profiles.png"))
    assert "no normalisable task" in capsys.readouterr().out


def test_oparls_gain_over_each_baseline_per_task_beside_the_papers_claim(mujoco_sweep, tmp_path):
    root, _ = mujoco_sweep
    claims = tmp_path / "claims.csv"
    claims.write_text("env_id,baseline,improvement_pct,source\nAnt-v4,td3,51.25,x\n")
    out = str(tmp_path / "out")
    plot([root, "--out", out, "--paper-claims", str(claims)])
    table = open(os.path.join(out, "table.md")).read()
    # 300 / 150 - 1 = +100%; PPO's mean is negative: no percentage
    assert "| Ant-v4 | n/a | +100.0% (paper: +51.25%) |" in table
    # the paper's Table 1 (DMC only) has no Ant-v4 row, so no empty *paper* columns
    assert "*paper*" not in table and "the paper's Table 1" not in table


def test_random_scores_file_errors_are_one_line(mujoco_sweep, tmp_path):
    root, _ = mujoco_sweep
    bad = tmp_path / "bad.csv"
    bad.write_text("env,score\nAnt-v4,1\n")
    for path, message in [
        (str(tmp_path / "missing.csv"), "no such file"),
        (str(bad), "needs the columns env_id and random_return"),
    ]:
        with pytest.raises(SystemExit, match=message):
            plot([root, "--out", str(tmp_path / "out"), "--random-scores", path])


def test_iqm_figure_widens_to_a_label_longer_than_the_axes(tmp_path):
    import matplotlib.image

    stats = {"oparl": {"iqm": (0.5, 0.4, 0.6), "tasks": 2, "runs": 6}, "td3": {"iqm": (0.3, 0.2, 0.4), "tasks": 2, "runs": 6}}
    short, long = str(tmp_path / "short.png"), str(tmp_path / "long.png")
    pr.plot_iqm(stats, short, normalisation="DMC return / 1000")
    pr.plot_iqm(stats, long, normalisation="a very long description of how some other kind of task is normalised " * 2)
    short_width, long_width = (matplotlib.image.imread(path).shape[1] for path in (short, long))
    assert long_width > short_width + 200  # the whole label is in the image, not cut at the figure's edge


def test_a_committed_folder_regenerates_byte_for_byte(tmp_path):
    """results/release from its own CSV with its documented command: the text files come back byte for byte, the
    figures pixel for pixel to within one level of antialiasing. A PNG's bytes are not compared: the compressor
    Pillow bundles picks its code path by CPU, and a coordinate's last bit (another CPU's BLAS) may shade an edge's
    pixel one level differently, so bytes recorded on one machine are not another machine's (docs/tests.md)."""
    folder = os.path.join(os.path.dirname(pr.__file__), "results", "release")
    plot(
        [
            os.path.join(folder, "eval_series.csv"),
            "--no-paper",
            "--smoothing",
            "3",
            "--out",
            str(tmp_path),
            "--bootstrap-reps",
            "2000",
        ]
    )
    for name in ("table.md", "eval_series.csv", "final_returns.csv"):
        assert (tmp_path / name).read_bytes() == open(os.path.join(folder, name), "rb").read(), name
    for name in ("curves.png", "iqm.png", "profiles.png"):
        assert same_picture(str(tmp_path / name), os.path.join(folder, name)), name


def same_picture(a: str, b: str) -> bool:
    """Two PNG files show the same picture: the same size, and no pixel's channel more than one level (of 255) apart."""
    import matplotlib.image

    first, second = (np.asarray(matplotlib.image.imread(path), dtype=np.float64) for path in (a, b))
    return first.shape == second.shape and float(np.abs(first - second).max()) <= 1.5 / 255


def test_same_picture_tells_a_changed_figure_from_another_compression(tmp_path):
    import matplotlib.image
    from PIL import Image

    picture = (np.arange(40 * 60 * 3).reshape(40, 60, 3) % 251).astype(np.uint8)
    Image.fromarray(picture).save(tmp_path / "a.png", compress_level=9)
    Image.fromarray(picture).save(tmp_path / "b.png", compress_level=1)  # other bytes, the same pixels
    assert (tmp_path / "a.png").read_bytes() != (tmp_path / "b.png").read_bytes()
    assert same_picture(str(tmp_path / "a.png"), str(tmp_path / "b.png"))
    shaded = picture.copy()
    shaded[10, 10, 0] += 1  # an edge pixel one level lighter
    Image.fromarray(shaded).save(tmp_path / "c.png")
    assert same_picture(str(tmp_path / "a.png"), str(tmp_path / "c.png"))
    moved = picture.copy()
    moved[10, 10:20] = 255  # a short stretch of a line drawn elsewhere
    Image.fromarray(moved).save(tmp_path / "d.png")
    assert not same_picture(str(tmp_path / "a.png"), str(tmp_path / "d.png"))
    matplotlib.image.imsave(tmp_path / "e.png", picture[:, :50])  # another size
    assert not same_picture(str(tmp_path / "a.png"), str(tmp_path / "e.png"))


def test_too_few_bootstrap_resamples_are_refused(sweep, tmp_path):
    with pytest.raises(SystemExit, match="--bootstrap-reps must be >= 100"):
        pr.main([sweep, "--out", str(tmp_path), "--bootstrap-reps", "10"])


def test_flags_a_run_may_change_on_resume_do_not_name_an_algorithm():
    # a flag that a resumed run may change (it does not change what is learned) must not split one algorithm's runs
    # into two rows, e.g. OPARL's GPU runs with --cudagraphs beside its CPU runs
    from rl_utils.cli import RESUMABLE_FLAGS

    assert RESUMABLE_FLAGS <= pr.NOT_ALGORITHM


def test_up_to_reads_every_run_at_one_step_and_leaves_out_those_not_there(tmp_path, capsys):
    """An unfinished sweep read where its runs are: each run's evaluations up to --up-to, the runs short of it named
    and left out; the CSVs keep every evaluation of every run."""
    root = str(tmp_path / "runs")
    write_run(root, "td3_continuous_action", DMC_A, 1, [0, 10, 30, 70])  # finished, at 15000
    write_run(root, "td3_continuous_action", DMC_A, 2, [0, 20, 50, 90])
    write_run(root, "oparl_continuous_action", DMC_A, 1, [0, 40, 60])  # at 10000
    write_run(root, "oparl_continuous_action", DMC_A, 2, [0, 45])  # at 5000: not there yet
    out = str(tmp_path / "out")
    plot([root, "--out", out, "--no-paper", "--up-to", "10000"])
    assert "--up-to 10000: left out, not there yet: oparl on dm_control/cartpole-swingup-v0 seed 2 (at 5000)" in (
        capsys.readouterr().err
    )
    lines = open(os.path.join(out, "table.md")).read().splitlines()
    assert lines[0].startswith("Last evaluation return up to step 10000 (--up-to)") and lines[0].endswith("at 10000 steps.")
    assert "Runs of different lengths" not in lines[1] and "Last evaluation return up to step 10000 per seed:" in lines
    assert "| cartpole-swingup-v0 | **60.0 (1)** | 40.0 +- 14.1 (2) |" in lines  # td3 at 10000: 30 and 50
    final = open(os.path.join(out, "final_returns.csv")).read()
    assert (
        "td3,dm_control/cartpole-swingup-v0,1,15000,70.0" in final and "oparl,dm_control/cartpole-swingup-v0,2,5000" in final
    )
    with pytest.raises(SystemExit, match="--up-to 20000: no run has reached step 20000 \\(the furthest is at 15000\\)"):
        plot([root, "--out", out, "--no-paper", "--up-to", "20000"])
    with pytest.raises(SystemExit, match="--up-to must be a step >= 0, got -1"):
        plot([root, "--out", out, "--no-paper", "--up-to", "-1"])
