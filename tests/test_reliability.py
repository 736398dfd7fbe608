"""Checkpoints, exact resume after SIGKILL, safe loading, the NaN guard, and every bad input."""

import os
import random
import signal
import subprocess
import time

import numpy as np
import pytest
import torch

from conftest import (
    OFF_POLICY,
    ON_POLICY,
    SCRIPTS,
    cli_flags,
    critic_lr_flag,
    declared,
    load,
    needs_cuda,
    parse,
    refusal,
    scalars,
    script_command,
)
import forkserver
from rl_utils import checkpoints, make_env


# (total steps, first step of learning, checkpoint frequency) of the kill-and-resume runs, by where the kills fall.
# "learning": one kill, after the checkpoint at step 500, where learning starts (the on-policy scripts: the first
# episode end from there), mid-episode where the env is Hopper's. "random+trained": two kills of one run, against one
# uninterrupted run: after the checkpoint at step 800, before learning starts at 1000, so that the resumed run acts
# at random from the action space's restored generator for its first steps; then, once resumed, after the checkpoint
# at step 1600, 600 training steps on, so that the checkpoint holds optimizer states (Adam's step counts and moments)
# that the second resume must restore: at "learning"'s checkpoint no optimizer of an off-policy script has stepped.
PHASES = {"learning": (1500, 500, 500), "random+trained": (2000, 1000, 800)}
# the on-policy scripts run ~1000 steps/s: a longer run keeps the kill (up to 1 s after the checkpoint) before its end
ON_POLICY_STEPS = 3000


def phase_of(script, phase="learning") -> tuple:
    """(total steps, first step of learning, checkpoint frequency) of a kill-and-resume run of `script`."""
    total, learning_starts, checkpoint_frequency = PHASES[phase]
    return (ON_POLICY_STEPS if script in ON_POLICY else total), learning_starts, checkpoint_frequency


def short(script, phase="learning"):
    total, learning_starts, _ = phase_of(script, phase)
    return cli_flags(
        script, total_timesteps=total, learning_starts=learning_starts, batch_size=64, eval_frequency=500, eval_episodes=1
    )


def start(script, cwd, *flags, log=None, fresh=False):
    """The script in a process of its own, its output unbuffered into a log (a killed process loses no line); forked
    from the tests' fork server unless `fresh` (tests/forkserver.py)."""
    log = open(os.path.join(cwd, log or f"{flags[flags.index('--run-name') + 1]}.log"), "w")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return forkserver.Popen(
        script_command(script, *flags), cwd=cwd, stdout=log, stderr=subprocess.STDOUT, env=env, fresh=fresh
    )


def identity(path) -> tuple:
    """Which file is at `path` now: a checkpoint is replaced whole (a new file renamed over the old)."""
    stat = os.stat(path)
    return stat.st_ino, stat.st_mtime_ns


def kill_after_a_checkpoint(process, checkpoint, log, after=None, within=1.0) -> dict:
    """SIGKILL `process` at an arbitrary moment (mid-step, mid-evaluation or mid-write) up to `within` seconds after
    it writes a checkpoint (a file other than the one `after` identifies); the checkpoint the kill leaves."""
    deadline = time.time() + 240
    while (not checkpoint.exists() or identity(checkpoint) == after) and process.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert checkpoint.exists() and identity(checkpoint) != after, log.read_text()
    time.sleep(random.uniform(0.0, within))
    process.send_signal(signal.SIGKILL)
    # not vacuous: the signal ended the run, before its last step (a finished run would resume as a no-op)
    assert process.wait() == -signal.SIGKILL, "the run ended before the kill: the comparison would test nothing"
    return torch.load(checkpoint, weights_only=True)


def final_actor(run_dir, script):
    return torch.load(os.path.join(run_dir, f"{script}_continuous_action.cleanrl_model"), weights_only=True)["actor"]


