"""Whole runs of every script: what they write, what they print, how they refuse bad input."""

import functools
import os
import re
import subprocess
import sys

import pytest
import torch

from conftest import ON_POLICY, REPO, SCRIPTS, cli_flags, declared, load, scalars, small_args, source
import forkserver
from rl_utils import make_env

pytestmark = pytest.mark.slow  # every test here trains or sweeps

COMMON_TAGS = {"eval/episodic_return", "charts/episodic_return", "charts/episodic_length", "charts/SPS"}
CRITIC_TAGS = {"losses/qf_loss", "losses/qf_values"}
PPO_TAGS = {
    "losses/policy_loss",
    "losses/value_loss",
    "losses/entropy",
    "losses/approx_kl",
    "losses/old_approx_kl",
    "losses/clipfrac",
    "losses/explained_variance",
    "charts/learning_rate",
}
# what each script logs beyond the common tags and the tags its source names in full ("losses/qf_loss"); a script
# without an entry is held to its base's
EXTRA_TAGS = {
    "td3": CRITIC_TAGS | {"losses/actor_loss"},
    "sac": CRITIC_TAGS | {"losses/actor_loss", "losses/alpha", "losses/alpha_loss"},
    "redq": CRITIC_TAGS | {"losses/actor_loss", "losses/alpha", "losses/alpha_loss"},
    "ppo": PPO_TAGS,
    "rnd": PPO_TAGS | {"charts/intrinsic_reward", "losses/rnd_loss"},
    "ebd": PPO_TAGS | {"charts/intrinsic_reward", "losses/forward_model_loss"},
    "oparl": CRITIC_TAGS
    | {
        "losses/pessimistic_actor_loss",
        "losses/optimistic_actor_loss",
        "charts/q_ensemble_std",
        "charts/optimistic_share",
        "charts/resets",
    },
}


@pytest.mark.parametrize("script", SCRIPTS)
@pytest.mark.parametrize("env_id", ["Hopper-v4", "dm_control/cartpole-swingup-v0"])
def test_short_run_writes_every_tag(script, env_id, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    module = load(script)
    args = small_args(module, env_id=env_id, total_timesteps=1200, learning_starts=1000, eval_frequency=500, run_name="run")
    module.main(args)
    logged = scalars(os.path.join("runs", "run"))
    named = set(re.findall(r'"((?:losses|charts|eval)/\w+)"', source(script)))
    missing = (COMMON_TAGS | named | (declared(EXTRA_TAGS, script) or set())) - set(logged)
    assert not missing, f"never logged: {sorted(missing)}"
    # evaluations at the start, every --eval-frequency steps, and at the end
    assert [step for step, _ in logged["eval/episodic_return"]] == [0, 500, 1000, 1200]
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(os.path.join("runs", "run"))
    acc.Reload()
    hyperparameters = acc.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()
    assert f"|env_id|{env_id}|" in hyperparameters


@pytest.mark.parametrize("script", SCRIPTS)
def test_save_model_writes_loadable_weights(script, tmp_path, monkeypatch):
    """The model is a plain single-seed state_dict per network: the trained actor's, loadable as it is into a fresh
    network of the script."""
    monkeypatch.chdir(tmp_path)
    module = load(script)
    result = module.main(small_args(module, env_id="Pendulum-v1", save_model=True, run_name="run"))
    path = os.path.join("runs", "run", f"{script}_continuous_action.cleanrl_model")
    saved = torch.load(path, weights_only=True)
    actor = result["agent" if script in ON_POLICY else "actor"]  # what the file saves as "actor"
    for name, tensor in actor.state_dict().items():
        torch.testing.assert_close(saved["actor"][name], tensor)
    assert ("normalizer" if script in ON_POLICY else "qf") in saved
    env = make_env("Pendulum-v1", seed=0)
    fresh = module.Agent(3, 1) if script in ON_POLICY else module.Actor(3, env.action_space)
    fresh.load_state_dict(saved["actor"])  # strict: the same names and shapes, no seeds dimension


def run_script(script, *flags, env=None):
    return forkserver.run(
        [sys.executable, os.path.join(REPO, f"{script}_continuous_action.py"), *flags],
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        timeout=300,
    )


@pytest.mark.parametrize("script", SCRIPTS)
def test_command_line_error_is_one_line_without_traceback(script, tmp_path):
    result = run_script(script, "--env-id", "Hoper-v4")
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: unknown --env-id 'Hoper-v4'; did you mean Hopper-v4")


# software rendering is slow: a Hopper-v4 frame takes ~0.35 s on a 2-core CPU, an InvertedPendulum-v4
# frame ~0.03 s, and an untrained policy topples the pendulum within a few dozen steps
VIDEO_ENV = "InvertedPendulum-v4"


@functools.lru_cache(maxsize=None)
def rendering_works():
    probe = f"import gymnasium as gym; e = gym.make('{VIDEO_ENV}', render_mode='rgb_array'); e.reset(seed=0); assert e.render().mean() > 0"
    try:
        return (
            subprocess.run(
                [sys.executable, "-c", probe], env={**os.environ, "MUJOCO_GL": "egl"}, capture_output=True, timeout=120
            ).returncode
            == 0
        )
    except subprocess.TimeoutExpired:
        return False


@pytest.mark.parametrize("script", SCRIPTS)
def test_capture_video_records_evaluation_episodes(script, tmp_path):
    if not rendering_works():
        pytest.skip(f"no headless OpenGL here: MUJOCO_GL=egl could not render {VIDEO_ENV} (install libegl1 / libosmesa6)")
    flags = [
        "--env-id",
        VIDEO_ENV,
        *cli_flags(script, total_timesteps=300, learning_starts=300, eval_frequency=300, eval_episodes=2),
    ]
    result = forkserver.run(
        [sys.executable, os.path.join(REPO, f"{script}_continuous_action.py"), *flags, "--capture-video", "--run-name", "run"],
        cwd=tmp_path,
        env={**os.environ, "MUJOCO_GL": "egl"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    videos = sorted(os.listdir(tmp_path / "videos" / "run"))
    # two evaluations (steps 0 and 300) of two episodes each; the first episode of each is recorded
    assert [v for v in videos if v.endswith(".mp4")] == ["rl-video-episode-0.mp4", "rl-video-episode-2.mp4"]
