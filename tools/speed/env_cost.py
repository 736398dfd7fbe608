"""What one environment step costs on this CPU, through a script's own environment layer (the make_env, with its
wrappers, that builds the script's environments: rl_utils.envs', which every script shares), stepped as a many-seed
process steps its environments: one after another, with random actions drawn beforehand.

    python tools/speed/env_cost.py dm_control/cartpole-swingup-v0 dm_control/walker-walk-v0 --envs 16 --steps 1000

A process training N seeds spends about N times this per training step on the CPU before any network runs,
which bounds its steps/s however fast the GPU is (docs/speed.md, "On one GPU").
"""

import argparse
import importlib.util
import os
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def load(script: str):
    sys.path.insert(0, REPO)  # the scripts import rl_utils
    spec = importlib.util.spec_from_file_location(script, os.path.join(REPO, f"{script}_continuous_action.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def make_env_of(script: str):
    """The make_env that builds the script's environments: the one its SeedEnvs calls (or its own, if it has one)."""
    module = load(script)
    if hasattr(module, "make_env"):
        return module.make_env
    return vars(sys.modules[module.SeedEnvs.__module__])["make_env"]


def step_cost(make_env, env_id: str, num_envs: int, steps: int) -> float:
    """Seconds per environment step, resets included, over steps x num_envs steps."""
    envs = [make_env(env_id, seed) for seed in range(num_envs)]
    actions = []  # drawn before the clock starts: a training step's actions come from the actor, not the action space
    for k, env in enumerate(envs):
        env.reset(seed=k)
        env.action_space.seed(k)
        actions.append([env.action_space.sample() for _ in range(steps)])
    start = time.perf_counter()
    for i in range(steps):
        for env, env_actions in zip(envs, actions):
            _, _, terminated, truncated, _ = env.step(env_actions[i])
            if terminated or truncated:
                env.reset()
    took = time.perf_counter() - start
    for env in envs:
        env.close()
    return took / (steps * num_envs)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("env_ids", nargs="+")
    parser.add_argument("--envs", type=int, default=16, help="environments stepped one after another")
    parser.add_argument("--steps", type=int, default=1000, help="steps of each environment")
    parser.add_argument("--script", default="td3", help="whose make_env (all off-policy scripts share one layer)")
    args = parser.parse_args(argv)
    if args.envs <= 0 or args.steps <= 0:
        parser.error(f"--envs and --steps must be > 0, got {args.envs} and {args.steps}")
    if not os.path.exists(os.path.join(REPO, f"{args.script}_continuous_action.py")):
        parser.error(f"--script {args.script}: no {args.script}_continuous_action.py")
    make_env = make_env_of(args.script)
    print(f"| task | ms per environment step ({args.envs} environments x {args.steps} steps) |")
    print("|---|---|")
    for env_id in args.env_ids:
        cost = step_cost(make_env, env_id, args.envs, args.steps)  # an unknown task: make_env's one-line error
        print(f"| {env_id} | {cost * 1e3:.3f} |")


if __name__ == "__main__":
    main()