# EBD is resumed on a DMC task, and TD3, the cheapest off-policy script, on one too (a DMC episode is rebuilt by
# rl_utils' env layer, the same for every script: one script of each kind checks it); the other on-policy scripts on
# Hopper-v4; every off-policy script twice in one run on Hopper, whose random episodes are short: in its random
# phase and once its optimizers have stepped
KILL_CASES = [
    ("td3", "dm_control/cartpole-swingup-v0", "learning"),
    ("ebd", "dm_control/cartpole-swingup-v0", "learning"),
]
KILL_CASES += [(script, "Hopper-v4", "random+trained") for script in OFF_POLICY]
KILL_CASES += [(script, "Hopper-v4", "learning") for script in ON_POLICY if script not in {s for s, _, _ in KILL_CASES}]
# the recorded updates of --cudagraphs resume exactly too (the graphs are recorded anew after a resume)
GRAPH_KILL_CASES = [
    pytest.param(s, "Hopper-v4", "learning", "--cudagraphs", marks=needs_cuda, id=f"{s}-cudagraphs") for s in OFF_POLICY
]


@pytest.mark.slow
@pytest.mark.parametrize(
    "script, env_id, phase, extra",
    [pytest.param(s, e, p, None, id=f"{s}-{e}-{p}") for s, e, p in KILL_CASES] + GRAPH_KILL_CASES,
)
def test_killed_and_resumed_run_ends_identical_to_an_uninterrupted_one(script, env_id, phase, extra, tmp_path):
    total, learning_starts, checkpoint_frequency = phase_of(script, phase)
    flags = ["--env-id", env_id, *short(script, phase), "--save-model", *([extra] if extra else [])]
    # the uninterrupted run in a new interpreter, the killed and resumed ones forked: the same numbers from both
    full = start(script, tmp_path, *flags, "--run-name", "full", fresh=True)
    killed = start(script, tmp_path, *flags, "--run-name", "killed", "--checkpoint-frequency", str(checkpoint_frequency))
    checkpoint = tmp_path / "runs" / "killed" / "checkpoint.pt"
    if phase == "random+trained":
        # the kills fall before the next checkpoint, and the second before the run's end: 400 training steps after its
        # checkpoint, which TD3 on a GPU may run in half a second (eager, 661-959 steps/s at batch 256 on an H200),
        # so the second within 0.25 s
        state = kill_after_a_checkpoint(killed, checkpoint, tmp_path / "killed.log", within=0.5)
        # the random phase goes on after the resume (the next checkpoint would fall after learning starts)
        first_kill = state["global_step"]
        assert checkpoint_frequency <= first_kill < learning_starts
        written = identity(checkpoint)
        killed = start(script, tmp_path, "--resume", "runs/killed", "--save-model", log="resumed.log")
        state = kill_after_a_checkpoint(killed, checkpoint, tmp_path / "resumed.log", after=written, within=0.25)
        assert f"resumed at step {first_kill}" in (tmp_path / "resumed.log").read_text()
        assert learning_starts < state["global_step"] < total
        for name, optimizer in state["optimizers"].items():  # every one has stepped (the actor's every 2nd step) often
            steps = [param_state["step"].item() for param_state in optimizer["state"].values()]
            assert steps and min(steps) >= 200, (name, steps)
    else:
        state = kill_after_a_checkpoint(killed, checkpoint, tmp_path / "killed.log")
    killed_at = state["global_step"]
    assert killed_at < total
    resumed = forkserver.run(
        script_command(script, "--resume", "runs/killed", "--save-model"),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert f"resumed at step {killed_at}" in resumed.stdout
    assert full.wait(timeout=300) == 0

    full_log, resumed_log = scalars(str(tmp_path / "runs" / "full")), scalars(str(tmp_path / "runs" / "killed"))
    assert resumed_log["eval/episodic_return"] == full_log["eval/episodic_return"]
    assert [step for step, _ in resumed_log["eval/episodic_return"]] == list(range(0, total + 1, 500))
    loss = "losses/value_loss" if script in ON_POLICY else "losses/qf_loss"
    assert resumed_log[loss] == full_log[loss]  # no step logged twice or lost
    full_actor, resumed_actor = (
        final_actor(tmp_path / "runs" / "full", script),
        final_actor(tmp_path / "runs" / "killed", script),
    )
    for name in full_actor:
        assert torch.equal(full_actor[name], resumed_actor[name]), name


@pytest.mark.parametrize("env_id", ["Hopper-v4", "dm_control/cartpole-swingup-v0"])
def test_a_checkpoint_restores_the_next_draw_of_every_random_generator(env_id, tmp_path):
    """Python's, NumPy's and torch's global generators, the action space's (the random phase's actions) and the
    environment's own (its start states), through a checkpoint file and back. Every script checkpoints and resumes
    through rl_utils.checkpoints (Run.start and Run.end_step), so this holds for each; the kill-and-resume runs check
    each script's use of it."""
    env = make_env(env_id, seed=3)

    def draws():
        start_state, _ = env.reset()  # no seed: the env's generator decides
        return [
            random.random(),
            np.random.rand(),
            torch.rand(2).tolist(),
            env.action_space.sample().tolist(),
            start_state.tolist(),
        ]

    env.reset(seed=3)
    draws()  # every generator moved on from its seed
    args = load("td3").Args(env_id=env_id)
    checkpoints.write_checkpoint(
        str(tmp_path / "c.pt"), checkpoints.snapshot("td3_continuous_action.py", args, [env], 0, {}, {}, {})
    )
    expected, after = draws(), draws()
    assert expected != after  # each call draws anew
    checkpoints.restore(torch.load(tmp_path / "c.pt", weights_only=True), [env], {}, {}, {})
    assert draws() == expected


@pytest.mark.parametrize("num_seeds", [1, 2])
def test_a_checkpoint_restores_every_optimizers_state_as_saved(num_seeds, tmp_path):
    """Adam's step counts and moments and its hyperparameters (a 0-d parameter's too), through each seed's checkpoint
    file and back into fresh optimizers, equal the saved ones, and the next step then moves the weights exactly as the uninterrupted one does
    (with two seeds, each seed's cut of the stacked state goes to its own file and comes back stacked)."""
    from rl_utils import stack_seeds
    from rl_utils.seeds import join_seeds, split_seeds

    env = make_env("Pendulum-v1", seed=3)
    env.reset(seed=3)
    seeds = list(range(1, num_seeds + 1))
    args = load("td3").Args(env_id="Pendulum-v1", num_seeds=num_seeds)

    def network():  # with a 0-d parameter, whose moments are 0-d in a seed's cut, as the step count is
        net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 1))
        net.scale = torch.nn.Parameter(torch.tensor(0.5))
        return [net]

    def built():
        (net,) = stack_seeds(network, seeds, "cpu")
        return {"net": net}, {"opt": torch.optim.Adam(net.parameters(), lr=1e-2, betas=(0.8, 0.95))}

    def step(nets, opts):  # a loss of the parameters alone: it holds for stacked seeds as for one
        loss = sum((p**3 - p).sum() for p in nets["net"].parameters())
        opts["opt"].zero_grad()
        loss.backward()
        opts["opt"].step()

    nets, opts = built()
    for _ in range(3):
        step(nets, opts)
    run_dirs = [str(tmp_path / f"seed{k}") for k in seeds]
    state = checkpoints.snapshot("td3_continuous_action.py", args, [env], 3, nets, opts, {})
    for run_dir, seed_state in zip(run_dirs, split_seeds(state, {}, [[] for _ in seeds], run_dirs)):
        os.makedirs(run_dir)
        checkpoints.write_checkpoint(os.path.join(run_dir, "checkpoint.pt"), seed_state)
    loaded = [torch.load(os.path.join(d, "checkpoint.pt"), weights_only=True) for d in run_dirs]
    fresh_nets, fresh_opts = built()
    checkpoints.restore(join_seeds(loaded, {}), [env], fresh_nets, fresh_opts, {})
    saved, restored = opts["opt"].state_dict(), fresh_opts["opt"].state_dict()
    assert restored["param_groups"] == saved["param_groups"]
    assert saved["state"].keys() == restored["state"].keys() and len(saved["state"]) == 5
    for i, param_state in saved["state"].items():
        assert param_state["step"].item() == 3.0
        for key, value in param_state.items():
            assert torch.equal(restored["state"][i][key], value), (i, key)
    step(nets, opts), step(fresh_nets, fresh_opts)
    for a, b in zip(nets["net"].parameters(), fresh_nets["net"].parameters()):
        assert torch.equal(a, b)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """One short checkpointed run per script, made once per test process and shared by the tests that only
    read it (each script's tests share an xdist group, so one process makes it)."""
    cache = {}

    def get(script):
        if script not in cache:
            cwd = tmp_path_factory.mktemp(script)
            flags = [
                "--env-id",
                "Pendulum-v1",
                *cli_flags(
                    script, total_timesteps=400, learning_starts=200, batch_size=32, eval_frequency=400, eval_episodes=1
                ),
            ]
            result = forkserver.run(
                script_command(script, *flags, "--run-name", "done", "--checkpoint-frequency", "200"),
                cwd=cwd,
                capture_output=True,
                text=True,
                timeout=300,
            )
            assert result.returncode == 0, result.stderr
            cache[script] = cwd
        return cache[script]

    return get


