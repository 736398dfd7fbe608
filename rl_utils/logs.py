"""What a process's runs report: each run's TensorBoard log (and Weights and Biases with --track), the progress bar,
the evaluations (recorded for the checkpoints too) and the training speed."""

import math
import os
import sys
import time

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from rl_utils.errors import fail, refusal
from rl_utils.numerics import NonFiniteError


class Logs:
    """TensorBoard, one writer per run folder (a resumed run hides what the killed process logged after its
    checkpoint), Weights and Biases with --track, and a progress bar on a terminal (in a log file the per-evaluation
    lines say the same). Each run's hyperparameters table gives its own seed, and the flags as the run was given
    them (`given`, before main filled any in from the task: a flag set from the action dimension would make every
    task's runs another variant of the algorithm in plot_results.py)."""

    def __init__(
        self, args, run_dirs: list, seeds: list, start_step: int, eval_returns: list, device: torch.device, given=None
    ):
        self.seeds, self.eval_returns = seeds, eval_returns
        given = dict(given if given is not None else vars(args))
        names = [os.path.basename(run_dir) for run_dir in run_dirs]
        if args.track:
            try:
                import wandb
            except ImportError:
                fail("--track needs Weights and Biases: pip install wandb")
            wandb.init(
                project=args.wandb_project_name,
                entity=args.wandb_entity,
                sync_tensorboard=True,
                config=given,
                name=names[0],
                monitor_gym=True,
                save_code=True,
            )
        self.writers = [SummaryWriter(d, purge_step=start_step if args.resume else None) for d in run_dirs]
        for seed, writer in zip(seeds, self.writers if not args.resume else []):
            table = "\n".join(f"|{key}|{value}|" for key, value in {**given, "seed": seed}.items())
            writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
        self.pbar = tqdm(total=args.total_timesteps, initial=start_step, unit="step", disable=not sys.stderr.isatty())
        resumed = f", resumed at step {start_step}" if args.resume else ""
        tqdm.write(f"{', '.join(names)}: {args.env_id} on {device}, logging to {', '.join(run_dirs)}{resumed}")
        self.sps_time, self.sps_step, self.sps = time.time(), start_step, 0.0

    def evaluate(self, step: int, returns: np.ndarray):
        """Records each seed's evaluation returns [num_seeds, episodes]: in its TensorBoard run, its checkpoints and a
        line. The time it took does not count in the training speed."""
        n = len(self.writers)
        if np.ndim(returns) != 2 or np.shape(returns)[0] != n:
            raise refusal(
                ValueError,
                f"run.evaluate: returns of shape {list(np.shape(returns))} for {n} seed(s): one row of episode returns per "
                f"seed, [{n}, episodes] (rl_utils.evaluate gives them)",
            )
        if self.eval_returns[0] and self.eval_returns[0][-1][0] == step:
            raise refusal(
                ValueError,
                f"run.evaluate: a second evaluation at step {step}: eval/episodic_return and the checkpoints keep one a "
                "step; log another policy's returns under a tag of its own (run.log({'eval/other_return': ...}, step))",
            )
        for k, (writer, seed_returns) in enumerate(zip(self.writers, returns)):
            self.eval_returns[k].append((step, float(seed_returns.mean())))
            writer.add_scalar("eval/episodic_return", seed_returns.mean(), step)
            label = f"seed {self.seeds[k]} " if len(self.seeds) > 1 else ""
            tqdm.write(
                f"{label}step {step}: return {seed_returns.mean():.1f} +- {seed_returns.std():.1f}, {self.sps:.0f} steps/s"
            )
        self.pbar.set_postfix(eval_return=f"{returns.mean():.1f}")
        self.sps_time = time.time()

    def log(self, logs: dict, step: int):
        """Writes {tag: one value per seed (a tensor [num_seeds]; with one seed, a number will do)}, each seed's into its
        run; a non-finite value stops the run (where --cudagraphs catches a NaN). With several seeds a value of another
        size stops in one line: a 0-d tensor (a mean over the seeds?), or a Python or NumPy number (a value read with
        .item() from every seed's values), which would be logged as every seed's own."""
        n = len(self.writers)
        for tag, value in logs.items():
            if (value.numel() if isinstance(value, torch.Tensor) else np.size(value)) == n:
                continue
            if n == 1:
                raise refusal(
                    ValueError,
                    f"run.log: `{tag}` has {np.size(value) if not isinstance(value, torch.Tensor) else value.numel()} "
                    f"values (shape {list(np.shape(value))}): log one number per seed (a mean over the batch, .mean())",
                )
            if isinstance(value, torch.Tensor) or np.ndim(value) > 0:
                what = f"{'a tensor' if isinstance(value, torch.Tensor) else 'an array'} of shape {list(np.shape(value))}"
                hint = "a mean over each seed's own dimensions, .mean(-1), not over the seeds"
            else:
                what = f"a number ({type(value).__name__})"
                hint = (
                    "a number read with .item() or float() from every seed's values is one for them all, and would be "
                    f"logged as each seed's; a value the seeds share, such as a schedule's: [value] * {n}"
                )
            raise refusal(
                ValueError, f"run.log: `{tag}` is {what} for {n} seeds: log one value per seed, a tensor [{n}] ({hint})"
            )
        values = {tag: torch.as_tensor(value).reshape(-1).broadcast_to(n).tolist() for tag, value in logs.items()}
        for tag, seed_values in values.items():
            if not all(math.isfinite(value) for value in seed_values):
                error = NonFiniteError(tag.split("/")[-1])
                error.tag = tag
                raise error
        for tag, seed_values in values.items():
            for writer, value in zip(self.writers, seed_values):
                writer.add_scalar(tag, value, step)

    def log_episodes(self, infos, step: int):
        """Each finished training episode's return and length (SeedEnvs' infos, or a list of one env's info)."""
        episodes = infos["episode"] if isinstance(infos, dict) else [info.get("episode") for info in infos]
        for writer, episode in zip(self.writers, episodes):
            if episode is not None:
                writer.add_scalar("charts/episodic_return", episode["r"], step)
                writer.add_scalar("charts/episodic_length", episode["l"], step)

    def step(self, step: int):
        """After step `step`: the training speed every 1000 steps (evaluations excluded) and the progress bar."""
        if (step + 1) % 1000 == 0:
            self.sps = (step + 1 - self.sps_step) / (time.time() - self.sps_time)
            for writer in self.writers:
                writer.add_scalar("charts/SPS", self.sps, step)
            self.sps_time, self.sps_step = time.time(), step + 1
        self.pbar.update(1)

    def close(self):
        self.pbar.close()
        for writer in self.writers:
            writer.close()
