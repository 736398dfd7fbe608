"""The tests' fork server (tests/forkserver.py): a script forked from it starts as `python script.py` would, and what it
cannot serve runs as a new process."""

import os
import signal
import subprocess
import sys
import time

import pytest

import forkserver

pytestmark = pytest.mark.skipif(forkserver.server() is None, reason="no fork server here (FORKSERVER=0, or no SOCK_SEQPACKET)")

# what a script sees of its start, one line each; then its stderr line, then its exit
PROBE = """import os, random, sys
preloaded = "torch" in sys.modules
import torch
torch_draw = torch.rand(1).item()
print(sys.argv)
print(os.getcwd())
print(sys.path[:2])
print(__name__, os.environ.get("PROBE_VALUE"), os.environ.get("PYTHONUNBUFFERED"))
print("preloaded" if preloaded else "new")
print(random.random(), torch_draw)
print("to stderr", file=sys.stderr)
if sys.argv[1] == "raise":
    raise ValueError("the probe's error")
if sys.argv[1] == "sleep":
    print("before the sleep", flush=False)
    import time
    time.sleep(60)
sys.exit(int(sys.argv[1]))
"""


@pytest.fixture
def probe(tmp_path):
    (tmp_path / "scripts").mkdir()
    path = tmp_path / "scripts" / "probe.py"
    path.write_text(PROBE)
    return path


def both(command, cwd, env):
    """(forked, new process) of one command."""
    forked = forkserver.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=60)
    new = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=60)
    return forked, new


@pytest.mark.parametrize("argument", ["0", "3", "raise"])
def test_a_forked_script_starts_ends_and_prints_as_a_new_interpreter_runs_it(probe, tmp_path, argument):
    env = {**os.environ, "PROBE_VALUE": "child's own", "PYTHONPATH": str(tmp_path)}
    forked, new = both([sys.executable, str(probe), argument], tmp_path, env)
    lines, new_lines = forked.stdout.splitlines(), new.stdout.splitlines()
    assert lines[4] == "preloaded" and new_lines[4] == "new"  # the first one was forked
    assert lines[:4] == new_lines[:4]  # argv, cwd, the script's folder then PYTHONPATH, __name__ and the environment
    assert lines[3] == f"__main__ child's own {env.get('PYTHONUNBUFFERED')}"
    assert forked.returncode == new.returncode == {"0": 0, "3": 3, "raise": 1}[argument]
    assert forked.stderr.splitlines()[0] == new.stderr.splitlines()[0] == "to stderr"
    assert forked.stderr.splitlines()[-1] == new.stderr.splitlines()[-1]  # "ValueError: the probe's error" on raise


def test_forked_scripts_draw_their_own_global_generators(probe, tmp_path):
    """Python's, NumPy's (the probe draws from Python's) and torch's global generators, each drawn anew in a child."""
    draws = [
        forkserver.run([sys.executable, str(probe), "0"], cwd=tmp_path, capture_output=True, text=True).stdout.splitlines()[5]
        for _ in range(2)
    ]
    (python_1, torch_1), (python_2, torch_2) = (d.split() for d in draws)
    assert python_1 != python_2 and torch_1 != torch_2


def test_a_variable_read_as_a_library_loads_runs_a_new_process(probe, tmp_path):
    """OMP_NUM_THREADS set otherwise than the server's would not reach its OpenMP: a new process runs it."""
    env = {**os.environ, "OMP_NUM_THREADS": str(int(os.environ.get("OMP_NUM_THREADS", "1")) + 1)}
    result = forkserver.run([sys.executable, str(probe), "0"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.splitlines()[4] == "new"
    other = forkserver.run([sys.executable, "-c", "import sys; print('torch' in sys.modules)"], capture_output=True, text=True)
    assert other.stdout == "False\n"  # not a script: a new process


def test_a_variable_of_the_tests_own_environment_changed_starts_a_server_for_it(probe, tmp_path, monkeypatch):
    """A test that sets such a variable in the test process (torch.compile sets TORCHINDUCTOR_CACHE_DIR) leaves the
    later runs forked, from a server started with it."""
    first = forkserver.server()
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    result = forkserver.run([sys.executable, str(probe), "0"], cwd=tmp_path, capture_output=True, text=True)
    assert result.stdout.splitlines()[4] == "preloaded" and forkserver.server() is not first
    assert forkserver.server().env["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "inductor")


def test_a_forked_process_is_killed_waited_for_and_timed_out_as_a_popen(probe, tmp_path):
    log = open(tmp_path / "log", "w")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = forkserver.Popen(
        [sys.executable, str(probe), "sleep"], cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT, env=env
    )
    assert isinstance(process, forkserver.Forked)
    with pytest.raises(subprocess.TimeoutExpired):
        process.wait(timeout=0.5)
    deadline = time.time() + 30
    while "before the sleep" not in (tmp_path / "log").read_text() and time.time() < deadline:
        time.sleep(0.05)
    assert process.poll() is None
    process.send_signal(signal.SIGKILL)
    assert process.wait() == -signal.SIGKILL
    # unbuffered: every line printed before the kill is in the log, stderr's among them
    log.close()
    assert (tmp_path / "log").read_text().splitlines()[-2:] == ["to stderr", "before the sleep"]
    with pytest.raises(subprocess.TimeoutExpired):
        forkserver.run([sys.executable, str(probe), "sleep"], cwd=tmp_path, timeout=1, capture_output=True)