# one xdist group per script: its finished run is made once (see finished_run)
SHARED_RUN = [pytest.param(s, marks=pytest.mark.xdist_group(f"finished-{s}"), id=s) for s in SCRIPTS]


@pytest.mark.parametrize("script", SHARED_RUN)
def test_resuming_a_finished_run_does_nothing(script, finished_run, monkeypatch, capsys):
    cwd = finished_run(script)
    checkpoint = cwd / "runs" / "done" / "checkpoint.pt"
    before = checkpoint.read_bytes()
    monkeypatch.chdir(cwd)
    module = load(script)
    result = module.main(parse(module, ["--resume", "runs/done"]))
    assert "had already finished its 400 steps" in capsys.readouterr().out
    assert [step for step, _ in result["eval_returns"]] == [0, 400]
    assert checkpoint.read_bytes() == before


@pytest.mark.parametrize("script", SHARED_RUN)
def test_checkpoint_loads_without_running_code(script, finished_run):
    path = finished_run(script) / "runs" / "done" / "checkpoint.pt"
    checkpoint = torch.load(path, weights_only=True)
    assert checkpoint["global_step"] == 400 and checkpoint["script"] == f"{script}_continuous_action.py"
    assert checkpoint["format"] == checkpoints.FORMAT
    if script in OFF_POLICY:
        assert checkpoint["buffer"]["rows"].shape[:2] == (1, 400)  # one seed's 400 rows
    else:
        assert checkpoint["rollout"]["obs"].shape[0] == 256


