"""Run the authors' released OPARL code, unmodified, on today's stack and on a CPU, and write its
evaluations in our eval_series.csv format (algorithm `oparl_release`), so plot_results.py draws it
beside ours.

    git clone https://github.com/yydsok/OPARL ../OPARL && git -C ../OPARL checkout 7974f9905f7cd306b895ab4c17e9e68ab5e15bd9
    python tools/authors_release.py --release-dir ../OPARL --env-id dm_control/walker-walk-v0 --seed 1 --total-timesteps 100000

The release (`main.py`, `TD3.py`, `utils.py`) runs with its own defaults; only the domain, task,
seed, budget and random phase are passed to its `main.py`. What this adapter changes, and why each
change leaves the algorithm untouched:

1. `dmc2gym.make` (which no longer installs beside today's dm_control) is a stand-in with
   dmc2gym's behaviour, for state observations with no action repeat as the release uses it: the
   task loaded with `task_kwargs={"random": seed}`, observations flattened in the task's order into
   one float64 vector, actions in [-1, 1] checked against those bounds and rescaled to the task's,
   `done` at the end of the task or after `_max_episode_steps = 1000` steps (gym's TimeLimit), and
   `seed()` re-seeding only the spaces (the physics keeps the generator the load gave it).
2. `import gym` is satisfied by Gymnasium, whose `Box` spaces stand in for gym's; the release uses
   them for `.shape`, `.high`, `.seed()` and `.sample()` only.
3. `main.py` moves the optimistic candidates with a hard-coded `.to('cuda')`; the two calls read
   `.to(TD3.device)` once loaded, the device `TD3.py` itself chose (the GPU where there is one).
   The file on disk is not changed.
4. It runs in its own folder (`--run-dir`), where `main.py` writes its `results/*.npy` and
   `seed=N_result.txt`, and with `--threads` torch threads.

Our scripts' evaluation schedule is the release's: 10 noiseless episodes of the pessimistic actor
at step 0 and every 5000 steps, the last at the end.
"""

import csv
import glob
import os
import re
import sys
import time
import types
from dataclasses import dataclass
from typing import Optional

import numpy as np
import tyro

RELEASE_COMMIT = "7974f9905f7cd306b895ab4c17e9e68ab5e15bd9"
ALGO = "oparl_release"
CUDA_CALL = ".to('cuda')"


@dataclass
class Args:
    release_dir: str
    """a checkout of github.com/yydsok/OPARL (main.py, TD3.py, utils.py), commit 7974f99 as tested"""
    env_id: str = "dm_control/walker-walk-v0"
    """a DeepMind Control task, dm_control/<domain>-<task>-v0 (the release runs dm_control only)"""
    seed: int = 1
    """the release's --seed"""
    total_timesteps: int = 100000
    """the release's --max_timesteps"""
    learning_starts: int = 25000
    """the release's --start_timesteps (random actions before learning)"""
    run_dir: Optional[str] = None
    """where main.py runs and writes (default: runs/{env}__oparl_release__{seed}__{total_timesteps})"""
    threads: int = 1
    """torch threads"""
    cuda: bool = False
    """let TD3.py take the GPU where there is one (it would by itself); off: the CPU, like our runs here"""


def fail(message: str):
    raise SystemExit("error: " + message)


def parse_env_id(env_id: str) -> tuple:
    match = re.fullmatch(r"dm_control/([a-z_]+)-([a-z_0-9]+)-v0", env_id)
    if not match:
        fail(f"--env-id {env_id!r}: the release runs DeepMind Control tasks only, as dm_control/<domain>-<task>-v0")
    from dm_control import suite

    if (match[1], match[2]) not in suite.ALL_TASKS:
        fail(f"--env-id {env_id!r}: dm_control has no task {match[1]}-{match[2]}")
    return match[1], match[2]


class DMCEnv:
    """dmc2gym's DMCWrapper inside gym's TimeLimit, as the release sees it (state observations, frame skip 1)."""

    def __init__(self, domain_name: str, task_name: str, seed: int):
        import gymnasium
        from dm_control import suite

        self._env = suite.load(domain_name, task_name, task_kwargs={"random": seed})
        spec = self._env.action_spec()
        self._low, self._high = spec.minimum.astype(np.float64), spec.maximum.astype(np.float64)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, spec.shape, np.float32)
        obs_dim = sum(int(np.prod(v.shape)) for v in self._env.observation_spec().values())
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self._max_episode_steps = 1000
        self._elapsed_steps = 0

    @staticmethod
    def _flatten(observation) -> np.ndarray:
        return np.concatenate(
            [np.array([v]) if np.isscalar(v) else np.asarray(v).ravel() for v in observation.values()]
        ).astype(np.float64)

    def seed(self, seed: int):
        self.action_space.seed(seed)
        self.observation_space.seed(seed)

    def reset(self) -> np.ndarray:
        self._elapsed_steps = 0
        return self._flatten(self._env.reset().observation)

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape or not np.all((action >= -1.0) & (action <= 1.0)):
            raise AssertionError(f"action {action} outside dmc2gym's [-1, 1]^{self.action_space.shape[0]}")
        time_step = self._env.step((action + 1.0) / 2.0 * (self._high - self._low) + self._low)
        self._elapsed_steps += 1
        done = time_step.last() or self._elapsed_steps >= self._max_episode_steps
        return self._flatten(time_step.observation), time_step.reward or 0.0, done, {"discount": time_step.discount}


