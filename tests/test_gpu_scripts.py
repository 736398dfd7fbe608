"""The GPU session scripts (tools/speed/gpu_seed_scaling.sh, tools/speed/gpu_speed.sh, their tools/speed/gpu_common.sh)
spend a lease that cannot be bought back, so their bookkeeping is checked here, on a CPU, with python, nvidia-smi and
the MPS control program replaced by fakes that only record how they were called: which steps run for a FIRST_STEP and
a BUDGET, where a call stops, what the log tells the next call, that every tool they call is where they call it, and
that MPS ends off."""

import os
import re
import subprocess

from conftest import REPO

FAKES = {
    # every python call is recorded with whether the fake MPS daemon was up, never run
    "python": '#!/bin/sh\necho "$*" "[daemon $(cat "$MPS.up" 2>/dev/null || echo off)]" >> "$CALLS"\n',
    "nvidia-smi": "#!/bin/sh\necho 'Fake GPU'\n",
    # the MPS control program: -d starts the daemon, "quit" on stdin stops it
    "nvidia-cuda-mps-control": (
        '#!/bin/sh\nif [ "$1" = -d ]; then echo start >> "$MPS"; echo on > "$MPS.up"; '
        'else read c; echo "$c" >> "$MPS"; echo off > "$MPS.up"; fi\n'
    ),
}


def run_script(tmp_path, script, first_step=None, budget=10_000):
    fakes = tmp_path / "fakes"
    fakes.mkdir(exist_ok=True)
    for name, body in FAKES.items():
        (fakes / name).write_text(body)
        (fakes / name).chmod(0o755)
    env = dict(os.environ, PATH=f"{fakes}:{os.environ['PATH']}", OUT=str(tmp_path / "out"), BUDGET=str(budget))
    env.update(CALLS=str(tmp_path / "calls.txt"), MPS=str(tmp_path / "mps.txt"), CLEANRL=str(tmp_path / "no_cleanrl"))
    env.update(MPS_STATE=str(tmp_path / "mps_state"), MPS_SETTLE="0")  # a fresh machine's record of MPS: none (off)
    args = ["bash", os.path.join(REPO, "tools", "speed", script)] + ([str(first_step)] if first_step else [])
    result = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    read = lambda name: (tmp_path / name).read_text().splitlines() if (tmp_path / name).exists() else []  # noqa: E731
    calls = read("calls.txt")
    # the fake python runs nothing: each script it was given must be there, where the repository's root (the working
    # folder of a session) has it
    scripts = {call.split()[0] for call in calls if call.split()[0].endswith(".py")}
    assert scripts and all(os.path.isfile(os.path.join(REPO, script)) for script in scripts), scripts
    return read("out/log.txt"), calls, read("mps.txt")


def numbered_steps(log):
    return [int(m.group(1)) for line in log if (m := re.match(r"== step (\d+) at", line))]


def test_scaling_runs_every_step_in_order_and_the_baseline_once(tmp_path):
    log, calls, mps = run_script(tmp_path, "gpu_seed_scaling.sh")
    steps = numbered_steps(log)
    assert steps == list(range(1, len(steps) + 1)) and len(steps) >= 20, steps
    assert sum(line.startswith("== every call") for line in log) == 1
    assert log[-1].startswith("done at")
    timed = [c for c in calls if c.startswith("tools/speed/throughput.py")]
    assert len(timed) == len(steps) - 2 + 1  # steps 1-2 are the environment cost and the tests, plus the baseline
    assert all("--cuda --window" in c and "--csv" in c for c in timed)
    # each row is labelled with how it ran; several processes ran both ways, one process always without MPS
    assert all(c.endswith(("--label mps=on [daemon on]", "--label mps=off [daemon off]")) for c in timed), timed
    several = [c for c in timed if re.match(r"\d+x:", c.split()[1])]
    assert {c.endswith("[daemon on]") for c in several} == {True, False}
    assert all(c.endswith("[daemon off]") for c in timed if c not in several)
    assert mps and mps[0] == "start" and mps[-1] == "quit"


def test_scaling_resumes_at_first_step_with_the_baseline(tmp_path):
    log, calls, _ = run_script(tmp_path, "gpu_seed_scaling.sh", first_step=16)
    steps = numbered_steps(log)
    assert steps[0] == 16 and steps == list(range(16, 16 + len(steps)))
    assert sum(line.startswith("== every call") for line in log) == 1
    first = next(c for c in calls if c.startswith("tools/speed/throughput.py"))
    assert first.split()[1] == "oparl" and "--num-seeds" not in first  # the one-seed baseline runs before step 16


def test_scaling_stops_before_the_first_step_that_does_not_fit(tmp_path):
    # the baseline needs ~25 s and step 3 ~60 s: with 55 s the call runs the baseline, then stops for good (step 4,
    # which would fit, must not run out of order) and names the step to start the next call from
    log, calls, mps = run_script(tmp_path, "gpu_seed_scaling.sh", first_step=3, budget=55)
    assert numbered_steps(log) == []
    assert sum(line.startswith("== every call") for line in log) == 1
    assert any("run again with FIRST_STEP 3" in line for line in log), log
    assert len([c for c in calls if c.startswith("tools/speed/throughput.py")]) == 1
    assert mps == []  # the baseline runs without MPS; nothing was started, so nothing to stop


def test_speed_runs_its_steps_without_cleanrl_and_without_mps(tmp_path):
    log, calls, mps = run_script(tmp_path, "gpu_speed.sh", first_step=2)
    assert numbered_steps(log) == [2, 3, 4, 5, 6, 7, 8, 9]
    assert any("no CleanRL folder" in line for line in log)
    phases = [c for c in calls if c.startswith("tools/speed/phase_times.py")]
    pairs = [script for script in ("td3", "oparl", "sac", "redq") for _ in range(4)]
    assert [c.split()[1] for c in phases] == pairs + ["td3", "oparl", "redq"]
    assert [("--no-sync" in c) for c in phases] == [True] * 16 + [False] * 3
    assert [("--blocking-copy" in c) for c in phases] == [False, True, True, False] * 4 + [False] * 3  # A B B A
    speed = [c for c in calls if c.startswith("tools/speed/throughput.py")]
    assert len(speed) == 1 and "dm_control/cartpole-swingup-v0" in speed[0] and "_continuous_action.py" not in speed[0]
    assert mps == []
