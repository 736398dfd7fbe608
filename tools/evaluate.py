"""Evaluate a policy saved with --save-model: N deterministic episodes, the mean return, optionally a video.

    python tools/evaluate.py runs/Hopper-v4__oparl_continuous_action__1__1700000000/oparl_continuous_action.cleanrl_model
    python tools/evaluate.py MODEL --algo sac --env-id dm_control/cartpole-swingup-v0 --episodes 20 --capture-video

The policy acts exactly as in the training script's own evaluations (the `policy` its `main` hands to
`rl_utils.evaluate`: the noiseless actor for TD3 and OPARL's pessimistic actor, the squashed mean action
(`deterministic_action`) for SAC and REDQ, the clipped mean action on observations normalised with the saved
training statistics for PPO, RND and EBD), on rl_utils' environment layer (`make_env`, `evaluate`). A saved
model is a plain single-seed state_dict per network; a seed of a --num-seeds process saves its own in the same
form, in its own run folder. The algorithm is read from the model's file
name (`{exp_name}.cleanrl_model`, the script's name unless --exp-name changed it) and the task from
its run folder's name (`{env_id}__...`, `dm_control-` standing for `dm_control/`); --algo and --env-id
say them when the names do not. --capture-video records the first episode to --video-folder. The file also
holds the trained policy's actions on fixed observations ("probe"): a policy rebuilt here that acts otherwise (a
fork's actor built with other settings than its defaults) stops with one line rather than give another
policy's return.
"""

import argparse
import glob
import importlib
import os
import sys

import numpy as np
import torch

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)  # the training scripts and rl_utils
from rl_utils import evaluate, make_env, per_seed  # noqa: E402

# every {algo}_continuous_action.py beside this folder, a new one included
ALGOS = sorted(os.path.basename(p).removesuffix("_continuous_action.py") for p in glob.glob(f"{REPO}/*_continuous_action.py"))


# how far an action of the rebuilt policy may be from the trained one's, over the action range: another device's or
# vmap's rounding, not another network
PROBE_TOLERANCE = 1e-4


def fail(message: str):
    sys.exit(f"error: {message}")


def infer_algo(model_path: str) -> str | None:
    name = os.path.basename(model_path)
    for algo in ALGOS:
        if name == f"{algo}_continuous_action.cleanrl_model":
            return algo
    return None


def infer_env_id(model_path: str) -> str | None:
    run_name = os.path.basename(os.path.dirname(os.path.abspath(model_path)))
    if "__" not in run_name:
        return None
    env_id = run_name.split("__")[0]
    return "dm_control/" + env_id[len("dm_control-") :] if env_id.startswith("dm_control-") else env_id