def dmc2gym_module() -> types.ModuleType:
    module = types.ModuleType("dmc2gym")

    def make(domain_name, task_name, seed=1, from_pixels=False, visualize_reward=True, **kwargs):
        if from_pixels:
            raise NotImplementedError("the stand-in serves state observations, as the release uses them")
        return DMCEnv(domain_name, task_name, seed)

    module.make = make
    return module


def release_main_source(release_dir: str) -> str:
    """main.py with its hard-coded CUDA device replaced by TD3.py's device."""
    path = os.path.join(release_dir, "main.py")
    source = open(path).read()
    if source.count(CUDA_CALL) != 2:
        fail(f"{path}: expected 2 calls {CUDA_CALL}, found {source.count(CUDA_CALL)}; is it commit {RELEASE_COMMIT[:7]}?")
    return source.replace(CUDA_CALL, ".to(TD3.device)")


def run_release(args: Args, domain: str, task: str, run_dir: str):
    import gymnasium
    import torch

    release_dir = os.path.abspath(args.release_dir)
    source = release_main_source(release_dir)
    if not args.cuda:
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # before TD3.py asks torch for a GPU
    torch.set_num_threads(args.threads)
    sys.modules["gym"] = gymnasium
    sys.modules["dmc2gym"] = dmc2gym_module()
    sys.path.insert(0, release_dir)
    argv = [
        "--domain_name",
        domain,
        "--task_name",
        task,
        "--seed",
        str(args.seed),
        "--max_timesteps",
        str(args.total_timesteps),
        "--start_timesteps",
        str(args.learning_starts),
    ]
    sys.argv = [os.path.join(release_dir, "main.py"), *argv]
    os.chdir(run_dir)
    exec(compile(source, sys.argv[0], "exec"), {"__name__": "__main__", "__file__": sys.argv[0]})


def evaluations(run_dir: str, seed: int) -> list:
    """The release's evaluations, (step, mean return), from the log main.py appends to: a line
    `Timesteps N Evaluation over 10 episodes: R` per evaluation, step 0 included (its results/*.npy
    holds the same, but only once a run has passed 5000 steps)."""
    path = os.path.join(run_dir, f"seed={seed}_result.txt")
    found = re.findall(
        r"^Timesteps (\d+) Evaluation over \d+ episodes: (-?[\d.]+)$", open(path).read() if os.path.exists(path) else "", re.M
    )
    if not found:
        fail(f"{path} holds no evaluation; main.py did not run to its first one")
    return [(int(step), float(value)) for step, value in found]


def write_eval_series(path: str, env_id: str, seed: int, evaluated: list):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["algo", "env_id", "seed", "step", "episodic_return"])
        writer.writerows((ALGO, env_id, seed, step, f"{value:.4f}") for step, value in evaluated)


def main(argv=None):
    args = tyro.cli(Args, args=argv)
    for name in ("main.py", "TD3.py", "utils.py"):
        if not os.path.isfile(os.path.join(args.release_dir, name)):
            fail(
                f"--release-dir {args.release_dir}: no {name} (a checkout of github.com/yydsok/OPARL, commit {RELEASE_COMMIT[:7]})"
            )
    if args.total_timesteps <= 0 or args.learning_starts < 0 or args.threads <= 0:
        fail("--total-timesteps and --threads must be > 0, --learning-starts >= 0")
    try:
        import einops  # noqa: F401  (the release's main.py imports it)
    except ImportError:
        fail("the release's main.py needs einops: pip install einops")
    domain, task = parse_env_id(args.env_id)
    run_dir = os.path.abspath(
        args.run_dir or os.path.join("runs", f"{args.env_id.replace('/', '-')}__{ALGO}__{args.seed}__{args.total_timesteps}")
    )
    csv_path = os.path.join(run_dir, "eval_series.csv")
    if os.path.isdir(os.path.join(run_dir, "results")):  # the release cannot resume: a run starts again from scratch
        for stale in glob.glob(os.path.join(run_dir, "results", "*.npy")) + glob.glob(
            os.path.join(run_dir, "seed=*_result.txt")
        ):
            os.remove(stale)
    os.makedirs(run_dir, exist_ok=True)
    start = time.time()
    run_release(args, domain, task, run_dir)
    evaluated = evaluations(run_dir, args.seed)
    write_eval_series(csv_path, args.env_id, args.seed, evaluated)
    print(
        f"{ALGO} {args.env_id} seed {args.seed}: {len(evaluated)} evaluations, final {evaluated[-1][1]:.1f} at step {evaluated[-1][0]}, {time.time() - start:.0f} s; {csv_path}"
    )
    return csv_path


if __name__ == "__main__":
    main()
