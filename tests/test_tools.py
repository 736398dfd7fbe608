"""The tools a user runs (tools/mkl_avx512.sh, random_scores.py, export_scalars.py, welch.py) run and report what
they say, on tiny settings. The speed- and memory-measuring tools in tools/speed/ are tests/test_speed_tools.py's."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO
import forkserver


def tool(name, *flags, timeout=600):
    return forkserver.run(
        [sys.executable, os.path.join(REPO, "tools", name), *flags], capture_output=True, text=True, timeout=timeout
    )


# float32 matmuls of a few shapes the scripts use; prints the preload, the largest error against
# float64 (per sqrt of the summed length) and a digest of the exact float32 bits, which tells one
# set of kernels from another
MATMUL_PROBE = """
import hashlib, os, torch
torch.manual_seed(0)
worst, digest = 0.0, hashlib.sha1()
for m, k, n in [(256, 256, 256), (256, 14, 256), (512, 256, 256)]:
    a, b = torch.randn(m, k), torch.randn(k, n)
    c = a @ b
    worst = max(worst, ((c.double() - a.double() @ b.double()).abs().max() / k**0.5).item())
    digest.update(c.numpy().tobytes())
print(os.environ.get("LD_PRELOAD", "-"), worst, digest.hexdigest())
"""


def mkl_avx512(tmp_path, *command):
    env = {**os.environ, "MKL_AVX512_BUILD_DIR": str(tmp_path / "build"), "OMP_NUM_THREADS": "1"}
    env.pop("LD_PRELOAD", None)
    return subprocess.run(
        ["bash", os.path.join(REPO, "tools", "mkl_avx512.sh"), *command], capture_output=True, text=True, env=env, timeout=300
    )


def amd_with_avx512():
    with open("/proc/cpuinfo") as f:
        cpuinfo = f.read()
    return "AuthenticAMD" in cpuinfo and " avx512f" in cpuinfo


def test_mkl_avx512_without_a_command_prints_usage(tmp_path):
    result = mkl_avx512(tmp_path)
    assert result.returncode == 2 and result.stderr.startswith("usage: bash tools/mkl_avx512.sh COMMAND")


def test_mkl_avx512_runs_the_command_with_its_arguments_and_exit_status(tmp_path):
    result = mkl_avx512(tmp_path, sys.executable, "-c", "import sys; print('ran', sys.argv[1:]); sys.exit(3)", "a b")
    assert result.returncode == 3 and result.stdout == "ran ['a b']\n"


def test_mkl_avx512_changes_the_kernels_not_the_results(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "LD_PRELOAD"}
    default = subprocess.run(
        [sys.executable, "-c", MATMUL_PROBE], capture_output=True, text=True, env={**env, "OMP_NUM_THREADS": "1"}, timeout=300
    )
    wrapped = mkl_avx512(tmp_path, sys.executable, "-c", MATMUL_PROBE)
    assert default.returncode == 0 and wrapped.returncode == 0, wrapped.stderr
    preload, worst, digest = wrapped.stdout.split()
    assert float(worst) < 1e-5 and float(default.stdout.split()[1]) < 1e-5  # float32 rounding, both
    if not amd_with_avx512():
        assert preload == "-" and "not an AMD CPU with AVX-512" in wrapped.stderr
    elif not (shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")):
        assert preload == "-" and "no C compiler" in wrapped.stderr
    else:
        assert preload == str(tmp_path / "build" / "libmkl_intel_cpu_true.so") and os.path.isfile(preload)
        assert wrapped.stderr == f"mkl_avx512: MKL's AVX-512 kernels (preloading {preload})\n"
        assert digest != default.stdout.split()[2]  # MKL took other kernels, which round otherwise


def test_random_scores_are_reproducible_means_of_random_episodes(tmp_path):
    sys.path.insert(0, os.path.join(REPO, "tools"))
    import random_scores

    first, second = tmp_path / "a.csv", tmp_path / "b.csv"
    random_scores.main(["Pendulum-v1", "--episodes", "3", "--out", str(first)])
    random_scores.main(["Pendulum-v1", "--episodes", "3", "--out", str(second)])
    assert first.read_text() == second.read_text()
    header, row = first.read_text().splitlines()
    assert header == "env_id,random_return,std,episodes,seed" and row.startswith("Pendulum-v1,")
    # a random policy on Pendulum-v1 scores well below -500 per 200-step episode
    assert float(row.split(",")[1]) < -500


def test_export_scalars_writes_any_tag_of_finished_runs(tmp_path):
    from torch.utils.tensorboard import SummaryWriter

    run_dir = tmp_path / "runs" / "r"
    writer = SummaryWriter(str(run_dir))
    writer.add_text(
        "hyperparameters", "|param|value|\n|-|-|\n|exp_name|rnd_continuous_action|\n|env_id|Pendulum-v1|\n|seed|2|"
    )
    for step, value in [(0, 0.5), (2048, 0.25)]:
        writer.add_scalar("charts/intrinsic_reward", value, step)
    writer.close()
    (run_dir / "DONE").touch()
    out = tmp_path / "out.csv"
    result = tool("export_scalars.py", str(run_dir), "--tag", "charts/intrinsic_reward", "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert out.read_text().splitlines() == [
        "algo,env_id,seed,step,value",
        "rnd,Pendulum-v1,2,0,0.5",
        "rnd,Pendulum-v1,2,2048,0.25",
    ]


def test_welch_compares_final_returns_task_by_task(tmp_path):
    from scipy import stats

    path = tmp_path / "final_returns.csv"
    rows = ["algo,env_id,seed,steps,final_return"]
    a, b = [100.0, 110.0, 130.0], [50.0, 52.0, 61.0]
    rows += [f"x,cartpole,{i},1000,{v}" for i, v in enumerate(a)] + [f"y,cartpole,{i},1000,{v}" for i, v in enumerate(b)]
    rows += ["x,only_x,1,1000,5.0", "x,only_x,2,1000,6.0"]  # a task y did not run: left out
    rows += [f"{algo},overlap,{i},1000,{v}" for algo, vs in (("x", [1, 5, 9]), ("y", [2, 5, 8])) for i, v in enumerate(vs)]
    path.write_text("\n".join(rows) + "\n")
    result = tool("welch.py", str(path), "x", "y")
    assert result.returncode == 0, result.stderr
    expected = stats.ttest_ind(a, b, equal_var=False)
    line = next(line for line in result.stdout.splitlines() if line.startswith("| cartpole |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1] == "3, 113.3 +- 15.3" and cells[3] == "+59.0"
    assert float(cells[4]) == pytest.approx(expected.statistic, abs=0.01)
    assert float(cells[6]) == pytest.approx(expected.pvalue, abs=0.001)
    va, vb = np.var(a, ddof=1) / 3, np.var(b, ddof=1) / 3
    assert float(cells[5]) == pytest.approx((va + vb) ** 2 / (va**2 / 2 + vb**2 / 2), abs=0.05)  # Welch-Satterthwaite
    assert cells[7] == "9/9"  # every run of x above every run of y
    df = (va + vb) ** 2 / (va**2 / 2 + vb**2 / 2)
    half = stats.t.ppf(0.975, df) * np.sqrt(va + vb)  # the 95% interval: difference +- t(0.975, df) * its standard error
    assert cells[8] == f"{59.0 - half:+.1f} to {59.0 + half:+.1f}" == "+25.9 to +92.1"
    overlap = next(line for line in result.stdout.splitlines() if line.startswith("| overlap |"))
    assert overlap.strip("|").split("|")[7].strip() == "4/9"  # 5 > 2, 9 > 2, 5, 8; the tie 5 = 5 counts for neither
    assert "only_x" not in result.stdout
    missing = tool("welch.py", str(path), "x", "z")
    assert missing.returncode != 0 and missing.stderr.strip().count("\n") == 0 and "no runs of 'z'" in missing.stderr


def test_welch_averages_a_window_of_evaluations_and_pools_algorithms(tmp_path):
    from scipy import stats

    path = tmp_path / "eval_series.csv"
    rows = ["algo,env_id,seed,step,episodic_return"]
    curves = {("x", 1): [0, 10, 20, 60], ("x", 2): [0, 20, 40, 60], ("y", 1): [0, 1, 2, 3], ("y", 2): [5, 2, 2, 5]}
    curves["z", 1] = [0, 0, 0, 24]  # means of the window: x 30, 40; y 2, 3; z 8 (medians: x 20, y 2, z 0)
    for (algo, seed), returns in curves.items():
        rows += [f"{algo},cartpole,{seed},{step},{r}" for step, r in zip((0, 500, 750, 1000), returns)]
    path.write_text("\n".join(rows) + "\n")
    result = tool("welch.py", str(path), "x", "y+z", "--steps", "500", "1000")
    assert result.returncode == 0, result.stderr
    x, yz = [30.0, 40.0], [2.0, 3.0, 8.0]  # each run's mean over steps 500-1000; y and z's runs together
    line = next(line for line in result.stdout.splitlines() if line.startswith("| cartpole |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1] == "2, 35.0 +- 7.1" and cells[2] == "3, 4.3 +- 3.2"
    assert float(cells[6]) == pytest.approx(stats.ttest_ind(x, yz, equal_var=False).pvalue, abs=0.001)
    assert cells[7] == "6/6"
    for bad, message in [(("1000", "500"), "LO is above HI"), (("2000", "3000"), "no runs of 'x'")]:
        refused = tool("welch.py", str(path), "x", "y", "--steps", *bad)
        assert refused.returncode != 0 and refused.stderr.strip().count("\n") == 0 and message in refused.stderr


def test_welch_paired_matches_runs_by_seed_and_pooled_arms_by_precedence(tmp_path):
    from scipy import stats

    path = tmp_path / "final_returns.csv"
    rows = ["algo,env_id,seed,steps,final_return"]
    rows += [f"x,cartpole,{seed},1000,{v}" for seed, v in [(1, 10), (2, 20), (3, 35), (5, 40), (10, 50)]]
    rows += [f"y,cartpole,{seed},1000,{v}" for seed, v in [(1, 8), (2, 21), (5, 40)]]  # seed 5: a tie
    rows += [f"z,cartpole,{seed},1000,{v}" for seed, v in [(1, 100), (3, 30), (4, 99)]]  # seed 1: y's counts (listed first)
    path.write_text("\n".join(rows) + "\n")
    result = tool("welch.py", str(path), "x", "y+z", "--paired")
    assert result.returncode == 0, result.stderr
    line = next(line for line in result.stdout.splitlines() if line.startswith("| cartpole |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    x, yz = [10, 20, 35, 40], [8, 21, 30, 40]  # seeds 1, 2, 3, 5; seed 10 has no partner, seed 4 no x run
    assert cells[1] == "4" and cells[4] == "+1.5 +- 2.6" and cells[7] == "2/4"  # d = 2, -1, 5, 0: sample SD; a tie: neither
    half = stats.t.ppf(0.975, 3) * np.std([2, -1, 5, 0], ddof=1) / 2  # t(0.975, n - 1) * sd / sqrt(n)
    assert cells[8] == f"{1.5 - half:+.1f} to {1.5 + half:+.1f}" == "-2.7 to +5.7"
    assert float(cells[6]) == pytest.approx(stats.ttest_rel(x, yz).pvalue, abs=0.001)
    refused = tool("welch.py", str(path), "y", "z", "--paired")  # one seed in common
    assert refused.returncode != 0 and "at least two seeds" in refused.stderr.strip().splitlines()[-1]


def test_learning_checks_summary_counts_the_check_and_the_final_mean(tmp_path):
    """tools/learning_checks.py's table on hand-made evaluations: a TD3 seed whose final evaluation dips passes the
    check and fails the final mean; one that never learns fails both; evaluations past the budget are rows of their
    own; a PPO run's end is its budget."""
    rows = []
    for step in range(0, 8501, 500):
        learned = step >= 6000
        rows.append(["td3", 1, step, *([-150.0] * 10 if learned and step != 8000 else [-700.0] * 10)])
        rows.append(["td3", 2, step, *([-1200.0] * 10)])
    rows += [["ppo", 1, step, *([1000.0] * 10)] for step in (26624, 28672, 30000)]
    path = tmp_path / "checks.csv"
    path.write_text("\n".join(",".join(map(str, row)) for row in rows) + "\n")
    done = tool("learning_checks.py", "--summary", str(path))
    assert done.returncode == 0, done.stderr
    td3 = [line for line in done.stdout.splitlines() if line.startswith("| td3")]
    assert len(td3) == 2  # the budget, and the one evaluation past it
    assert td3[0].startswith(
        "| td3, Pendulum-v1, > -400 (the test's budget) | 8000 | 2 | 1 of 2 | -1200.0 (seed 2) | 0 of 2 |"
    )
    assert td3[1].startswith("| td3, Pendulum-v1, > -400 | 8500 | 2 | 1 of 2 |") and "| 1 of 2 |" in td3[1]
    assert "| ppo, InvertedPendulum-v4, > 500 (the test's budget) | 30000 | 1 | 1 of 1 |" in done.stdout


@pytest.mark.parametrize(
    "flags,message",
    [
        (["redq", "--out", "x.csv"], "redq has no learning check"),
        (["ppo", "--extra-steps", "2048", "--out", "x.csv"], "anneal(s) the learning rate over the run"),
        (["td3"], "--out CSV is needed"),
        (["--summary", "missing.csv"], "no such file missing.csv"),
    ],
)
def test_learning_checks_bad_input_gets_one_line(flags, message, tmp_path):
    done = forkserver.run(
        [sys.executable, os.path.join(REPO, "tools", "learning_checks.py"), *flags],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert done.returncode == 2 and message in done.stderr.strip().splitlines()[-1]
