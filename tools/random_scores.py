"""The mean return of a uniformly random policy per task: the 0 of plot_results.py --random-scores, which
normalises tasks without a common scale (MuJoCo) from the random policy (0) to the best run seen (1).

    python tools/random_scores.py Ant-v4 Hopper-v4 Humanoid-v4 Walker2d-v4 --episodes 100 --out results/mujoco/random_scores.csv

Episodes run through the scripts' own environment layer (rl_utils.envs.make_env), with actions
drawn uniformly from the action space, seeded, so the file is reproducible.
"""

import argparse
import csv
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from rl_utils import make_env  # noqa: E402


def random_returns(env_id: str, episodes: int, seed: int) -> np.ndarray:
    env = make_env(env_id, seed)
    returns = np.zeros(episodes)
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        done = False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            returns[episode] += reward
            done = terminated or truncated
    env.close()
    return returns


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("env_ids", nargs="+")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="the CSV to write: env_id, random_return (mean), std, episodes, seed")
    args = parser.parse_args(argv)
    if args.episodes <= 0:
        parser.error(f"--episodes must be > 0, got {args.episodes}")
    os.environ.setdefault("MUJOCO_GL", "disable")
    rows = []
    for env_id in args.env_ids:
        returns = random_returns(env_id, args.episodes, args.seed)
        rows.append((env_id, f"{returns.mean():.4f}", f"{returns.std():.4f}", args.episodes, args.seed))
        print(f"{env_id}: {returns.mean():.1f} +- {returns.std():.1f} over {args.episodes} random episodes")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["env_id", "random_return", "std", "episodes", "seed"])
        writer.writerows(rows)


if __name__ == "__main__":
    main()
