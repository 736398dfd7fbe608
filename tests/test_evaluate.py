"""tools/evaluate.py on models the scripts save (plain single-seed state_dicts; a seed of a --num-seeds process's:
tests/test_many_seeds.py): it reproduces the script's own last evaluation, and bad input gets one line."""

import os
import re
import sys

import pytest
import torch

from conftest import REPO, SCRIPTS, load, small_args
import forkserver
from rl_utils.envs import PROBE_SIZE
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
    returns = evaluate.main([model, "--seed", str(SEED + 100), "--episodes", "2"])  # its probe passed (below)
    assert len(returns) == 2
    probe = torch.load(model, weights_only=True)["probe"]  # how the evaluated policy acts, for evaluate.py to check
    assert probe["observations"].shape == (PROBE_SIZE, 3) and probe["actions"].shape == (PROBE_SIZE, 1)
    assert returns.mean() == pytest.approx(last_eval, rel=1e-6)
    # another seed sees other start states
    assert evaluate.main([model, "--seed", str(SEED + 101), "--episodes", "2"]).mean() != pytest.approx(last_eval, rel=1e-6)


def test_names_are_inferred_from_the_run_folder():
    path = os.path.join(
        "runs", "dm_control-cartpole-swingup-v0__sac_continuous_action__1__17", "sac_continuous_action.cleanrl_model"
    )
    assert evaluate.infer_algo(path) == "sac"
    assert evaluate.infer_env_id(path) == "dm_control/cartpole-swingup-v0"
    assert evaluate.infer_algo("model.pt") is None
    assert evaluate.infer_env_id(os.path.join("models", "model.pt")) is None


