"""benchmark.sh: the sweep's commands (through --dry-run, in the fast tier), parallel runs, skip and resume, failures,
and a real Slurm (these train or sweep: marked slow)."""

import fcntl
import io
import os
import shlex
import shutil
import socket
import subprocess
import sys
import time

import pytest

from conftest import REPO

BENCHMARK = os.path.join(REPO, "benchmark.sh")
TINY = [
    "--total-timesteps",
    "300",
    "--",
    "--learning-starts",
    "200",
    "--batch-size",
    "32",
    "--eval-frequency",
    "300",
    "--eval-episodes",
    "1",
]


def bench_env(**extra) -> dict:
    """The environment a sweep runs in: this Python first on PATH, without the suite's own LD_PRELOAD (a suite run
    under tools/mkl_avx512.sh, whose library a sweep would name in its logs), plus `extra`."""
    env = {k: v for k, v in os.environ.items() if k != "LD_PRELOAD"}
    return {**env, "PATH": os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"], **extra}


def bench(*flags, cwd, timeout=600, benchmark=BENCHMARK, env=None):
    env = bench_env(**(env or {}))
    return subprocess.run(["bash", benchmark, *flags], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


def test_help_lists_the_flags(tmp_path):
    result = bench("--help", cwd=tmp_path)
    assert result.returncode == 0
    for flag in (
        "--algos",
        "--env-ids",
        "--suite",
        "--seeds",
        "--seeds-per-process",
        "--total-timesteps",
        "--workers",
        "--dry-run",
        "--slurm-partition",
        "--slurm-extra",
    ):
        assert flag in result.stdout


def planned(stdout: str) -> list:
    """--dry-run's lines as (script, --seed, --num-seeds, --run-name, the flags after --checkpoint-frequency N) per
    process, and ("finished", name) per run that counts as finished."""
    found = []
    for line in stdout.splitlines():
        if line.startswith("# finished: "):
            found.append(("finished", line.removeprefix("# finished: ")))
            continue
        words = shlex.split(line)
        value = lambda flag, default=None: words[words.index(flag) + 1] if flag in words else default  # noqa: E731
        script = os.path.basename(words[1]).removesuffix("_continuous_action.py")
        rest = words[words.index("--checkpoint-frequency") + 2 :]
        found.append((script, int(value("--seed")), int(value("--num-seeds", 1)), value("--run-name"), rest))
    return found


def test_dry_run_prints_each_runs_training_command_with_its_own_seed_and_name(tmp_path):
    flags = ["--algos", "td3", "oparl", "--env-ids", "dm_control/cartpole-balance-v0", "Pendulum-v1", "--seeds", "1", "2"]
    result = bench(*flags, "3", "--dry-run", *TINY, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert all(line.split()[0] == sys.executable and " --total-timesteps 300 " in line for line in lines)
    tiny = ["--learning-starts", "200", "--batch-size", "32", "--eval-frequency", "300", "--eval-episodes", "1"]
    suffix = "learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1"
    expected = [
        (algo, seed, 1, f"{env.replace('/', '-')}__{algo}__{seed}__300__{suffix}", tiny)
        for env in ("dm_control/cartpole-balance-v0", "Pendulum-v1")
        for seed in (1, 2, 3)
        for algo in ("td3", "oparl")
    ]
    assert planned(result.stdout) == expected
    assert [line.split()[line.split().index("--env-id") + 1] for line in lines] == 6 * [
        "dm_control/cartpole-balance-v0"
    ] + 6 * ["Pendulum-v1"]
    assert not os.path.exists(tmp_path / "runs")


def test_dry_run_leaves_out_finished_runs_and_resumes_a_started_one(tmp_path):
    """A run marked DONE or named in --skip-listed's file is a '# finished' line, not a command; one with a checkpoint
    is resumed from it; with --seeds-per-process, the finished seeds leave the groups."""
    name = lambda seed: f"Pendulum-v1__td3__{seed}__300"  # noqa: E731
    listed = tmp_path / "finished_runs.txt"
    listed.write_text(name(2) + "\n")
    (tmp_path / "runs" / name(3)).mkdir(parents=True)
    (tmp_path / "runs" / name(3) / "DONE").touch()
    (tmp_path / "runs" / name(4)).mkdir(parents=True)
    (tmp_path / "runs" / name(4) / "checkpoint.pt").touch()
    flags = ["--algos", "td3", "--env-ids", "Pendulum-v1", "--seeds", "1", "2", "3", "4", "5", *TINY[:2], "--dry-run"]
    result = bench(*flags, "--skip-listed", str(listed), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert planned(result.stdout) == [
        ("td3", 1, 1, name(1), []),
        ("finished", name(2)),
        ("finished", name(3)),
        ("td3", 4, 1, name(4), ["--resume", f"runs/{name(4)}"]),
        ("td3", 5, 1, name(5), []),
    ]
    assert [p[:3] for p in planned(bench(*flags, cwd=tmp_path).stdout)][1] == ("td3", 2, 1)  # not listed: it runs
    grouped = planned(bench(*flags, "--skip-listed", str(listed), "--seeds-per-process", "5", cwd=tmp_path).stdout)
    assert [p[:3] for p in grouped] == [("finished", name(2)), ("finished", name(3)), ("td3", 1, 1), ("td3", 4, 2)]


def test_defaults_are_the_papers_tasks_and_ten_seeds(tmp_path):
    dmc = bench("--dry-run", cwd=tmp_path).stdout.strip().splitlines()
    assert len(dmc) == 3 * 18 * 10
    mujoco = bench("--suite", "mujoco", "--algos", "td3", "--seeds", "1", "--dry-run", cwd=tmp_path).stdout.split()
    assert {"Ant-v4", "Hopper-v4", "Humanoid-v4", "Walker2d-v4"} <= set(mujoco)


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--algos", "ppo2"], "unknown algorithm 'ppo2'"),
        (["--workers", "0"], "--workers must be a positive integer"),
        (["--seeds-per-process", "x"], "--seeds-per-process must be a positive integer"),
        (["--suite", "atari"], "--suite takes dmc or mujoco"),
        (["--seeds", "x"], "seeds must be non-negative integers"),
        (["--frobnicate"], "unknown flag '--frobnicate'"),
        (["--algos"], "--algos needs at least one value"),
    ],
)
def test_bad_flags_get_one_line(flags, message, tmp_path):
    result = bench(*flags, cwd=tmp_path)
    assert (
        result.returncode != 0 and result.stderr.strip().splitlines() == [result.stderr.strip()] and message in result.stderr
    )


@pytest.mark.slow
def test_sweep_runs_in_parallel_then_skips_finished_runs(tmp_path):
    flags = ["--algos", "td3", "sac", "--env-ids", "Pendulum-v1", "--seeds", "1", "--workers", "2", *TINY]
    first = bench(*flags, cwd=tmp_path)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "summary: 2 done, 0 skipped (finished before), 0 failed" in first.stdout
    assert "runs: 0 finished, 2 running, 0 left" in first.stdout
    names = sorted(os.listdir(tmp_path / "runs"))
    assert names == [
        "Pendulum-v1__sac__1__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1",
        "Pendulum-v1__td3__1__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1",
    ]
    for name in names:
        assert (tmp_path / "runs" / name / "DONE").exists() and (tmp_path / "logs" / f"{name}.log").exists()
        # the log says which float32 kernels the run used (no tools/mkl_avx512.sh here: MKL's default ones)
        assert "float32 kernels: mkl-default" in (tmp_path / "logs" / f"{name}.log").read_text()
    second = bench(*flags, cwd=tmp_path)
    assert "summary: 0 done, 2 skipped (finished before), 0 failed" in second.stdout


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("flock") is None, reason="flock (util-linux) is not installed: runs are not locked")
def test_a_run_another_sweep_holds_is_left_alone(tmp_path):
    flags = ["--algos", "td3", "--env-ids", "Pendulum-v1", "--seeds", "1", *TINY]
    name = "Pendulum-v1__td3__1__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1"
    os.makedirs(tmp_path / "logs")
    with open(tmp_path / "logs" / f"{name}.lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as the training process of another sweep would
        busy = bench(*flags, cwd=tmp_path)
    assert busy.returncode == 0, busy.stdout + busy.stderr
    assert "summary: 0 done, 0 skipped (finished before), 0 failed" in busy.stdout
    assert f"left alone, running in another sweep: {name}" in busy.stdout
    assert not os.path.exists(tmp_path / "runs" / name)
    free = bench(*flags, cwd=tmp_path)  # the lock released: the run goes ahead
    assert "summary: 1 done, 0 skipped (finished before), 0 failed" in free.stdout, free.stdout + free.stderr


@pytest.mark.slow
def test_unfinished_run_resumes_from_its_checkpoint(tmp_path):
    flags = [
        "--algos",
        "td3",
        "--env-ids",
        "Pendulum-v1",
        "--seeds",
        "1",
        "--total-timesteps",
        "600",
        "--checkpoint-frequency",
        "200",
        "--",
        "--learning-starts",
        "200",
        "--batch-size",
        "32",
        "--eval-episodes",
        "1",
    ]
    name = "Pendulum-v1__td3__1__600__learning-starts_200_batch-size_32_eval-episodes_1"
    # a run that stopped at step 400 with its checkpoint: the first 400 steps of the same run
    first_part = subprocess.run(
        [
            sys.executable,
            os.path.join(REPO, "td3_continuous_action.py"),
            "--env-id",
            "Pendulum-v1",
            "--seed",
            "1",
            "--total-timesteps",
            "600",
            "--run-name",
            name,
            "--checkpoint-frequency",
            "200",
            "--learning-starts",
            "200",
            "--batch-size",
            "32",
            "--eval-episodes",
            "1",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert first_part.returncode == 0
    (tmp_path / "runs" / name / "checkpoint.pt").rename(tmp_path / "final.pt")
    os.remove(tmp_path / "final.pt")
    # no checkpoint: the run starts again from scratch
    result = bench(*flags, cwd=tmp_path)
    assert "1 done" in result.stdout and "resumed" not in (tmp_path / "logs" / f"{name}.log").read_text()
    # checkpoint but no DONE: the run resumes
    os.remove(tmp_path / "runs" / name / "DONE")
    result = bench(*flags, cwd=tmp_path)
    assert (
        "1 done" in result.stdout and "had already finished its 600 steps" in (tmp_path / "logs" / f"{name}.log").read_text()
    )


@pytest.mark.slow
def test_a_failing_run_does_not_stop_the_others_and_fails_the_sweep(tmp_path):
    result = bench(
        "--algos",
        "td3",
        "sac",
        "--env-ids",
        "Pendulum-v1",
        "--seeds",
        "1",
        "--workers",
        "2",
        "--total-timesteps",
        "300",
        "--",
        "--learning-starts",
        "200",
        "--batch-size",
        "32",
        "--q-lr",
        "0.001",
        cwd=tmp_path,
    )
    assert result.returncode != 0
    assert "summary: 1 done, 0 skipped (finished before), 1 failed" in result.stdout  # td3 has no --q-lr
    assert "failed: Pendulum-v1__td3__1__300__learning-starts_200_batch-size_32_q-lr_0.001 (log: logs/" in result.stdout


# --- a real one-node Slurm cluster on localhost -------------------------------------------------


def start_slurm(tmp_path):
    """Start munged, slurmctld and slurmd for this machine alone; returns the environment to talk to them."""
    missing = [b for b in ("munged", "slurmctld", "slurmd", "sbatch") if shutil.which(b) is None]
    if missing:
        pytest.skip(f"Slurm is not installed here ({', '.join(missing)} missing): apt-get install slurm-wlm munge")
    if os.geteuid() != 0:
        pytest.skip("starting slurmctld/slurmd for a test needs root")
    host = socket.gethostname().split(".")[0]
    conf_dir = tmp_path / "slurm"
    for d in ("state", "spool", "munge"):
        (conf_dir / d).mkdir(parents=True)
    key = "/etc/munge/munge.key"
    if not os.path.exists(key):
        os.makedirs("/etc/munge", exist_ok=True)
        with open(key, "wb") as f:
            f.write(os.urandom(1024))
        shutil.chown(key, "munge", "munge")
        os.chmod(key, 0o400)
    socket_path = conf_dir / "munge" / "munge.socket.2"
    munged = subprocess.run(
        [
            "munged",
            "--force",
            f"--socket={socket_path}",
            f"--pid-file={conf_dir / 'munge' / 'munged.pid'}",
            f"--seed-file={conf_dir / 'munge' / 'seed'}",
        ],
        capture_output=True,
        text=True,
    )
    if munged.returncode != 0:
        pytest.skip(f"munged would not start: {munged.stderr.strip()}")
    memory_mb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2**20 // 2
    conf = conf_dir / "slurm.conf"
    conf.write_text(
        "\n".join(
            [
                "ClusterName=test",
                f"SlurmctldHost={host}",
                "SlurmUser=root",
                "SlurmdUser=root",
                f"StateSaveLocation={conf_dir / 'state'}",
                f"SlurmdSpoolDir={conf_dir / 'spool'}",
                f"SlurmctldPidFile={conf_dir / 'slurmctld.pid'}",
                f"SlurmdPidFile={conf_dir / 'slurmd.pid'}",
                f"SlurmctldLogFile={conf_dir / 'slurmctld.log'}",
                f"SlurmdLogFile={conf_dir / 'slurmd.log'}",
                "ProctrackType=proctrack/linuxproc",
                "TaskPlugin=task/none",
                "SelectType=select/cons_tres",
                "SelectTypeParameters=CR_Core",
                "ReturnToService=2",
                "MpiDefault=none",
                "JobAcctGatherType=jobacct_gather/none",
                f"AuthInfo=socket={socket_path}",
                f"NodeName={host} CPUs={os.cpu_count()} RealMemory={memory_mb} State=UNKNOWN",
                f"PartitionName=debug Nodes={host} Default=YES MaxTime=INFINITE State=UP",
            ]
        )
        + "\n"
    )
    env = {**os.environ, "SLURM_CONF": str(conf), "PATH": os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"]}
    for daemon in ("slurmctld", "slurmd"):
        started = subprocess.run([daemon, "-f", str(conf)], env=env, capture_output=True, text=True)
        if started.returncode != 0:
            pytest.skip(f"{daemon} would not start: {started.stderr.strip()}")
    deadline = time.time() + 30
    while time.time() < deadline:
        sinfo = subprocess.run(["sinfo", "-h", "-o", "%t"], env=env, capture_output=True, text=True)
        if sinfo.stdout.strip() in ("idle", "mix", "alloc"):
            break
        time.sleep(0.5)
    else:
        pytest.skip(f"the Slurm node never became idle (sinfo: {sinfo.stdout.strip()} {sinfo.stderr.strip()})")
    pid_files = [conf_dir / "slurmctld.pid", conf_dir / "slurmd.pid", conf_dir / "munge" / "munged.pid"]
    return env, pid_files


@pytest.fixture
def slurm(tmp_path):
    env, pid_files = start_slurm(tmp_path)
    yield env
    for pid_file in pid_files:
        try:
            os.kill(int(pid_file.read_text().strip()), 15)
        except (OSError, ValueError):
            pass


@pytest.mark.slow
def test_slurm_array_runs_every_run_of_the_sweep(slurm, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    flags = [
        "--slurm",
        "--slurm-partition",
        "debug",
        "--slurm-time",
        "00:10:00",
        "--slurm-extra",
        "--job-name=tiny-sweep",
        "--algos",
        "td3",
        "sac",
        "--env-ids",
        "Pendulum-v1",
        "--seeds",
        "1",
        *TINY,
    ]
    submitted = subprocess.run(["bash", BENCHMARK, *flags], cwd=work, env=slurm, capture_output=True, text=True, timeout=60)
    assert submitted.returncode == 0, submitted.stdout + submitted.stderr
    assert "Submitted batch job" in submitted.stdout and "submitted 2 runs as one array job" in submitted.stdout
    names = [
        "Pendulum-v1__td3__1__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1",
        "Pendulum-v1__sac__1__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1",
    ]
    deadline = time.time() + 300
    while time.time() < deadline and not all((work / "runs" / n / "DONE").exists() for n in names):
        time.sleep(1)
    for name in names:
        assert (work / "runs" / name / "DONE").exists(), (work / "logs").iterdir() and [
            p.read_text() for p in (work / "logs").iterdir()
        ]
        assert "step 300/300" in (work / "logs" / f"{name}.log").read_text()
    job_script = next((work / "slurm").iterdir()) / "job.sh"
    text = job_script.read_text()
    assert "#SBATCH --array=0-1" in text and "#SBATCH --partition=debug" in text and "#SBATCH --job-name=tiny-sweep" in text


@pytest.mark.slow
def test_runs_listed_as_finished_are_skipped(tmp_path):
    listed = tmp_path / "finished_runs.txt"
    listed.write_text("Pendulum-v1__td3__1__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1\n")
    result = bench(
        "--algos", "td3", "--env-ids", "Pendulum-v1", "--seeds", "1", "2", "--skip-listed", str(listed), *TINY, cwd=tmp_path
    )
    assert "summary: 1 done, 1 skipped (finished before), 0 failed" in result.stdout, result.stdout + result.stderr
    assert sorted(os.listdir(tmp_path / "runs")) == [
        "Pendulum-v1__td3__2__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1"
    ]
    assert "no such file" in bench("--skip-listed", "nope.txt", cwd=tmp_path).stderr


# --- --seeds-per-process: consecutive seeds in one process ------------------------------------------

FAKE_SCRIPT = '''"""A stand-in for a training script: prints its command line, makes each seed's run folder with a checkpoint."""
import os
import sys
import time


class Args:
    num_seeds: int = 1


argv = sys.argv[1:]
seed = int(argv[argv.index("--seed") + 1])
num_seeds = int(argv[argv.index("--num-seeds") + 1]) if "--num-seeds" in argv else 1
run_name = argv[argv.index("--run-name") + 1]
print("command:", " ".join(argv))
for s in range(seed, seed + num_seeds):
    os.makedirs(os.path.join("runs", run_name.replace("{seed}", str(s))), exist_ok=True)
    open(os.path.join("runs", run_name.replace("{seed}", str(s)), "checkpoint.pt"), "w").close()
time.sleep(float(os.environ.get("FAKE_SLEEP", "0")))
sys.exit(int(os.environ.get("FAKE_EXIT", "0")))
'''
FAKE = ["--algos", "fake", "--env-ids", "Pendulum-v1", "--total-timesteps", "300"]


def fake_name(seed):
    return f"Pendulum-v1__fake__{seed}__300"


@pytest.fixture
def fake(tmp_path):
    """A copy of benchmark.sh beside stand-in scripts, `fake` (it has --num-seeds), `oneseed` (it has not) and
    `checked` (its check_args refuses more than one seed), and an empty folder to sweep in: sweeps of a few
    milliseconds a run."""
    repo, work = tmp_path / "repo", tmp_path / "work"
    repo.mkdir()
    work.mkdir()
    shutil.copy(BENCHMARK, repo / "benchmark.sh")
    (repo / "fake_continuous_action.py").write_text(FAKE_SCRIPT)
    (repo / "oneseed_continuous_action.py").write_text(FAKE_SCRIPT.replace("num_seeds: int = 1", "seed: int = 1"))
    refusing = '\n\ndef check_args(args):\n    return [(args.num_seeds == 1, "--num-seeds: one seed per process")]\n'
    (repo / "checked_continuous_action.py").write_text(FAKE_SCRIPT + refusing)  # has --num-seeds, refuses 2

    def run(*flags, env=None):
        return bench(*flags, cwd=work, benchmark=str(repo / "benchmark.sh"), env=env, timeout=120)

    run.work = work
    return run


def test_seeds_per_process_groups_consecutive_seeds_and_starts_a_group_at_a_gap(tmp_path):
    flags = ["--algos", "td3", "oparl", "--env-ids", "Pendulum-v1", "--seeds", "1", "2", "3", "5", *TINY[:2]]
    result = bench(*flags, "--seeds-per-process", "4", "--dry-run", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert [p[:3] for p in planned(result.stdout)] == [("td3", 1, 3), ("oparl", 1, 3), ("td3", 5, 1), ("oparl", 5, 1)]
    assert planned(result.stdout)[0][3] == "Pendulum-v1__td3__{seed}__300"
    five = ["--algos", "td3", "--env-ids", "Pendulum-v1", "--seeds", "1", "2", "3", "4", "5", "--seeds-per-process", "2"]
    groups = [p[1:3] for p in planned(bench(*five, "--dry-run", cwd=tmp_path).stdout)]
    assert groups == [(1, 2), (3, 2), (5, 1)]
    job = bench(*five, "--dry-run", "--slurm", cwd=tmp_path).stdout  # one array task per group
    assert "#SBATCH --array=0-2" in job and "# run: td3 Pendulum-v1 3-4 default 10000 -- " in job
    assert not os.path.exists(tmp_path / "runs")


@pytest.mark.slow
def test_stopping_the_sweeps_first_process_lets_its_running_runs_finish_and_starts_no_more(fake):
    # docs/sweeps.md: kill only the `bash benchmark.sh` you started; each run's own shell writes its DONE
    sweep = subprocess.Popen(
        ["bash", str(fake.work.parent / "repo" / "benchmark.sh"), *FAKE, "--seeds", "1", "2", "3", "--workers", "2"],
        cwd=fake.work,
        env=bench_env(FAKE_SLEEP="3"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.time() + 60
    while not all((fake.work / "runs" / fake_name(seed)).exists() for seed in (1, 2)) and time.time() < deadline:
        time.sleep(0.1)
    sweep.terminate()
    _, stderr = sweep.communicate(timeout=60)  # returns once the two running runs, which hold its pipes, have ended
    assert [(fake.work / "runs" / fake_name(seed) / "DONE").exists() for seed in (1, 2)] == [True, True]
    assert not (fake.work / "runs" / fake_name(3)).exists()  # never started
    assert stderr == ""  # nothing about the progress files the stopped sweep took with it


@pytest.mark.slow
def test_seeds_per_process_one_changes_nothing(fake, tmp_path):
    assert bench("--dry-run", cwd=tmp_path).stdout == bench("--dry-run", "--seeds-per-process", "1", cwd=tmp_path).stdout
    result = fake(*FAKE, "--seeds", "1", "2", "--seeds-per-process", "1")
    assert "summary: 2 done, 0 skipped (finished before), 0 failed" in result.stdout, result.stdout + result.stderr
    for seed in (1, 2):
        assert (fake.work / "logs" / f"{fake_name(seed)}.log").read_text() == (
            "float32 kernels: mkl-default\n"
            f"command: --env-id Pendulum-v1 --seed {seed} --total-timesteps 300 --run-name {fake_name(seed)} "
            "--checkpoint-frequency 10000\n"
        )


def test_a_sweep_under_the_mkl_wrapper_says_so_in_each_runs_log(fake, tmp_path):
    library = tmp_path / "libmkl_intel_cpu_true.so"  # the wrapper's library, by name: an empty file the loader skips
    library.touch()
    result = fake(*FAKE, "--seeds", "1", env={"LD_PRELOAD": str(library)})
    assert "summary: 1 done" in result.stdout, result.stdout + result.stderr
    assert (fake.work / "logs" / f"{fake_name(1)}.log").read_text().startswith("float32 kernels: mkl-avx512\n")


@pytest.mark.slow
def test_a_group_is_one_process_for_its_seeds(fake):
    result = fake(*FAKE, "--seeds", "1", "2", "3", "4", "--seeds-per-process", "3", "--workers", "1")
    assert "summary: 4 done, 0 skipped (finished before), 0 failed" in result.stdout, result.stdout + result.stderr
    # the progress counts runs, not processes
    assert "runs: 3 finished, 0 running, 1 left" in result.stdout and "runs: 4 finished, 0 running, 0 left" in result.stdout
    logs = fake.work / "logs"
    assert (logs / f"{fake_name(1)}.log").read_text() == (
        "float32 kernels: mkl-default\n"
        f"seeds per process: 3 (output in logs/{fake_name(1)}.log)\n"
        "command: --env-id Pendulum-v1 --seed 1 --num-seeds 3 --total-timesteps 300 --run-name Pendulum-v1__fake__{seed}__300 "
        "--checkpoint-frequency 10000\n"
    )
    for seed in (2, 3):
        assert (logs / f"{fake_name(seed)}.log").read_text() == (
            f"float32 kernels: mkl-default\nseeds per process: 3 (output in logs/{fake_name(1)}.log)\n"
        )
    assert "--seed 4 --total-timesteps 300" in (logs / f"{fake_name(4)}.log").read_text()  # a group of one: as ever
    assert all((fake.work / "runs" / fake_name(seed) / "DONE").exists() for seed in (1, 2, 3, 4))


@pytest.mark.slow
def test_a_group_leaves_out_finished_runs(fake):
    (fake.work / "runs" / fake_name(2)).mkdir(parents=True)
    (fake.work / "runs" / fake_name(2) / "DONE").touch()
    listed = fake.work / "finished_runs.txt"
    listed.write_text(fake_name(5) + "\n")
    flags = [*FAKE, "--seeds", "1", "2", "3", "4", "5", "--seeds-per-process", "5", "--skip-listed", str(listed)]
    assert [p[1:3] for p in planned(fake(*flags, "--dry-run").stdout) if p[0] == "fake"] == [(1, 1), (3, 2)]
    result = fake(*flags)
    assert "summary: 3 done, 2 skipped (finished before), 0 failed" in result.stdout, result.stdout + result.stderr
    assert os.listdir(fake.work / "runs" / fake_name(2)) == ["DONE"] and not (fake.work / "runs" / fake_name(5)).exists()
    assert "--seed 3 --num-seeds 2 " in (fake.work / "logs" / f"{fake_name(3)}.log").read_text()
    nothing_left = fake(*FAKE, "--seeds", "2", "5", "--seeds-per-process", "2", "--skip-listed", str(listed), "--slurm")
    assert nothing_left.returncode == 0 and "nothing to submit: the sweep's 2 runs are all finished" in nothing_left.stdout


@pytest.mark.slow
def test_a_group_resumes_from_its_first_runs_folder(fake):
    runs = fake.work / "runs"
    for seed in (1, 2, 4):  # 1-2 stopped with their checkpoints; 3-4 died before theirs (4's is another run's)
        (runs / fake_name(seed)).mkdir(parents=True)
        (runs / fake_name(seed) / "events").touch()
        if seed != 3:
            (runs / fake_name(seed) / "checkpoint.pt").touch()
    result = fake(*FAKE, "--seeds", "1", "2", "3", "4", "--seeds-per-process", "2")
    assert "summary: 4 done, 0 skipped (finished before), 0 failed" in result.stdout, result.stdout + result.stderr
    log = (fake.work / "logs" / f"{fake_name(1)}.log").read_text()
    assert log.rstrip().endswith(f"--checkpoint-frequency 10000 --resume runs/{fake_name(1)}")
    assert (runs / fake_name(2) / "events").exists()  # a resumed group's folders are kept
    assert "--resume" not in (fake.work / "logs" / f"{fake_name(3)}.log").read_text()
    assert not (runs / fake_name(4) / "events").exists()  # a group that starts again starts every run afresh


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("flock") is None, reason="flock (util-linux) is not installed: runs are not locked")
def test_a_group_is_busy_if_any_of_its_runs_is_and_fails_as_a_whole(fake):
    flags = [*FAKE, "--seeds", "1", "2", "3", "--seeds-per-process", "2"]
    (fake.work / "logs").mkdir()
    with open(fake.work / "logs" / f"{fake_name(2)}.lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        busy = fake(*flags)
    assert "summary: 1 done, 0 skipped (finished before), 0 failed" in busy.stdout, busy.stdout + busy.stderr
    for seed in (1, 2):
        assert f"left alone, running in another sweep: {fake_name(seed)}" in busy.stdout
    assert not (fake.work / "runs" / fake_name(1)).exists()
    failed = fake(*flags, env={"FAKE_EXIT": "1"})
    assert failed.returncode != 0
    assert "summary: 0 done, 1 skipped (finished before), 2 failed" in failed.stdout
    for seed in (1, 2):  # each run of the group failed, its output in the group's log
        assert f"failed: {fake_name(seed)} (log: logs/{fake_name(1)}.log)" in failed.stdout


@pytest.mark.slow
def test_seeds_per_process_needs_a_script_with_num_seeds(fake):
    refused = fake(*FAKE[:1], "fake", "oneseed", *FAKE[2:], "--seeds", "1", "2", "--seeds-per-process", "2")
    assert refused.returncode == 2 and refused.stderr.strip().splitlines() == [
        "error: --seeds-per-process 2: oneseed_continuous_action.py has no --num-seeds (one seed per process)"
    ]
    assert os.listdir(fake.work) == []  # refused before anything ran
    assert fake("--algos", "oneseed", *FAKE[2:], "--seeds", "1", "2", "--seeds-per-process", "1", "--dry-run").returncode == 0
    checked = fake("--algos", "checked", *FAKE[2:], "--seeds", "1", "2", "--seeds-per-process", "2", "--dry-run")
    assert checked.returncode == 2 and checked.stderr.strip().splitlines() == [
        "error: --seeds-per-process 2: checked_continuous_action.py trains one seed per process (its --num-seeds check)"
    ]


@pytest.mark.slow
def test_a_real_group_trains_its_seeds_in_one_process(tmp_path):
    result = bench(
        "--algos", "td3", "--env-ids", "Pendulum-v1", "--seeds", "1", "2", "--seeds-per-process", "2", *TINY, cwd=tmp_path
    )
    assert "summary: 2 done, 0 skipped (finished before), 0 failed" in result.stdout, result.stdout + result.stderr
    first, second = (
        f"Pendulum-v1__td3__{seed}__300__learning-starts_200_batch-size_32_eval-frequency_300_eval-episodes_1"
        for seed in (1, 2)
    )
    assert (tmp_path / "runs" / first / "DONE").exists() and (tmp_path / "runs" / second / "DONE").exists()
    assert "seed 2 step 300" in (tmp_path / "logs" / f"{first}.log").read_text()
    assert f"seeds per process: 2 (output in logs/{first}.log)" in (tmp_path / "logs" / f"{second}.log").read_text()


# --- --gpu: the sweep on one GPU ---------------------------------------------------------------------------------


def fake_gpu(tmp_path, free_mib) -> dict:
    """An nvidia-smi that reports `free_mib` MiB free, first on PATH."""
    bin_dir = tmp_path / "fake_bin"
    bin_dir.mkdir(exist_ok=True)
    (bin_dir / "nvidia-smi").write_text(f"#!/bin/sh\necho {free_mib}\n")
    (bin_dir / "nvidia-smi").chmod(0o755)
    (bin_dir / "nvidia-cuda-mps-control").write_text("#!/bin/sh\nexit 0\n")  # "MPS is running": none is started
    (bin_dir / "nvidia-cuda-mps-control").chmod(0o755)
    return {"PATH": f"{bin_dir}{os.pathsep}{os.path.dirname(sys.executable)}{os.pathsep}{os.environ['PATH']}"}


GPU_SWEEP = ["--gpu", "--algos", "td3", "oparl", "--env-ids", "Pendulum-v1", "--seeds", "1", "2", "3", "--workers", "16"]


def test_gpu_sweep_groups_the_seeds_records_its_updates_and_keeps_the_run_names(tmp_path):
    """--gpu: the seeds of a task and script in one process (up to 16), --cudagraphs on each, the run names a CPU
    sweep gives them; the memory estimate said before anything starts."""
    result = bench(*GPU_SWEEP, "--total-timesteps", "1000000", "--dry-run", cwd=tmp_path, env=fake_gpu(tmp_path, 81000))
    assert result.returncode == 0, result.stderr
    assert [p[:4] for p in planned(result.stdout)] == [
        ("td3", 1, 3, "Pendulum-v1__td3__{seed}__1000000"),
        ("oparl", 1, 3, "Pendulum-v1__oparl__{seed}__1000000"),
    ]
    assert all(p[4] == ["--cudagraphs"] for p in planned(result.stdout))
    assert result.stderr.startswith("gpu_fit: 2 process(es) at once need about ")
    assert "the GPU has 79.1 GiB free" in result.stderr
    mixed = bench(*GPU_SWEEP[:3], "redq", *GPU_SWEEP[4:], "--dry-run", cwd=tmp_path, env=fake_gpu(tmp_path, 81000))
    assert [p[:3] for p in planned(mixed.stdout)][:2] == [("td3", 1, 3), ("redq", 1, 3)]


def test_gpu_sweep_that_would_not_fit_is_refused_in_one_line_before_it_starts(tmp_path):
    result = bench(*GPU_SWEEP, "--total-timesteps", "1000000", cwd=tmp_path, env=fake_gpu(tmp_path, 2000))
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.strip().count("\n") == 0 and result.stderr.startswith("error: 2 process(es) at once need about")
    assert "the GPU has 2.0 GiB free: run fewer at once (--workers) or fewer seeds a process (--seeds-per-process)" in (
        result.stderr
    )
    assert not os.path.exists(tmp_path / "runs") and not os.path.exists(tmp_path / "logs")


def test_gpu_sweep_is_not_a_slurm_array(tmp_path):
    result = bench(*GPU_SWEEP, "--slurm", "--dry-run", cwd=tmp_path, env=fake_gpu(tmp_path, 81000))
    assert result.returncode == 2 and result.stdout == "" and result.stderr.strip().count("\n") == 0
    assert result.stderr.startswith("error: --gpu runs the sweep on this machine's GPU, not as a Slurm array")


def test_gpu_sweep_without_nvidia_smi_previews_in_a_dry_run_and_refuses_to_train(tmp_path):
    """No nvidia-smi (a CPU machine): --dry-run prints the plan and says the memory check waits; a real run stops in
    one line before anything starts."""
    path = os.pathsep.join([os.path.dirname(sys.executable), "/usr/bin", "/bin"])
    if shutil.which("nvidia-smi", path=path):
        pytest.skip("nvidia-smi is installed in /usr/bin or /bin here")
    preview = bench(*GPU_SWEEP, "--total-timesteps", "1000000", "--dry-run", cwd=tmp_path, env={"PATH": path})
    assert preview.returncode == 0, preview.stderr
    assert [p[:3] for p in planned(preview.stdout)] == [("td3", 1, 3), ("oparl", 1, 3)]
    assert (
        preview.stderr.strip()
        == "dry run: no nvidia-smi here, so the GPU memory check (tools/gpu_fit.py) is left to the real run"
    )
    real = bench(*GPU_SWEEP, "--total-timesteps", "1000000", cwd=tmp_path, env={"PATH": path})
    assert real.returncode == 2 and real.stdout == "" and real.stderr.strip().count("\n") == 0
    assert real.stderr.startswith("error: --gpu trains on this machine's CUDA GPU, and there is no nvidia-smi here")
    assert not os.path.exists(tmp_path / "runs") and not os.path.exists(tmp_path / "logs")


@pytest.mark.slow
def test_gpu_sweep_logs_the_gpu_as_the_runs_kernels(tmp_path):
    """A --gpu run's log names the GPU's kernels (recorded as CUDA graphs where the script takes --cudagraphs), not
    the CPU's (here, without CUDA, td3 then refuses --cudagraphs in one line, and PPO trains on the CPU)."""
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA GPU is here: td3 would train under --cudagraphs (test_cudagraphs.py covers that)")
    result = bench(
        "--gpu", "--algos", "td3", "ppo", "--env-ids", "Pendulum-v1", "--seeds", "1", "--total-timesteps", "300",
        "--workers", "2", cwd=tmp_path, env=fake_gpu(tmp_path, 81000),
    )  # fmt: skip
    for algo, kernels in (("td3", "cuda-cudagraphs"), ("ppo", "cuda")):
        log = open(tmp_path / "logs" / f"Pendulum-v1__{algo}__1__300.log").read()
        assert log.startswith(f"float32 kernels: {kernels}\n"), log
    assert not (tmp_path / "runs" / "Pendulum-v1__td3__1__300" / "DONE").exists(), result.stdout


def test_gpu_fit_adds_each_process_context_buffers_and_networks(monkeypatch, capsys):
    """The arithmetic: a process is its CUDA context plus, per seed, its replay buffer (rows of 2 obs + action + 2
    floats) and its networks; the `--workers` largest run at once."""
    sys.path.insert(0, os.path.join(REPO, "tools"))
    import gpu_fit

    obs, act = gpu_fit.dims("Pendulum-v1")
    assert (obs, act) == (3, 1)
    command = [sys.executable, os.path.join(REPO, "td3_continuous_action.py"), "--env-id", "Pendulum-v1"]
    three = [*command, "--seed", "1", "--num-seeds", "3", "--run-name", "r{seed}", "--total-timesteps", "200000"]
    mib, _ = gpu_fit.process_mib(three)
    assert mib == pytest.approx(gpu_fit.CONTEXT_MIB + 3 * (200000 * (2 * 3 + 1 + 2) * 4 / 2**20 + gpu_fit.NETWORKS_MIB))
    one = [*command, "--buffer-size", "1000", "--total-timesteps", "200000"]  # rows: the smaller of the two
    assert gpu_fit.process_mib(one)[0] == pytest.approx(gpu_fit.CONTEXT_MIB + 1000 * 9 * 4 / 2**20 + gpu_fit.NETWORKS_MIB)
    lines = [shlex.join(three), shlex.join(one), shlex.join(one)]
    need = mib + gpu_fit.process_mib(one)[0]  # the two largest of three, with --workers 2
    monkeypatch.setattr(sys, "stdin", io.StringIO("\n".join(lines)))
    gpu_fit.main(["--workers", "2", "--free-mib", str(need + 1)])
    assert f"need about {need / 1024:,.1f} GiB" in capsys.readouterr().out
    monkeypatch.setattr(sys, "stdin", io.StringIO("\n".join(lines)))
    with pytest.raises(SystemExit, match="^error: 2 process"):
        gpu_fit.main(["--workers", "2", "--free-mib", str(need - 1)])
