"""--cudagraphs: the recorded updates learn what the eager ones learn, resume exactly, and refuse a CPU.

The tests that need a GPU skip on a machine without CUDA (CI has none); run them on one with
`python -m pytest tests/test_cudagraphs.py tests/test_reliability.py -k cudagraphs`."""

import os
import sys

import numpy as np
import pytest
import torch

from conftest import OFF_POLICY, REPO, cli_flags, critic_lr_flag, load, needs_cuda, parse, scalars, script_command, small_args
import forkserver

LOSSES = ["losses/qf_loss", "losses/qf_values"]
# (script, seeds in the process)
SEED_CASES = [(s, n) for s in OFF_POLICY for n in (1, 3)]


@needs_cuda
@pytest.mark.parametrize("script,num_seeds", SEED_CASES)
def test_graphs_train_as_the_eager_updates_do(script, num_seeds, tmp_path, monkeypatch):
    """Same seed, with and without --cudagraphs: the same losses at every logged step (the first
    updates run eagerly as warm-up, the rest are replays) and the same final actor; with 3 seeds in
    one process, for every seed (the generator advances inside the graphs as it does eagerly)."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    runs = {}
    for graphs in (False, True):
        args = small_args(
            module,
            env_id="Pendulum-v1",
            total_timesteps=800,
            learning_starts=300,
            eval_frequency=800,
            cudagraphs=graphs,
            num_seeds=num_seeds,
            run_name=f"graphs_{graphs}_{{seed}}",
        )
        runs[graphs] = module.main(args)
    assert len(runs[True]["run_dirs"]) == num_seeds
    for eager_dir, graphed_dir in zip(runs[False]["run_dirs"], runs[True]["run_dirs"]):
        eager, graphed = scalars(eager_dir), scalars(graphed_dir)
        for tag in LOSSES:
            steps = [step for step, _ in eager[tag]]
            assert steps == [step for step, _ in graphed[tag]] and len(steps) >= 4, (eager_dir, tag)
            torch.testing.assert_close(
                torch.tensor([v for _, v in graphed[tag]]), torch.tensor([v for _, v in eager[tag]]), rtol=1e-4, atol=1e-5
            )
    for (name, a), b in zip(runs[False]["actor"].state_dict().items(), runs[True]["actor"].state_dict().values()):
        torch.testing.assert_close(b, a, rtol=1e-3, atol=1e-4, msg=name)


@needs_cuda
@pytest.mark.parametrize("script,num_seeds", SEED_CASES)
def test_training_syncs_nothing_with_the_host_once_recorded(script, num_seeds, tmp_path, monkeypatch):
    """From drawing a batch to the end of a replayed update the host waits for nothing: under torch's
    'error' sync debug mode any .item(), host copy or NaN check there would raise."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    args = small_args(
        module,
        env_id="Pendulum-v1",
        total_timesteps=400,
        learning_starts=300,
        eval_frequency=400,
        cudagraphs=True,
        num_seeds=num_seeds,
        run_name="strict_{seed}",
    )
    sample, call = module.ReplayBuffer.sample, module.CudaGraph.__call__
    replays = []

    def strict_sample(self, *shape):
        torch.cuda.set_sync_debug_mode("error")  # on until the update returns
        return sample(self, *shape)

    def strict_call(self, *inputs):
        try:
            if self.key(*inputs) not in self.graphs:  # warm-up and recording may sync; replays must not
                torch.cuda.set_sync_debug_mode("default")
            else:
                replays.append(self.key(*inputs))
            return call(self, *inputs)
        finally:
            torch.cuda.set_sync_debug_mode("default")

    monkeypatch.setattr(module.ReplayBuffer, "sample", strict_sample)
    monkeypatch.setattr(module.CudaGraph, "__call__", strict_call)
    module.main(args)
    assert len(replays) > 50


@needs_cuda
@pytest.mark.parametrize("script", OFF_POLICY)
def test_non_finite_loss_under_graphs_stops_at_a_logging_step(script, tmp_path):
    flags = [
        "--env-id",
        "Pendulum-v1",
        *cli_flags(script, total_timesteps=800, learning_starts=100, batch_size=32, eval_frequency=800, eval_episodes=1),
    ]
    command = script_command(script, *flags, critic_lr_flag(script), "1e30", "--cudagraphs", "--run-name", "nan")
    result = forkserver.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith("error: ") and "became non-finite by step" in line and "--cudagraphs checks every 100 steps" in line


@needs_cuda
@pytest.mark.parametrize("script", OFF_POLICY)
def test_phase_times_charges_the_recorded_update_to_its_replay(script, tmp_path):
    """tools/speed/phase_times.py under --cudagraphs: after warm-up every update is a replay (no eager critic update is
    timed), and the synchronising timers leave the recording intact (the run ends and reports)."""
    flags = cli_flags(script, total_timesteps=600, learning_starts=100, batch_size=32, eval_frequency=600, eval_episodes=1)
    tool = [sys.executable, os.path.join(REPO, "tools", "speed", "phase_times.py"), script, "--env-id", "Pendulum-v1", *flags]
    result = forkserver.run([*tool, "--cudagraphs", "--warmup-updates", "20"], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    summary = next(line for line in result.stdout.splitlines() if "training steps timed on" in line)
    assert "480 training steps timed on" in summary and "timed on cpu" not in summary
    syncs = next(line for line in result.stdout.splitlines() if line.startswith("(synchronised at every phase's"))
    assert float(syncs.split(": ")[1].split()[0]) >= 8  # acting, env, store, sample, replay: a start and an end each
    assert "| update: graph replay and input copies |" in result.stdout and "| update: critic |" not in result.stdout


@pytest.mark.parametrize("script", OFF_POLICY)
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=needs_cuda)])
def test_acting_sends_observations_to_the_device_without_waiting_for_it(script, device):
    """to_device, acting's copy of the observations: the same values on the device; to a GPU without waiting for
    the work queued before it (as a replaying update): the GPU is still busy when it returns, where a plain copy
    from pageable memory (the control) returns only once the GPU is idle."""
    module = load(script)
    obs = np.random.default_rng(0).standard_normal((3, 5), dtype=np.float32)
    if device == "cuda":
        module.to_device(obs, torch.device(device))  # the first pinned block is allocated before timing starts
        for copy, waits in [
            (lambda: torch.as_tensor(obs, device=device), True),
            (lambda: module.to_device(obs, torch.device(device)), False),
        ]:
            torch.cuda.synchronize()
            torch.cuda._sleep(100_000_000)  # a kernel that keeps the GPU busy for tens of milliseconds
            copy()
            assert torch.cuda.current_stream().query() == waits  # query(): whether everything queued has finished
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")  # and no synchronisation that torch's sync debug mode sees
    try:
        moved = module.to_device(obs, torch.device(device))
        again = module.to_device(moved, torch.device(device))  # a tensor already there stays as it is
    finally:
        if device == "cuda":
            torch.cuda.set_sync_debug_mode("default")
    assert moved.device.type == device and moved.dtype == torch.float32 and again is moved
    assert torch.equal(moved.cpu(), torch.from_numpy(obs))


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize("script", OFF_POLICY)
def test_cudagraphs_without_a_gpu_is_refused_in_one_line(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    module = load(script)
    with pytest.raises(SystemExit) as exit_info:
        module.main(parse(module, ["--cudagraphs"]))
    assert str(exit_info.value) == "error: --cudagraphs needs a CUDA GPU; torch finds none here"
