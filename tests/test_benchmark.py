"""benchmark.sh: the sweep's commands, parallel runs, skip and resume, failures, and a real Slurm."""

import fcntl
import os
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


def bench(*flags, cwd, timeout=600):
    env = {**os.environ, "PATH": os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"]}
    return subprocess.run(["bash", BENCHMARK, *flags], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


def test_help_lists_the_flags(tmp_path):
    result = bench("--help", cwd=tmp_path)
    assert result.returncode == 0
    for flag in (
        "--algos",
        "--env-ids",
        "--suite",
        "--seeds",
        "--total-timesteps",
        "--workers",
        "--dry-run",
        "--slurm-partition",
        "--slurm-extra",
    ):
        assert flag in result.stdout


def test_dry_run_prints_one_command_per_run_with_deterministic_names(tmp_path):
    result = bench(
        "--algos",
        "td3",
        "oparl",
        "--env-ids",
        "dm_control/cartpole-balance-v0",
        "--seeds",
        "1",
        "2",
        "--dry-run",
        *TINY,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 4 and all("--run-one" in line for line in lines)
    assert "--run-one oparl dm_control/cartpole-balance-v0 2 300 10000 -- --learning-starts 200" in lines[3]
    assert not os.path.exists(tmp_path / "runs")


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
