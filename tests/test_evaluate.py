"""tools/evaluate.py on models the scripts save (plain single-seed state_dicts, a seed of a --num-seeds process's
included): it reproduces the script's own last evaluation, and bad input gets one line."""

import dataclasses
import os
import subprocess
import sys

import pytest

from conftest import REPO, SCRIPTS, load, small_args
from test_end_to_end import VIDEO_ENV, rendering_works

sys.path.insert(0, os.path.join(REPO, "tools"))
import evaluate  # noqa: E402

SEED = 3


def train_and_save(script: str, tmp_path, monkeypatch, env_id="Pendulum-v1") -> tuple:
    """A few hundred steps with --save-model; the model's path and the script's own last evaluation."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    result = module.main(small_args(module, env_id=env_id, seed=SEED, eval_episodes=2, save_model=True))
    model = os.path.join(result["run_dir"], f"{script}_continuous_action.cleanrl_model")
    assert os.path.isfile(model)
    return model, result["eval_returns"][-1][1]


@pytest.mark.parametrize("script", SCRIPTS)
def test_evaluating_a_saved_model_reproduces_the_scripts_last_evaluation(script, tmp_path, monkeypatch):
    model, last_eval = train_and_save(script, tmp_path, monkeypatch)
    # the training's evaluations: seed + 100, 2 episodes; the algorithm and task come from the path
    returns = evaluate.main([model, "--seed", str(SEED + 100), "--episodes", "2"])
    assert len(returns) == 2
    assert returns.mean() == pytest.approx(last_eval, rel=1e-6)
    # another seed sees other start states
    assert evaluate.main([model, "--seed", str(SEED + 101), "--episodes", "2"]).mean() != pytest.approx(last_eval, rel=1e-6)


def several_seeds_allowed(script: str) -> bool:
    """Whether a script trains --num-seeds 2 in one process (REDQ refuses)."""
    module = load(script)
    if "num_seeds" not in {f.name for f in dataclasses.fields(module.Args)}:
        return False
    return all(ok for ok, _ in getattr(module, "check_args", lambda args: [])(module.Args(num_seeds=2)))


@pytest.mark.parametrize("script", [s for s in SCRIPTS if several_seeds_allowed(s)])
def test_a_seed_of_a_several_seed_process_saves_a_model_that_evaluates_as_that_seed(script, tmp_path, monkeypatch):
    """Each seed of a 2-seed process saves its model in its own run folder, in a single-seed run's form: the tool loads
    it into the script's single-seed network and repeats that seed's last evaluation (on its seed + 100)."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    result = module.main(small_args(module, env_id="Pendulum-v1", seed=SEED, num_seeds=2, eval_episodes=2, save_model=True))
    models = [os.path.join(run_dir, f"{script}_continuous_action.cleanrl_model") for run_dir in result["run_dirs"]]
    last_evals = [returns[-1][1] for returns in result["seeds_eval_returns"]]
    assert last_evals[0] != pytest.approx(last_evals[1], rel=1e-3)  # the two seeds' policies differ
    for k in range(2):  # each seed's model evaluates as its seed (vmapped in training: to rounding)
        returns = evaluate.main([models[k], "--seed", str(SEED + k + 100), "--episodes", "2"])
        assert returns.mean() == pytest.approx(last_evals[k], rel=1e-6)


def test_names_are_inferred_from_the_run_folder():
    path = os.path.join(
        "runs", "dm_control-cartpole-swingup-v0__sac_continuous_action__1__17", "sac_continuous_action.cleanrl_model"
    )
    assert evaluate.infer_algo(path) == "sac"
    assert evaluate.infer_env_id(path) == "dm_control/cartpole-swingup-v0"
    assert evaluate.infer_algo("model.pt") is None
    assert evaluate.infer_env_id(os.path.join("models", "model.pt")) is None


def run_cli(*flags, cwd, env=None):
    return subprocess.run(
        [sys.executable, os.path.join(REPO, "tools", "evaluate.py"), *flags], capture_output=True, text=True, cwd=cwd, env=env
    )


def test_capture_video_records_the_first_episode(tmp_path, monkeypatch):
    if not rendering_works():
        pytest.skip(f"no headless OpenGL here: MUJOCO_GL=egl could not render {VIDEO_ENV} (install libegl1 / libosmesa6)")
    model, _ = train_and_save("td3", tmp_path, monkeypatch, env_id=VIDEO_ENV)
    env = {**os.environ, "MUJOCO_GL": "egl"}
    done = run_cli(model, "--episodes", "2", "--capture-video", "--video-folder", "v", cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stderr
    assert [name for name in os.listdir(tmp_path / "v") if name.endswith(".mp4")] == ["rl-video-episode-0.mp4"]


def test_bad_input_gets_one_line(tmp_path, monkeypatch):
    model, _ = train_and_save("td3", tmp_path, monkeypatch)
    renamed = tmp_path / "model.pt"
    os.rename(model, renamed)
    cases = [
        (["missing.cleanrl_model"], "no such model file"),
        ([str(renamed), "--env-id", "Pendulum-v1"], "cannot tell the algorithm"),
        ([str(renamed), "--algo", "td3"], "cannot tell the task"),
        ([str(renamed), "--algo", "td3", "--env-id", "Pendulum-v1", "--episodes", "0"], "--episodes must be >= 1"),
        ([str(renamed), "--algo", "td3", "--env-id", "MountainCarContinuous-v0"], "does not fit td3 on this task"),
        ([str(renamed), "--algo", "ppo", "--env-id", "Pendulum-v1"], "does not fit ppo on this task"),
        ([str(renamed), "--algo", "td3", "--env-id", "Pendulum-v9"], "unknown --env-id"),
    ]
    (tmp_path / "junk.cleanrl_model").write_text("not a model")
    cases.append(([str(tmp_path / "junk.cleanrl_model"), "--algo", "td3", "--env-id", "Pendulum-v1"], "could not load"))
    for flags, message in cases:
        done = run_cli(*flags, cwd=tmp_path)
        assert done.returncode != 0, flags
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], (flags, done.stderr)