def run_cli(*flags, cwd, env=None):
    return forkserver.run(
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
    for flags, message in cases:  # in this process: the one-line SystemExit the command line prints
        with pytest.raises(SystemExit) as exit_info:
            evaluate.main(flags)
        assert str(exit_info.value).startswith("error: ") and "\n" not in str(exit_info.value), flags
        assert message in str(exit_info.value), (flags, str(exit_info.value))
    done = run_cli(*cases[-1][0], cwd=tmp_path)  # and once on the command line: one line on stderr, exit status 1
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1 and lines[0].startswith("error: ") and cases[-1][1] in lines[0]
    td3 = load("td3")

    class ForkedActor(td3.Actor):  # a fork's actor that takes one more argument
        def __init__(self, obs_dim, action_space, activation):
            super().__init__(obs_dim, action_space)

    monkeypatch.setattr(td3, "Actor", ForkedActor)
    with pytest.raises(SystemExit, match=re.escape("td3's networks are not built as tools/evaluate.py builds them")):
        evaluate.main([str(renamed), "--algo", "td3", "--env-id", "Pendulum-v1"])


# a fork's flag that changes how its actor acts, not its weights' shapes: (activation, observations clipped at), the
# values evaluate.py builds the fork's actor with; the model was trained with ReLU and unclipped observations
FORKS = {"as trained": (torch.relu, None), "--actor-activation tanh": (torch.tanh, None), "--obs-clip 2.5": (torch.relu, 2.5)}


@pytest.mark.parametrize("fork", FORKS)
def test_an_actor_that_acts_otherwise_than_the_trained_one_is_refused(fork, tmp_path, monkeypatch):
    """Built with other values than the trained actor's, the fork's actor stops evaluate.py in one line rather than
    give another policy's return (a clip at 2.5 shows only on observations past it: Pendulum's reach 8); built as
    trained, it repeats the last evaluation."""
    td3 = load("td3")
    model, last_eval = train_and_save("td3", tmp_path, monkeypatch)
    activation, clip = FORKS[fork]

    class ForkedActor(td3.Actor):  # the values keywords with defaults, given by the fork's flags in its main
        def __init__(self, obs_dim, action_space, activation=activation, clip=clip):
            super().__init__(obs_dim, action_space)
            self.activation, self.clip = activation, clip

        def forward(self, x):
            x = x if self.clip is None else x.clamp(-self.clip, self.clip)
            x = self.activation(self.fc2(self.activation(self.fc1(x))))
            return torch.tanh(self.fc_mu(x)) * self.action_scale + self.action_bias

    monkeypatch.setattr(td3, "Actor", ForkedActor)
    flags = [model, "--seed", str(SEED + 100), "--episodes", "2"]
    if fork == "as trained":
        assert evaluate.main(flags).mean() == pytest.approx(last_eval, rel=1e-6)
        return
    with pytest.raises(SystemExit) as exit_info:
        evaluate.main(flags)
    message = str(exit_info.value)
    assert message.startswith("error: the policy built from") and "\n" not in message
    assert "does not act as the run's evaluated policy did" in message and "load_policy" in message


def test_the_rebuilt_actor_runs_in_eval_mode(tmp_path, monkeypatch):
    """A fork's actor with dropout, which its evaluations run in eval mode (as forking.md asks), is evaluated in eval
    mode too: the run's last evaluation again, not a policy dropping units at random."""
    td3 = load("td3")
    model, last_eval = train_and_save("td3", tmp_path, monkeypatch)

    class DropoutActor(td3.Actor):  # no parameters of its own: the saved weights load
        def __init__(self, obs_dim, action_space):
            super().__init__(obs_dim, action_space)
            self.dropout = torch.nn.Dropout(0.5)

        def forward(self, x):
            x = self.dropout(torch.relu(self.fc2(self.dropout(torch.relu(self.fc1(x))))))
            return torch.tanh(self.fc_mu(x)) * self.action_scale + self.action_bias

    monkeypatch.setattr(td3, "Actor", DropoutActor)
    assert evaluate.main([model, "--seed", str(SEED + 100), "--episodes", "2"]).mean() == pytest.approx(last_eval, rel=1e-6)


def test_a_nan_in_the_probe_fails_the_check_unless_both_policies_give_it(tmp_path, monkeypatch):
    model, last_eval = train_and_save("td3", tmp_path, monkeypatch)
    saved = torch.load(model, weights_only=True)
    actions = saved["probe"]["actions"]
    saved["probe"]["actions"] = torch.cat([torch.full_like(actions[:1], float("nan")), actions[1:] + 1.0])  # all off
    torch.save(saved, model)
    with pytest.raises(SystemExit, match="does not act as the run's evaluated policy did"):
        evaluate.main([model, "--seed", str(SEED + 100), "--episodes", "1"])
    td3 = load("td3")  # an actor that gives NaN on the first probe observation, as the saved actions say it did
    saved["probe"]["actions"][1:] = actions[1:]
    torch.save(saved, model)
    first = saved["probe"]["observations"][0]

    class NanOnFirst(td3.Actor):
        def forward(self, x):
            return super().forward(x).masked_fill((x == first).all(-1, keepdim=True), float("nan"))

    monkeypatch.setattr(td3, "Actor", NanOnFirst)
    assert evaluate.main([model, "--seed", str(SEED + 100), "--episodes", "2"]).mean() == pytest.approx(last_eval, rel=1e-6)


@pytest.mark.parametrize("why", ["the policy fails on it", "no policy given"])
def test_a_model_without_its_probe_is_saved_with_a_warning_and_evaluated_unchecked(why, tmp_path, monkeypatch, capsys):
    """The probe is a check, not the point of --save-model: where the policy cannot act on it, or a fork's main gives
    run.finish no policy, the model is saved without it, with a warning, and evaluate.py evaluates it unchecked, as a
    model saved before the probe."""
    import rl_utils.run

    def failing_probe(*_):
        raise ValueError("a fork's policy that wants a dict\nsecond line")

    finish = rl_utils.run.Run.finish
    if why == "no policy given":
        monkeypatch.setattr(
            rl_utils.run.Run, "finish", lambda run, save, eval_envs=None, policy=None: finish(run, save, eval_envs)
        )
        expected = "(run.finish was given no policy)"
    else:
        monkeypatch.setattr(rl_utils.run, "policy_probe", failing_probe)
        expected = "(ValueError: a fork's policy that wants a dict)"
    model, last_eval = train_and_save("td3", tmp_path, monkeypatch)
    assert (
        f"warning: --save-model leaves out the policy's probe {expected}; evaluate.py cannot check it"
        in capsys.readouterr().err
    )
    assert "probe" not in torch.load(model, weights_only=True)
    assert evaluate.main([model, "--seed", str(SEED + 100), "--episodes", "2"]).mean() == pytest.approx(last_eval, rel=1e-6)
