"""The speed-, memory- and GPU-measuring tools in tools/speed/ run and report what they say, on tiny settings (the GPU
session scripts that drive them: tests/test_gpu_scripts.py)."""

import csv
import functools
import importlib
import os
import shutil
import subprocess
import sys
import types

import pytest

from conftest import REPO
import forkserver

SPEED = os.path.join(REPO, "tools", "speed")


def tool(name, *flags, timeout=600):
    return forkserver.run([sys.executable, os.path.join(SPEED, name), *flags], capture_output=True, text=True, timeout=timeout)


def load_tool(name: str):
    sys.path.insert(0, SPEED)
    try:
        return importlib.import_module(name)
    finally:
        sys.path.pop(0)


@pytest.mark.slow
def test_throughput_reports_a_median_table_with_ratios():
    # two entries of one script (--bf16 would be ~15x slower on a CPU without bfloat16 instructions, for nothing)
    result = tool(
        "throughput.py",
        "td3 --batch-size 32",
        "td3 --batch-size 16",
        "--env-id",
        "Pendulum-v1",
        "--learning-starts",
        "100",
        "--steps",
        "60",
        "--repeats",
        "1",
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert "| `td3 --batch-size 16` |" in result.stdout
    first = next(line for line in lines if line.startswith("| `td3 --batch-size 32` |"))
    assert "| 1.00x |" in first and float(first.split("|")[2]) == pytest.approx(float(first.split("|")[5]))  # one seed
    assert [line.split(":")[0] for line in result.stderr.splitlines() if line.startswith("repeat")] == [
        "repeat 1/1 td3 --batch-size 32",
        "repeat 1/1 td3 --batch-size 16",
    ]
    warmups = [line.split(":")[0] for line in result.stderr.splitlines() if line.startswith("warm-up")]
    assert warmups == ["warm-up td3 --batch-size 32", "warm-up td3 --batch-size 16"]  # each entry's, as it ends


@pytest.mark.slow
def test_throughput_counts_the_seeds_an_entry_trains_at_once():
    throughput = load_tool("throughput")

    assert throughput.agents_of("oparl") == 1
    assert throughput.agents_of("oparl --num-seeds 4") == 4
    assert throughput.agents_of("2x:mkl-avx512:oparl --num-seeds 3") == 6
    assert throughput.copies_of("2x:oparl --bf16") == (2, "oparl --bf16")
    result = tool(
        "throughput.py", "td3 --batch-size 32 --num-seeds 2", "2x:td3 --batch-size 32", "--env-id", "Pendulum-v1",
        "--learning-starts", "100", "--steps", "40", "--repeats", "1",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    for line in (line for line in result.stdout.splitlines() if line.startswith("| `td3")):
        cells = line.split("|")
        assert float(cells[5]) == pytest.approx(2 * float(cells[2]), abs=0.2), line  # both rounded to 0.1


@pytest.mark.slow
def test_throughput_runs_an_entry_prefixed_mkl_avx512_through_the_wrapper():
    throughput = load_tool("throughput")

    prefix, ours = throughput.command_of("mkl-avx512:td3 --bf16")
    assert (
        prefix
        == [
            "bash",
            os.path.join(REPO, "tools", "mkl_avx512.sh"),
            sys.executable,
            os.path.join(REPO, "td3_continuous_action.py"),
            "--bf16",
        ]
        and ours
    )
    assert throughput.command_of("mkl-avx512:other/script.py")[0][-2:] == [sys.executable, "other/script.py"]
    assert throughput.command_of("td3")[0] == [sys.executable, os.path.join(REPO, "td3_continuous_action.py")]
    result = tool("throughput.py", "mkl-avx512:")
    assert result.returncode != 0 and "names no script or command" in result.stderr


@pytest.mark.slow
def test_throughput_runs_a_script_and_imports_given_relative_to_the_caller(tmp_path, monkeypatch):
    """Entries run in a scratch folder; a relative script path and PYTHONPATH still mean the caller's."""
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "marker.py").write_text("")
    (tmp_path / "other").mkdir()
    script = tmp_path / "other" / "script.py"  # imports from lib/, takes the tool's flags, does nothing
    script.write_text("import sys, marker\nlearning_starts: int = 0\n")
    monkeypatch.chdir(tmp_path)
    env = {**os.environ, "PYTHONPATH": "lib"}
    result = forkserver.run(
        [
            sys.executable,
            os.path.join(SPEED, "throughput.py"),
            "other/script.py",
            "--steps",
            "10",
            "--learning-starts",
            "10",
            "--repeats",
            "1",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "| `other/script.py` |" in result.stdout


def test_throughput_survives_a_run_that_writes_more_than_a_pipe_holds(tmp_path):
    """A run that writes megabytes to stderr (dm-control under NumPy 2.5 warns at every step) must not block on a
    full pipe; a run that fails is reported by the last line it wrote."""
    chatty = tmp_path / "chatty.py"
    chatty.write_text("import sys\nlearning_starts: int = 0\nsys.stderr.write('warning\\n' * 200_000)\n")
    result = tool("throughput.py", str(chatty), "--steps", "10", "--learning-starts", "10", "--repeats", "1", timeout=60)
    assert result.returncode == 0, result.stderr
    failing = tmp_path / "failing.py"
    failing.write_text(
        "import sys\nlearning_starts: int = 0\nsys.stderr.write('noise\\n' * 50_000 + 'the cause\\n')\nsys.exit(3)\n"
    )
    result = tool("throughput.py", str(failing), "--steps", "10", "--learning-starts", "10", "--repeats", "1", timeout=60)
    assert result.returncode != 0 and result.stderr.strip().splitlines()[-1].endswith("failed (3): the cause")


@pytest.mark.slow
def test_throughput_window_reads_the_logged_rate_of_each_timed_window(tmp_path):
    """--window: one run per entry and repeat; every 1000-step window after learning starts + warm-up is a sample, and
    a process's agent-steps/s are its steps/s times its seeds."""
    out = tmp_path / "w.csv"
    result = tool(
        "throughput.py", "td3 --batch-size 32 --num-seeds 2", "--env-id", "Pendulum-v1", "--learning-starts", "800",
        "--warmup", "100", "--steps", "1200", "--repeats", "1", "--window", "--csv", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert [row["window_end"] for row in rows] == ["2000"]  # [1000, 2000): the only window from step 900 on
    assert list(rows[0]) == load_tool("throughput").CSV_FIELDS and rows[0]["repeat"] == "1"
    assert rows[0]["seeds_per_copy"] == "2" and rows[0]["copies"] == "1"
    assert float(rows[0]["agent_steps_per_s"]) == pytest.approx(2 * float(rows[0]["steps_per_s"]), abs=0.1)
    result = tool("throughput.py", "td3", "--window", "--learning-starts", "100", "--steps", "1000")
    assert result.returncode != 0 and "--steps must be >= 1900" in result.stderr.strip().splitlines()[-1]


def test_throughput_window_reads_a_cumulative_rate_as_cleanrl_logs_it(tmp_path):
    """Another script's charts/SPS is logged as CleanRL's loop logs it (every 100 steps after learning starts, under
    runs/{env id}/...): --window reads each 1000-step window's rate from the events' times. The fake run takes 5 s
    to start, then runs 400 steps/s to step 2000 and 250 after."""
    fake = tmp_path / "fake.py"
    fake.write_text(
        "import argparse\nfrom torch.utils.tensorboard import SummaryWriter\nlearning_starts: int = 0\n"
        "p = argparse.ArgumentParser()\np.add_argument('--total-timesteps', type=int)\n"
        "p.add_argument('--learning-starts', type=int)\na, _ = p.parse_known_args()\n"
        "w = SummaryWriter('runs/dm_control/fake')\nfor step in range(a.total_timesteps):\n"
        "    seconds = 5 + min(step, 2000) / 400 + max(step - 2000, 0) / 250\n"
        "    if step > a.learning_starts and step % 100 == 0:\n"
        "        w.add_scalar('charts/SPS', int(step / seconds), step, walltime=1e9 + seconds)\nw.close()\n"
    )
    out = tmp_path / "w.csv"
    result = tool(
        "throughput.py", str(fake), "--window", "--learning-starts", "1000", "--warmup", "0", "--steps", "3000",
        "--repeats", "1", "--csv", str(out), "--label", "fake",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    with open(out) as f:
        rows = {row["window_end"]: (float(row["steps_per_s"]), row["label"]) for row in csv.DictReader(f)}
    # [1000, 2000) is not timed: CleanRL logs no step 1000 when learning starts there
    assert rows == {"3000": (pytest.approx(250), "fake"), "4000": (pytest.approx(250), "fake")}


def test_throughput_times_the_windows_from_the_first_step_that_every_seed_logged():
    throughput = load_tool("throughput")
    windows = {1000: [50.0, 70.0], 2000: [40.0, 60.0], 3000: [30.0], 4000: [20.0, 20.0]}  # 3000: one seed's only
    assert throughput.timed_windows(windows, 1000, 2) == [(2000, 50.0, 100.0), (4000, 20.0, 40.0)]  # from [1000, 2000)
    assert throughput.timed_windows(windows, 999, 2)[0] == (2000, 50.0, 100.0)  # [0, 1000) starts before step 999
    assert throughput.timed_windows(windows, 0, 2)[0] == (1000, 60.0, 120.0)
    assert throughput.timed_windows(windows, 1001, 1) == [(3000, 30.0, 30.0)]


def test_throughput_summary_is_the_median_with_its_range_and_ratio():
    throughput = load_tool("throughput")
    rows = throughput.summary({"td3": [1.0, 2.0, 30.0], "oparl --num-seeds 4": [4.0, 1.0, 5.0, 6.0]}, "td3")
    assert rows[0] == ("td3", 2.0, 1.0, 30.0, 1.0, 2.0)
    assert rows[1] == ("oparl --num-seeds 4", 4.5, 1.0, 6.0, 2.25, 18.0)


def test_throughput_takes_the_gpu_name_it_is_given(monkeypatch):
    throughput = load_tool("throughput")
    monkeypatch.setenv("GPU_NAME", "NVIDIA H200")
    assert throughput.gpu_name() == "NVIDIA H200"
    monkeypatch.delenv("GPU_NAME")
    asked = []
    monkeypatch.setattr(
        throughput.subprocess, "run", lambda cmd, **kw: asked.append(cmd) or subprocess.CompletedProcess(cmd, 0, "X\n")
    )
    assert throughput.gpu_name() == "X" and len(asked) == 1


def test_throughput_refuses_bad_settings():
    result = tool("throughput.py", "td3", "--steps", "0")
    assert result.returncode != 0 and "--steps must be > 0" in result.stderr
    result = tool("throughput.py", "td3", "--baseline", "sac")
    assert result.returncode != 0 and "is not one of the entries" in result.stderr


def test_levers_prints_one_row_per_lever():
    result = tool("levers.py", "--repeats", "1", "--calls", "2")
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ") and not line.startswith("| lever")]
    assert len(rows) == 8 and any("fused" in row for row in rows) and any("hand-batched" in row for row in rows)


def test_profile_run_attributes_samples_to_phases():
    if shutil.which("py-spy") is None:
        pytest.skip("py-spy is not installed (pip install py-spy)")
    result = tool(
        "profile_run.py",
        "td3",
        "--env-id",
        "Pendulum-v1",
        "--learning-starts",
        "100",
        "--total-timesteps",
        "600",
        "--batch-size",
        "32",
        "--eval-episodes",
        "1",
    )
    if result.returncode != 0 and "Permission" in result.stderr:
        pytest.skip(f"py-spy may not sample here: {result.stderr.strip()}")
    assert result.returncode == 0, result.stderr
    assert "| critic update (forward, backward, Adam) |" in result.stdout and "| TD target |" in result.stdout


def test_profile_run_charges_acting_under_no_grad_to_acting():
    """py-spy puts torch.no_grad's wrapper between main and noisy_action, and a list comprehension's frame between
    main and the random actions' Box.sample (Python 3.11; stacks as py-spy 0.4.3 reported them)."""
    phase_of = functools.partial(load_tool("profile_run").phase_of, calls={})  # no frame named by its caller's line
    main = ["<module> (sac_continuous_action.py:346)", "main (sac_continuous_action.py:306)"]
    per_seed, no_grad = (
        "per_seed.<locals>.run (rl_utils/seeds.py:64)",
        "context_decorator.<locals>.decorate_context (torch/utils/_contextlib.py:124)",
    )
    forward = ["Actor.sampled_action (sac_continuous_action.py:163)", "Module._call_impl (torch/nn/modules/module.py:1789)"]
    for acting in ("noisy_action (sac_continuous_action.py:176)", "optimistic_action (oparl_continuous_action.py:205)"):
        assert phase_of([*main, per_seed, no_grad, acting, *forward]) == "acting (actor forward, noise)"
    random = [
        "SeedEnvs.sample_actions (rl_utils/envs.py:135)",
        "SeedEnvs.sample_actions.<locals>.<listcomp> (rl_utils/envs.py:135)",
    ]
    assert phase_of([*main, *random, "Box.sample (gymnasium/spaces/box.py:455)"]) == "acting (actor forward, noise)"
    assert phase_of([*main, "ReplayBuffer.add (rl_utils/buffers.py:28)"]) == "storing the transition"
    assert phase_of([*main, "SeedEnvs.step (rl_utils/envs.py:140)", "EpisodeRecord.step (rl_utils/envs.py:86)"]) == (
        "environment step"
    )
    assert phase_of([*main, no_grad]) == "rest of the loop (Python, conversions, progress bar)"
    assert phase_of(["<module> (<frozen site>:616)", "main (<frozen site>:603)"]) == "start-up and imports"  # not a script's


def test_profile_run_charges_an_update_its_optimizer_step_and_a_per_seed_call_its_function():
    """An optimizer step, optimize(loss, "qf_loss", ...), is told apart by the script's line that calls it, and the
    frames of rl_utils.per_seed (its own work, vmap's for several seeds) and acting's copy to the device by the line
    that calls per_seed(fn): each is charged to its update or to acting (stacks as py-spy 0.4.3 reported them)."""
    profile_run = load_tool("profile_run")

    def at(script, text, frame="main.<locals>.update"):  # the frame of `script`'s function, at the line holding text
        with open(os.path.join(REPO, f"{script}_continuous_action.py")) as f:
            line = next(k for k, source in enumerate(f, start=1) if text in source)
        return f"{frame} ({script}_continuous_action.py:{line})"

    main = ["<module> (td3_continuous_action.py:277)", at("td3", "logs = update(", "main")]
    step = ["optimize (td3_continuous_action.py:186)", "Adam.step (torch/optim/adam.py:248)"]
    per_seed = ["per_seed.<locals>.run (rl_utils/seeds.py:62)", "num_seeds (rl_utils/seeds.py:53)"]
    critic, actor = "critic update (forward, backward, Adam)", "actor update(s)"
    assert profile_run.phase_of([*main, at("td3", "optimize(qf_loss"), *step]) == critic
    assert profile_run.phase_of([*main, at("td3", "optimize(actor_loss"), *step]) == actor
    assert profile_run.phase_of([*main, at("td3", "per_seed(critic_loss)"), *per_seed]) == critic
    assert profile_run.phase_of([*main, at("td3", "per_seed(policy_loss)"), *per_seed]) == actor
    sac = ["<module> (sac_continuous_action.py:346)", at("sac", "logs = update(", "main")]
    assert profile_run.phase_of([*sac, at("sac", "optimize(alpha_loss"), "optimize (sac_continuous_action.py:218)"]) == (
        "entropy (alpha) update"
    )
    acting = ["<module> (td3_continuous_action.py:277)", at("td3", "per_seed(noisy_action)", "main")]
    assert profile_run.phase_of([*acting, "to_device (rl_utils/numerics.py:80)"]) == "acting (actor forward, noise)"
    assert profile_run.phase_of([*acting, per_seed[0]]) == "acting (actor forward, noise)"
    # the update's own lines (its logs) are the rest of the loop, as is a per_seed frame below another line
    rest = "rest of the loop (Python, conversions, progress bar)"
    assert profile_run.phase_of([*main, at("td3", '"losses/qf_values"')]) == rest
    assert profile_run.phase_of([*main, at("td3", '"losses/qf_values"'), *per_seed]) == rest
    evaluation = ["<module> (td3_continuous_action.py:277)", at("td3", "run.evaluate(global_step", "main")]
    policy = [at("td3", "per_seed(actor)", "main.<locals>.policy"), *per_seed]
    assert profile_run.phase_of([*evaluation, "evaluate (rl_utils/envs.py:164)", *policy]) == "evaluation"


def test_phase_timer_charges_each_phase_its_own_time(monkeypatch):
    """Exclusive rows: an outer phase is charged its time minus its timed inner calls'; evaluation is charged
    whole (the environment steps inside it are not split out); the device is synchronised at every boundary."""
    phase_times = load_tool("phase_times")
    now = [0.0]
    monkeypatch.setattr(phase_times.time, "perf_counter", lambda: now[0])
    syncs = []
    timer = phase_times.PhaseTimer(lambda: syncs.append(now[0]) or True)

    def advance(seconds):
        now[0] += seconds

    env_step = timer.wrap("environment step", lambda: advance(5.0))
    critic = timer.wrap("update: critic", lambda: advance(3.0))
    evaluation = timer.wrap("evaluation", lambda: [env_step() for _ in range(2)])

    @functools.partial(timer.wrap, "update: graph replay and input copies")
    def replay():
        advance(2.0)
        critic()
        advance(1.0)

    replay()
    env_step()
    evaluation()
    assert dict(timer.seconds) == {
        "update: graph replay and input copies": 3.0,
        "update: critic": 3.0,
        "environment step": 5.0,
        "evaluation": 10.0,
    }
    assert dict(timer.calls) == {
        "update: graph replay and input copies": 1,
        "update: critic": 1,
        "environment step": 1,
        "evaluation": 1,
    }
    assert syncs == [0.0, 2.0, 5.0, 6.0, 6.0, 11.0, 11.0, 21.0] and timer.syncs == 8


def test_phase_times_charges_a_per_seed_call_and_an_optimizer_step_to_their_phase(monkeypatch):
    """The scripts act and compute their losses through rl_utils.per_seed and step their optimizers through
    optimize(loss, name): a phase is charged per_seed's own work (vmap's, for several seeds) and its loss's optimizer
    step, as one call; acting's copy to the device is acting's, not a second call, and the clock starts at it, but not at
    an evaluation's copy; the step of a loss that names no phase is the rest of the loop's."""
    import rl_utils.envs

    phase_times = load_tool("phase_times")
    for _, where, name in phase_times.PHASES:  # what instrument replaces in rl_utils, put back after the test
        if where is not None:
            owner = phase_times.owner_of(None, where)
            monkeypatch.setattr(owner, name, getattr(owner, name))
    monkeypatch.setattr(rl_utils.envs, "make_env", rl_utils.envs.make_env)
    now = [0.0]
    monkeypatch.setattr(phase_times.time, "perf_counter", lambda: now[0])

    def takes(seconds, then=lambda *args: None):  # a function that takes this long, then calls `then`
        def fn(*args):
            now[0] += seconds
            return then(*args)

        return fn

    script = types.SimpleNamespace(to_device=takes(1.0), noisy_action=takes(2.0), td_target=takes(4.0))
    script.critic_loss = takes(8.0, lambda *args: script.td_target())  # td_target from the module, as the scripts call it
    script.policy_loss, script.optimize = takes(16.0), takes(32.0)
    script.per_seed = lambda fn: takes(64.0, fn)  # its own work, then fn
    script.evaluate = lambda policy: policy()
    timer = phase_times.PhaseTimer()
    clock = phase_times.instrument(script, timer, warmup_updates=0)
    script.evaluate(lambda: script.to_device())
    assert clock["start"] is None  # not at an evaluation's copy
    script.per_seed(script.noisy_action)(script.to_device())  # as the scripts act: the copy, then per_seed's call
    assert clock["start"] == 1.0
    script.optimize(script.per_seed(script.critic_loss)(), "qf_loss")
    script.optimize(script.per_seed(script.policy_loss)(), "actor_loss")
    script.optimize(None, "a loss of no phase")
    script.evaluate(lambda: script.to_device())
    assert dict(timer.seconds) == {
        "acting": 1.0 + 64.0 + 2.0,
        "update: TD target": 4.0,
        "update: critic": 64.0 + 8.0 + 32.0,
        "update: actor(s)": 64.0 + 16.0 + 32.0,
        "evaluation": 1.0,
    }
    assert set(timer.calls.values()) == {1}
    assert clock["mark"]["wall"] == 67.0 + 108.0 + 112.0 + 32.0  # the unnamed step: in the loop, in no phase


def test_phase_times_table_of_a_real_run(tmp_path):
    """A real run, 2 seeds: every phase of the loop in the loop's order, one action, sample and stored transition
    and two environment steps (one per seed) a training step, the actor every second step, rows that add up to the
    loop's time, which ends where the last evaluation starts (the evaluations at 200 and 400 are in it)."""
    out = tmp_path / "phases.csv"
    flags = ["--env-id", "Pendulum-v1", "--learning-starts", "100", "--total-timesteps", "600", "--batch-size", "32"]
    flags += ["--num-seeds", "2", "--eval-frequency", "200", "--eval-episodes", "1"]
    result = tool("phase_times.py", "td3", *flags, "--warmup-updates", "50", "--csv", str(out), "--no-sync")
    assert result.returncode == 0, result.stderr
    threads = os.environ["OMP_NUM_THREADS"]  # the tool's, as it inherits it (conftest's default: 1)
    assert f"450 training steps timed on cpu ({threads} thread(s))" in result.stdout
    assert "(not synchronised: 0.0 device synchronisations a step)" in result.stdout
    assert "evaluation (not in the loop's time): " in result.stdout and result.stdout.rstrip().endswith(" in 2 calls")
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == load_tool("phase_times").CSV_FIELDS and {row["synchronised"] for row in rows} == {"False"}
    phases = [row["phase"] for row in rows]
    assert phases[:5] == ["acting", "environment step", "environment reset", "storing the transition", "replay sampling"]
    assert phases[5:] == [
        "update: TD target",
        "update: critic",
        "update: actor(s)",
        "update: target networks",
        "logging",
        "rest of the loop",
    ]  # TD3 has no alpha, the run no checkpoints; the evaluations are not in the loop
    calls = {row["phase"]: float(row["calls_per_step"]) for row in rows}
    assert calls["replay sampling"] == 1 and calls["environment step"] == 2 and calls["update: actor(s)"] == 0.5
    assert calls["acting"] == 1 and calls["storing the transition"] == 1
    assert abs(sum(float(row["share"]) for row in rows) - 100) < 0.1 and float(rows[-1]["ms_per_step"]) >= 0
    assert {row["script"] for row in rows} == {"td3"} and all(row["timed_steps"] == "450" for row in rows)


def test_phase_times_labels_a_blocking_copy_run(tmp_path):
    """--blocking-copy (acting's copy as before commit e4d8b37, for a comparison on a GPU) labels the run and its rows."""
    flags = ["--env-id", "Pendulum-v1", "--learning-starts", "100", "--total-timesteps", "300", "--batch-size", "32"]
    own = ["--warmup-updates", "50", "--csv", str(tmp_path / "p.csv"), "--no-sync", "--blocking-copy"]
    result = tool("phase_times.py", "sac", *flags, *own)
    assert result.returncode == 0, result.stderr
    assert f"sac {' '.join(flags)} (--blocking-copy): 150 training steps timed on cpu" in result.stdout
    with open(tmp_path / "p.csv") as f:
        assert {row["flags"] for row in csv.DictReader(f)} == {" ".join(flags) + " (--blocking-copy)"}


def write_phases(path, runs):
    """A phases CSV as --csv writes it: per run (script, flags, [ms of each phase]), phases named in order, the last
    one "rest of the loop"."""
    names = ["acting", "environment step", "replay sampling"]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(load_tool("phase_times").CSV_FIELDS)
        for script, label, ms in runs:
            for phase, value in zip(names[: len(ms) - 1] + ["rest of the loop"], ms):
                writer.writerow([script, label, "gpu", 1, False, 100, phase, value, 50, 1])


def test_phase_times_summary_adds_each_runs_phases_and_compares_the_copies(tmp_path):
    """--summary: a run is its rows up to its "rest of the loop" row, within one file (runs with the same flags back
    to back, or ending one file and starting the next, stay apart), its step is the sum of its phases, and a script's
    mean is compared with that of its --blocking-copy runs under the same flags (none at all included)."""
    flags = "--env-id Hopper-v4"
    runs = [("td3", flags, [0.5, 0.5]), ("td3", flags, [0.4, 0.6]), ("td3", flags + " (--blocking-copy)", [1.0, 1.5])]
    runs += [("td3", flags + " (--blocking-copy)", [1.0, 0.2, 0.3]), ("sac", flags, [2.0, 1.0])]
    write_phases(tmp_path / "a.csv", runs + [("sac", "", [1.0, 1.0])])
    write_phases(tmp_path / "b.csv", [("sac", "", [0.5, 0.5]), ("sac", "(--blocking-copy)", [3.0, 1.0])])
    result = tool("phase_times.py", "--summary", str(tmp_path / "a.csv"), str(tmp_path / "b.csv"))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert f"| td3 | {flags} | gpu | 1 | False | 100 | 1.000, 1.000 | 1.000 | -1.000 (-50.0%) |" in lines
    assert f"| td3 | {flags} (--blocking-copy) | gpu | 1 | False | 100 | 2.500, 1.500 | 2.000 |  |" in lines
    assert f"| sac | {flags} | gpu | 1 | False | 100 | 3.000 | 3.000 |  |" in lines
    assert "| sac |  | gpu | 1 | False | 100 | 2.000, 1.000 | 1.500 | -2.500 (-62.5%) |" in lines and len(lines) == 7


@pytest.mark.parametrize(
    "rows,cut,error",
    [
        ([("td3", "", [1.0, 1.0]), ("sac", "", [1.0])], False, None),  # a well-formed pair, the control
        ([("td3", "", [1.0, 1.0])], True, "ends inside a run"),  # the run loses its "rest of the loop" row
        ([("td3", "", [1.0, 1.0]), ("phase", "", ["ms"])], False, "not a phase row"),  # a header in the middle
    ],
)
def test_phase_times_summary_refuses_a_cut_off_run_in_one_line(tmp_path, rows, cut, error):
    path = tmp_path / "p.csv"
    write_phases(path, rows)
    if cut:
        path.write_text("".join(path.read_text().splitlines(keepends=True)[:-1]))
    result = tool("phase_times.py", "--summary", str(path))
    if error is None:
        assert result.returncode == 0, result.stderr
    else:
        assert result.returncode != 0 and result.stderr.strip().startswith("error: ") and error in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_phase_times_summary_refuses_a_run_whose_key_changes_before_it_ends(tmp_path):
    path = tmp_path / "p.csv"
    write_phases(path, [("td3", "", [1.0, 1.0])])
    with open(path) as f:
        lines = f.read().splitlines()
    lines.insert(2, lines[1].replace("td3", "sac", 1))  # a sac row inside the td3 run: the td3 run was cut off
    path.write_text("\n".join(lines) + "\n")
    result = tool("phase_times.py", "--summary", str(path))
    assert result.returncode != 0 and "line 3: a run's rows end before" in result.stderr, result.stderr
    bad = tool("phase_times.py", "--summary", str(tmp_path / "missing.csv"))
    assert bad.returncode != 0 and bad.stderr.strip().startswith("error: cannot read"), bad.stderr


@pytest.mark.parametrize(
    "flags,error",
    [
        (["ppo"], "error: usage: python tools/speed/phase_times.py {td3,sac,oparl,redq}"),
        (["td3", "--warmup-updates", "-1"], "error: --warmup-updates must be an integer >= 0, got -1"),
        (["td3", "--csv"], "error: --csv needs a value"),
        (["td3", "--blocking-copy"], "error: --blocking-copy changes only what the host waits for: give --no-sync with it"),
        (
            ["td3", "--env-id", "Pendulum-v1", "--total-timesteps", "300", "--learning-starts", "100", "--batch-size", "32"],
            "error: no training step",
        ),
    ],
)
def test_phase_times_bad_input_is_one_line(flags, error):
    result = tool("phase_times.py", *flags)
    assert result.returncode != 0 and result.stderr.strip().splitlines()[-1].startswith(error), result.stderr


def test_memory_tool_reports_checkpoint_cost_and_resident_memory():
    result = tool("memory.py", "checkpoint", "--script", "td3", "--rows", "1000")
    assert result.returncode == 0, result.stderr
    assert "td3, Hopper-v4 shapes, 1000 transitions:" in result.stdout and "MiB" in result.stdout and "write" in result.stdout
    result = tool("memory.py", "rss", "td3", "--env-id", "Pendulum-v1", "--total-timesteps", "300", "--learning-starts", "256")
    assert result.returncode == 0, result.stderr
    assert "resident memory" in result.stdout and "peak" in result.stdout


class CountingEnv:
    """A stand-in for make_env's environment: its episodes end every 7 steps; it logs its steps, resets and draws."""

    def __init__(self, log: list):
        self.log, self.t = log, 0
        env = self

        class Space:
            def seed(self, seed):
                pass

            def sample(self):
                env.log.append("sample")
                return 0.0

        self.action_space = Space()

    def reset(self, seed=None):
        self.log.append("reset")
        self.t = 0
        return 0.0, {}

    def step(self, action):
        self.log.append("step")
        self.t += 1
        return 0.0, 0.0, self.t == 7, False, {}

    def close(self):
        pass


def test_env_cost_steps_every_environment_with_actions_drawn_before_the_clock(monkeypatch):
    env_cost = load_tool("env_cost")
    log, built = [], []

    def make_env(env_id, seed):
        built.append((env_id, seed))
        return CountingEnv(log)

    clock = iter([10.0, 13.0])
    monkeypatch.setattr(env_cost.time, "perf_counter", lambda: log.append("clock") or next(clock))
    cost = env_cost.step_cost(make_env, "Fake-v0", num_envs=3, steps=20)
    assert cost == pytest.approx(3.0 / 60) and built == [("Fake-v0", 0), ("Fake-v0", 1), ("Fake-v0", 2)]
    assert log.count("step") == 60 and log.count("sample") == 60
    assert log.count("reset") == 3 + 3 * 2  # each env's first, then after its steps 7 and 14
    assert max(i for i, e in enumerate(log) if e == "sample") < log.index("clock") < log.index("step")  # no draw timed
    loaded = []
    monkeypatch.setattr(env_cost, "make_env_of", lambda script: loaded.append(script) or make_env)
    monkeypatch.setattr(env_cost.time, "perf_counter", lambda: 0.0)
    env_cost.main(["Fake-v0", "--script", "sac", "--envs", "1", "--steps", "1"])
    assert loaded == ["sac"]


def test_env_cost_takes_the_make_env_that_builds_the_scripts_environments():
    """A script's environments come from rl_utils.envs.make_env, through its SeedEnvs (the off-policy scripts) or
    imported itself (PPO): that is the layer env_cost times."""
    import rl_utils.envs

    env_cost = load_tool("env_cost")
    for script in ("td3", "ppo"):
        assert env_cost.make_env_of(script) is rl_utils.envs.make_env, script


def test_env_cost_times_each_task_through_the_scripts_environment_layer():
    result = tool("env_cost.py", "Pendulum-v1", "MountainCarContinuous-v0", "--envs", "2", "--steps", "50")
    assert result.returncode == 0, result.stderr
    rows = [
        line.split("|")
        for line in result.stdout.splitlines()
        if line.startswith("| Pendulum") or line.startswith("| Mountain")
    ]
    assert [row[1].strip() for row in rows] == ["Pendulum-v1", "MountainCarContinuous-v0"]
    assert all(0 < float(row[2]) < 100 for row in rows)  # milliseconds per step
    result = tool("env_cost.py", "NoSuchTask-v0", "--envs", "1", "--steps", "1")
    assert result.returncode != 0 and result.stderr.strip().splitlines()[-1].startswith("error: unknown --env-id")