def load_policy(script, algo: str, model_path: str, env):
    """The saved policy as the training script's `main` evaluates it: observations [1, obs_dim] -> actions."""
    try:
        saved = torch.load(model_path, map_location="cpu", weights_only=True)
    except Exception as e:
        fail(f"could not load {model_path!r} as a --save-model file ({type(e).__name__}: {str(e).splitlines()[0]})")
    if not isinstance(saved, dict) or "actor" not in saved:
        fail(f"{model_path!r} holds no 'actor': not a model written by --save-model")
    obs_dim = int(np.prod(env.observation_space.shape))
    low, high = env.action_space.low, env.action_space.high
    try:
        if hasattr(script, "Normalizer"):  # PPO, RND, EBD: an agent and its observation statistics
            agent = script.Agent(obs_dim, int(np.prod(env.action_space.shape)))
            agent.load_state_dict(saved["actor"])
            agent.eval()  # as an evaluation runs a network: a dropout layer, say, off
            normalizer = script.Normalizer(obs_dim, gamma=0.99)  # gamma only matters for rewards, not used here
            normalizer.load_state_dict(saved["normalizer"])

            # the mean action on the training statistics (not updated), clipped
            def policy(obs):
                return agent.actor_mean(torch.as_tensor(normalizer.observation(obs, update=False))).numpy().clip(low, high)
        else:
            actor = script.Actor(obs_dim, env.action_space)
            actor.load_state_dict(saved["actor"])
            actor.eval()  # as an evaluation runs a network: a dropout layer, say, off
            # SAC's and REDQ's squashed mean action, TD3's and OPARL's (pessimistic) actor; per_seed runs it on one
            # observation, as the scripts' one-seed evaluations do
            act = getattr(actor, "deterministic_action", actor)

            def policy(obs):
                return per_seed(act)(torch.as_tensor(obs)).numpy()
    except (RuntimeError, KeyError) as e:  # another algorithm's or another task's model
        fail(f"{model_path!r} does not fit {algo} on this task ({type(e).__name__}: {str(e).splitlines()[0]})")
    except TypeError as e:  # a fork whose networks take other arguments
        fail(
            f"{algo}'s networks are not built as tools/evaluate.py builds them (Actor(obs_dim, action_space); Agent(obs_dim, "
            f"action_dim)): {str(e).splitlines()[0]}; build its policy in load_policy as the script's main does"
        )
    if "probe" in saved:  # the trained policy's actions on fixed observations (rl_utils.envs.policy_probe)
        probe = saved["probe"]
        with torch.no_grad():
            rebuilt = np.stack([policy(x[None].numpy())[0] for x in probe["observations"]])
        differences = np.abs(rebuilt - probe["actions"].numpy())
        differences[np.isnan(rebuilt) & np.isnan(probe["actions"].numpy())] = 0  # NaN where the trained one gave NaN
        if not np.max(differences) <= PROBE_TOLERANCE * float(np.max(high - low)):  # a NaN of one of them fails it
            fail(
                f"the policy built from {model_path!r} does not act as the run's evaluated policy did (an action off by "
                f"{np.max(differences):.3g} on the fixed observations --save-model recorded): {algo}'s policy depends on "
                "something tools/evaluate.py does not rebuild (a flag of a fork, a changed default, another policy "
                "evaluated in main); build it in load_policy as the script's main does"
            )
    return policy


def main(argv=None) -> np.ndarray:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a file written by --save-model (runs/{run_name}/{exp_name}.cleanrl_model)")
    parser.add_argument("--algo", choices=ALGOS, help="the script that trained it (default: from the file name)")
    parser.add_argument("--env-id", help="the task (default: from the run folder's name)")
    parser.add_argument("--episodes", type=int, default=10, help="deterministic episodes to run (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode's reset (default 0)")
    parser.add_argument("--capture-video", action="store_true", help="record the first episode")
    parser.add_argument(
        "--video-folder", default="videos/evaluate", help="where --capture-video writes (default videos/evaluate)"
    )
    args = parser.parse_args(argv)

    if not os.path.isfile(args.model):
        fail(f"no such model file: {args.model!r}")
    if args.episodes < 1:
        fail(f"--episodes must be >= 1, got {args.episodes}")
    algo = args.algo or infer_algo(args.model)
    if algo is None:
        fail(f"cannot tell the algorithm from {os.path.basename(args.model)!r}; pass --algo ({', '.join(ALGOS)})")
    env_id = args.env_id or infer_env_id(args.model)
    if env_id is None:
        fail(f"cannot tell the task from the folder of {args.model!r}; pass --env-id")
    if not args.capture_video:
        os.environ.setdefault("MUJOCO_GL", "disable")  # as the scripts: nothing probes for a display

    torch.set_num_threads(1)
    script = importlib.import_module(f"{algo}_continuous_action")
    video_folder = args.video_folder if args.capture_video else None
    env = make_env(env_id, args.seed, video_folder, video_every=args.episodes)
    policy = load_policy(script, algo, args.model, env)
    with torch.no_grad():
        returns = evaluate(policy, [env], [args.seed], args.episodes)[0]  # the one env's
    env.close()
    print(f"{algo} on {env_id}: mean return {returns.mean():.1f} +- {returns.std():.1f} over {args.episodes} episodes")
    if video_folder:
        print(f"video of the first episode in {video_folder}")
    return returns


if __name__ == "__main__":
    main()
