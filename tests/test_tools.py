"""The measuring tools run and report what they say, on tiny settings."""
import os
import shutil
import subprocess
import sys

import pytest

from conftest import REPO


def tool(name, *flags, timeout=600):
    return subprocess.run([sys.executable, os.path.join(REPO, "tools", name), *flags], capture_output=True, text=True, timeout=timeout)


def test_throughput_reports_a_median_table_with_ratios():
    result = tool("throughput.py", "td3 --batch-size 32", "td3 --batch-size 32 --bf16", "--env-id", "Pendulum-v1", "--learning-starts", "100", "--steps", "60", "--repeats", "1")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert "| `td3 --batch-size 32 --bf16` |" in result.stdout
    assert next(line for line in lines if line.startswith("| `td3 --batch-size 32` |")).endswith("| 1.00x |")
    assert [line.split(":")[0] for line in result.stderr.splitlines() if line.startswith("repeat")] == ["repeat 1/1 td3 --batch-size 32", "repeat 1/1 td3 --batch-size 32 --bf16"]


def test_throughput_refuses_bad_settings():
    result = tool("throughput.py", "td3", "--steps", "0")
    assert result.returncode != 0 and "--steps must be > 0" in result.stderr
    result = tool("throughput.py", "td3", "--baseline", "sac")
    assert result.returncode != 0 and "is not one of the entries" in result.stderr


def test_levers_prints_one_row_per_lever():
    result = tool("levers.py", "--repeats", "1", "--calls", "2")
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ") and not line.startswith("| lever")]
    assert len(rows) == 9 and any("fused" in row for row in rows)


def test_profile_run_attributes_samples_to_phases():
    if shutil.which("py-spy") is None:
        pytest.skip("py-spy is not installed (pip install py-spy)")
    result = tool("profile_run.py", "td3", "--env-id", "Pendulum-v1", "--learning-starts", "100", "--total-timesteps", "600", "--batch-size", "32", "--eval-episodes", "1")
    if result.returncode != 0 and "Permission" in result.stderr:
        pytest.skip(f"py-spy may not sample here: {result.stderr.strip()}")
    assert result.returncode == 0, result.stderr
    assert "| critic update (forward, backward, Adam) |" in result.stdout and "| TD target |" in result.stdout


def test_memory_tool_reports_checkpoint_cost_and_resident_memory():
    result = tool("memory.py", "checkpoint", "--script", "td3", "--rows", "1000")
    assert result.returncode == 0, result.stderr
    assert "td3, Hopper-v4 shapes, 1000 transitions:" in result.stdout and "MiB" in result.stdout and "write" in result.stdout
    result = tool("memory.py", "rss", "td3", "--env-id", "Pendulum-v1", "--total-timesteps", "300", "--learning-starts", "256")
    assert result.returncode == 0, result.stderr
    assert "resident memory" in result.stdout and "peak" in result.stdout