def one_line_error(result):
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    return lines[0]


@pytest.mark.parametrize("script", SHARED_RUN)
def test_truncated_foreign_and_old_checkpoints_are_refused(script, finished_run, tmp_path, monkeypatch):
    path = finished_run(script) / "runs" / "done" / "checkpoint.pt"
    good = path.read_bytes()
    cases = {
        "truncated": (good[: len(good) // 2], "is not a readable checkpoint"),
        "text": (b"hello", "is not a readable checkpoint"),
    }
    for name, (content, message) in cases.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "checkpoint.pt").write_bytes(content)
    (tmp_path / "foreign").mkdir()
    torch.save({"script": "someone_else.py"}, tmp_path / "foreign" / "checkpoint.pt")
    cases["foreign"] = (None, "was not written by")
    # the layout before this one (format 2: the critics as one hand-batched module) does not load into it
    (tmp_path / "old").mkdir()
    torch.save({**torch.load(path, weights_only=True), "format": 2}, tmp_path / "old" / "checkpoint.pt")
    cases["old"] = (None, "was written by an older")

    class Exploit:  # a pickle that would run code when loaded without weights_only
        def __reduce__(self):
            return (os.system, ("touch pwned",))

    (tmp_path / "exploit").mkdir()
    torch.save({"script": f"{script}_continuous_action.py", "x": Exploit()}, tmp_path / "exploit" / "checkpoint.pt")
    cases["exploit"] = (None, "is not a readable checkpoint")
    for name, (_, message) in cases.items():
        assert message in refusal(script, ["--resume", name], tmp_path, monkeypatch), name
    assert not (tmp_path / "pwned").exists()


@pytest.mark.parametrize("script", SHARED_RUN)
def test_resume_with_other_hyperparameters_is_refused(script, finished_run, monkeypatch):
    assert "--gamma 0.5 (run: 0.99)" in refusal(
        script, ["--resume", "runs/done", "--gamma", "0.5"], finished_run(script), monkeypatch
    )


@pytest.mark.parametrize("script", OFF_POLICY)
def test_bf16_step_sees_weights_an_optimizer_changed_within_the_step(script):
    # SAC and REDQ use the actor again after its optimizer step, inside one training step
    layer, x = torch.nn.Linear(8, 8), torch.randn(4, 8)
    with load(script).bf16_autocast(torch.device("cpu"), True):
        before = layer(x)
        with torch.no_grad():
            layer.weight.add_(1.0)
        after = layer(x)
    assert before.dtype == torch.bfloat16
    assert torch.allclose(after.float(), x @ layer.weight.T + layer.bias, rtol=0.02, atol=0.05)
    assert not torch.allclose(before.float(), after.float(), atol=0.5)


@pytest.mark.parametrize("script", OFF_POLICY)
def test_bf16_off_keeps_float32(script):
    layer, x = torch.nn.Linear(8, 8), torch.randn(4, 8)
    with load(script).bf16_autocast(torch.device("cpu"), False):
        assert layer(x).dtype == torch.float32


@pytest.mark.parametrize("script", SCRIPTS)
def test_non_finite_loss_stops_with_the_step_and_the_last_good_state(script, tmp_path):
    flags = [
        "--env-id",
        "Pendulum-v1",
        *cli_flags(script, total_timesteps=600, learning_starts=100, batch_size=32, eval_frequency=600, eval_episodes=1),
    ]
    result = forkserver.run(
        script_command(script, *flags, critic_lr_flag(script), "1e30", "--run-name", "nan"),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    line = one_line_error(result)
    assert "became non-finite at step" in line and "last_good_state.pt" in line
    state = torch.load(tmp_path / "runs" / "nan" / "last_good_state.pt", weights_only=True)
    assert f"at step {state['global_step']} " in line
    assert all(torch.isfinite(t).all() for net in state["nets"].values() for t in net.values())


# (flags, part of the message); the off-policy scripts share OFF_POLICY_BAD_INPUTS, each adds its own (a script not
# in EXTRA_BAD_INPUTS is held to its base's entry). The messages come from rl_utils.cli (its RULES, by flag name,
# and the checks of pairs of flags), rl_utils.envs (the env ids), rl_utils.checkpoints (--resume) and a script's own
# check_args (REDQ's); each row runs through the script's own command line, so a script that drops or renames a
# flag, or stops passing its check_args, fails its rows.
BAD_INPUTS = [
    (["--total-timesteps", "0"], "--total-timesteps must be > 0"),
    (["--gamma", "1.5"], "--gamma must be in [0, 1]"),
    (["--eval-frequency", "0"], "--eval-frequency must be > 0"),
    (["--eval-episodes", "0"], "--eval-episodes must be > 0"),
    (["--checkpoint-frequency", "-1"], "--checkpoint-frequency must be >= 0"),
    (["--env-id", "Hopper-v9"], "unknown --env-id 'Hopper-v9'; did you mean"),
    (["--env-id", "CartPole-v1"], "Discrete action space"),
    (["--env-id", "Hopper-v3"], "could not create --env-id 'Hopper-v3'"),
    (["--resume", "runs/missing"], "--resume runs/missing: no such run folder"),
]
OFF_POLICY_BAD_INPUTS = [
    (["--buffer-size", "0"], "--buffer-size must be > 0"),
    (["--batch-size", "0"], "--batch-size must be > 0"),
    (["--learning-starts", "10"], "--learning-starts (10) must be >= --batch-size"),
    (["--tau", "0"], "--tau must be in (0, 1]"),
    (["--tau", "1.5"], "--tau must be in (0, 1]"),
    (["--cudagraphs", "--no-cuda"], "--cudagraphs needs a CUDA GPU"),
    (["--num-seeds", "0"], "--num-seeds must be >= 1"),
    (["--num-seeds", "2", "--run-name", "one"], "--run-name one names one folder for 2 seeds"),
]
PPO_BAD_INPUTS = [
    (["--num-steps", "0"], "--num-steps must be > 0"),
    (["--total-timesteps", "1000"], "--total-timesteps (1000) must be >= --num-steps (2048)"),
    (["--num-minibatches", "0"], "--num-minibatches must be in [1, --num-steps (2048)]"),
    (["--update-epochs", "0"], "--update-epochs must be > 0"),
    (["--gae-lambda", "1.5"], "--gae-lambda must be in [0, 1]"),
    (["--clip-coef", "0"], "--clip-coef must be > 0"),
    (["--max-grad-norm", "0"], "--max-grad-norm must be > 0"),
    (["--target-kl", "0"], "--target-kl must be > 0"),
    (["--learning-rate", "0"], "--learning-rate must be > 0"),
]
# the settings RND and EBD add to PPO's
INTRINSIC_BAD_INPUTS = [
    (["--int-coef", "-1"], "--int-coef must be >= 0"),
    (["--ext-coef", "-0.5"], "--ext-coef must be >= 0"),
    (["--int-gamma", "1.5"], "--int-gamma must be in [0, 1]"),
    (["--num-iterations-obs-norm-init", "-1"], "--num-iterations-obs-norm-init must be >= 0"),
]
EXTRA_BAD_INPUTS = {
    "td3": [
        (["--policy-frequency", "0"], "--policy-frequency must be > 0"),
        (["--learning-rate", "0"], "--learning-rate must be > 0"),
        (["--policy-noise", "-0.1"], "--policy-noise must be >= 0"),
        (["--noise-clip", "-1"], "--noise-clip must be >= 0"),
        (["--exploration-noise", "-1"], "--exploration-noise must be >= 0"),
    ],
    "sac": [
        (["--policy-lr", "0"], "--policy-lr must be > 0"),
        (["--q-lr", "-1"], "--q-lr must be > 0"),
        (["--alpha", "-0.1"], "--alpha must be >= 0"),
        (["--target-network-frequency", "0"], "--target-network-frequency must be > 0"),
        (["--policy-frequency", "0"], "--policy-frequency must be > 0"),
    ],
    "redq": [
        (["--num-q", "0"], "--num-q must be >= 1"),
        (["--num-min", "11"], "--num-min must be in [1, --num-q (10)]"),
        (["--utd-ratio", "0"], "--utd-ratio must be >= 1"),
        (["--policy-lr", "-1"], "--policy-lr must be > 0"),
    ],
    "ppo": PPO_BAD_INPUTS,
    "rnd": PPO_BAD_INPUTS
    + INTRINSIC_BAD_INPUTS
    + [
        (["--update-proportion", "0"], "--update-proportion must be in (0, 1]"),
        (["--update-proportion", "1.5"], "--update-proportion must be in (0, 1]"),
    ],
    "ebd": PPO_BAD_INPUTS
    + INTRINSIC_BAD_INPUTS
    + [
        (["--num-models", "1"], "--num-models must be >= 2"),
    ],
    "oparl": [
        (["--policy-frequency", "0"], "--policy-frequency must be > 0"),
        (["--q-num", "1"], "--q-num must be >= 2"),
        (["--optimistic-ratio", "1.5"], "--optimistic-ratio must be in [0, 1]"),
        (["--optimistic-ratio", "-0.1"], "--optimistic-ratio must be in [0, 1]"),
        (["--num-candidates", "0"], "--num-candidates must be >= 1"),
        (["--reset-frequency", "-1"], "--reset-frequency must be >= 0"),
        (["--learning-rate", "-1"], "--learning-rate must be > 0"),
    ],
}
CASES = [
    (s, flags, message)
    for s in SCRIPTS
    for flags, message in BAD_INPUTS
    + (OFF_POLICY_BAD_INPUTS if s in OFF_POLICY else [])
    + (declared(EXTRA_BAD_INPUTS, s) or [])
]


@pytest.mark.parametrize("script, flags, message", CASES, ids=[f"{s}: {' '.join(f)}" for s, f, _ in CASES])
def test_bad_input_is_refused_in_one_line(script, flags, message, tmp_path, monkeypatch):
    assert message in refusal(script, flags, tmp_path, monkeypatch)
    assert not os.path.exists("runs")  # refused before anything is written


@pytest.mark.parametrize("script", OFF_POLICY)
def test_a_run_that_never_reaches_learning_starts_says_so(script, capsys):
    """Allowed (a quick check of the wiring), but not silent: a user who shortens --total-timesteps and keeps the
    default --learning-starts would otherwise get an untrained policy and no word about it."""
    module = load(script)
    parse(module, ["--learning-starts", "500", "--total-timesteps", "500"])  # steps 0-499: all random
    note = "note: --learning-starts (500) >= --total-timesteps (500): every step acts at random and the networks are never trained"
    assert capsys.readouterr().err == note + "\n"
    parse(module, ["--learning-starts", "500", "--total-timesteps", "501"])  # step 500 trains
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("script", SCRIPTS)
def test_resume_without_checkpoint_is_refused(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs" / "empty").mkdir(parents=True)
    module = load(script)
    with pytest.raises(SystemExit, match="holds no checkpoint.pt"):
        parse(module, ["--resume", "runs/empty"])
