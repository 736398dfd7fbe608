"""A process's runs: one per seed (--num-seeds), each with its folder under runs/, its TensorBoard log, its
evaluations, its checkpoints and its saved model, as an ordinary single-seed run has them."""

import contextlib
import dataclasses
import math
import os
import sys
import time

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from rl_utils import checkpoints as ckpt
from rl_utils.cli import fail, script_of
from rl_utils.envs import SeedEnvs
from rl_utils.numerics import NonFiniteError


class Run:
    """The machinery around a script's loop, in the order the loop meets it:

    run = Run(args)                        # run folders; with --resume, the checkpoints to continue from
    obs = run.start(envs, device, nets, optimizers, buffer=rb)   # restored on --resume; opens the logs
    run.evaluate(step, returns)            # a deterministic evaluation: recorded, logged, printed
    run.log(logs, step); run.log_episodes(infos, step)
    with run.stop_on_nan(step): ...        # a non-finite loss ends the run, its last finite state saved
    run.end_step(step)                     # speed, progress bar, a checkpoint when one is due
    return run.finish(save={"actor": actor})
    """

    def __init__(self, args):
        self.args, self.script = args, script_of(type(args))
        self.seeds = list(range(args.seed, args.seed + getattr(args, "num_seeds", 1)))  # trained side by side
        self.checkpoints = ckpt.load_checkpoints(args.resume, self.script) if args.resume else None  # one per seed
        self.run_dirs = self.folders()
        self.start_step = self.checkpoints[0]["global_step"] if self.checkpoints else 0
        self.eval_returns = [c["eval_returns"] for c in self.checkpoints] if self.checkpoints else [[] for _ in self.seeds]
        self.finished = self.start_step >= args.total_timesteps
        if self.finished:
            print(f"{', '.join(self.run_dirs)} had already finished its {args.total_timesteps} steps")
        self.video_folders = [f"videos/{os.path.basename(d)}" if args.capture_video else None for d in self.run_dirs]
        if not args.capture_video:  # nothing renders: spare dm_control its probe for a display (and its warning)
            os.environ.setdefault("MUJOCO_GL", "disable")

    def folders(self) -> list:
        """Each seed's run folder: --resume's and those of the seeds that trained beside it, or runs/ + --run-name
        ({seed} replaced by each seed's number), by default {env_id}__{exp_name}__{seed}__{unix time}."""
        args = self.args
        if self.checkpoints:
            parent = os.path.dirname(os.path.normpath(args.resume))
            return [os.path.join(parent, name) for name in self.checkpoints[0]["run_names"]]
        template = args.run_name or f"{args.env_id.replace('/', '-')}__{args.exp_name}__{{seed}}__{int(time.time())}"
        return [os.path.join("runs", template.replace("{seed}", str(seed))) for seed in self.seeds]

    def start(self, envs, device: torch.device, nets: dict, optimizers: dict, **parts):
        """Names what a checkpoint holds (with the envs and the random generators): the networks, the optimizers and
        `parts` (the replay buffer, tensors such as SAC's log_alpha, objects with a state_dict()); restores them on
        --resume; opens the logs. Returns the observations to act on: for SeedEnvs [num_seeds, obs_dim], fresh or
        restored; for one plain env, the restored observation, or None where an episode starts."""
        self.envs, self.nets, self.optimizers, self.parts = envs, nets, optimizers, parts
        self.env_list = list(envs) if isinstance(envs, SeedEnvs) else [envs]
        observations = None
        if self.checkpoints:
            observations = ckpt.restore(ckpt.join_seeds(self.checkpoints, nets, parts), self.env_list, nets, optimizers, parts)
        self.open_logs(device)
        self.next_checkpoint = self.start_step + self.args.checkpoint_frequency
        if isinstance(envs, SeedEnvs):
            return np.stack(observations) if observations else envs.reset()
        return observations[0] if observations else None

    def open_logs(self, device: torch.device):
        """TensorBoard, one writer per run folder (a resumed run hides what the killed process logged after its
        checkpoint), Weights and Biases with --track, and a progress bar on a terminal (in a log file the per-evaluation
        lines say the same). Each run's hyperparameters table gives its own seed."""
        args, names = self.args, [os.path.basename(run_dir) for run_dir in self.run_dirs]
        if args.track:
            try:
                import wandb
            except ImportError:
                fail("--track needs Weights and Biases: pip install wandb")
            wandb.init(
                project=args.wandb_project_name,
                entity=args.wandb_entity,
                sync_tensorboard=True,
                config=vars(args),
                name=names[0],
                monitor_gym=True,
                save_code=True,
            )
        self.writers = [SummaryWriter(d, purge_step=self.start_step if args.resume else None) for d in self.run_dirs]
        for seed, writer in zip(self.seeds, self.writers if not args.resume else []):
            table = "\n".join(f"|{key}|{value}|" for key, value in {**vars(args), "seed": seed}.items())
            writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
        self.pbar = tqdm(total=args.total_timesteps, initial=self.start_step, unit="step", disable=not sys.stderr.isatty())
        resumed = f", resumed at step {self.start_step}" if args.resume else ""
        tqdm.write(f"{', '.join(names)}: {args.env_id} on {device}, logging to {', '.join(self.run_dirs)}{resumed}")
        self.sps_time, self.sps_step, self.sps = time.time(), self.start_step, 0.0

    def evaluate(self, step: int, returns: np.ndarray):
        """Records each seed's evaluation returns [num_seeds, episodes]: in its TensorBoard run, its checkpoints and a
        line. The time it took does not count in the training speed."""
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
        """Writes {tag: one value per seed (a tensor [num_seeds]), or one for all (a number)}, each seed's into its
        run; a non-finite value stops the run (where --cudagraphs catches a NaN)."""
        n = len(self.writers)
        values = {tag: torch.as_tensor(value).reshape(-1).broadcast_to(n).tolist() for tag, value in logs.items()}
        for tag, seed_values in values.items():
            if not all(math.isfinite(value) for value in seed_values):
                raise NonFiniteError(tag.split("/")[-1])
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

    def state(self, step: int) -> list:
        """One checkpoint per seed of the process's state at `step`."""
        state = ckpt.snapshot(self.script, self.args, self.env_list, step, self.nets, self.optimizers, self.parts)
        return ckpt.split_seeds(state, self.nets, self.parts, self.eval_returns, self.run_dirs)

    @contextlib.contextmanager
    def stop_on_nan(self, step: int):
        """Ends the run on a non-finite loss. An eager update stops before the optimizer step that the loss would
        have poisoned, so the state is still finite and is saved (each seed's in its folder); a recorded graph is
        checked only when it logs."""
        try:
            yield
        except NonFiniteError as quantity:
            if getattr(self.args, "cudagraphs", False):
                fail(
                    f"{quantity} became non-finite by step {step} (--cudagraphs checks every 100 steps and keeps no last "
                    "finite state; without it a run stops at the first bad update)"
                )
            ckpt.write_checkpoints(self.run_dirs, self.state(step), "last_good_state.pt")
            fields = [f.name for f in dataclasses.fields(self.args)]
            rates = [f"--{name.replace('_', '-')}" for name in fields if name.endswith(("lr", "learning_rate"))]
            path = os.path.join(self.run_dirs[0], "last_good_state.pt")
            where = path if len(self.run_dirs) == 1 else f"{path} and the other seeds' folders"
            fail(
                f"{quantity} became non-finite at step {step} (try a smaller {' or '.join(rates)}); the last finite state "
                f"is in {where}"
            )

    def end_step(self, step: int, can_checkpoint: bool = True):
        """After step `step`: the training speed every 1000 steps (evaluations excluded), the progress bar, and a
        checkpoint every --checkpoint-frequency steps (where `can_checkpoint`; the last one is finish()'s)."""
        args = self.args
        if (step + 1) % 1000 == 0:
            self.sps = (step + 1 - self.sps_step) / (time.time() - self.sps_time)
            for writer in self.writers:
                writer.add_scalar("charts/SPS", self.sps, step)
            self.sps_time, self.sps_step = time.time(), step + 1
        self.pbar.update(1)
        if args.checkpoint_frequency and can_checkpoint and self.next_checkpoint <= step + 1 < args.total_timesteps:
            ckpt.write_checkpoints(self.run_dirs, self.state(step + 1))
            self.next_checkpoint = step + 1 + args.checkpoint_frequency

    def finish(self, save: dict, eval_envs=None) -> dict:
        """The last checkpoint, --save-model (each seed's cut of the `save` networks, tensors or objects), the envs and
        logs closed. Returns the runs' folders and evaluations."""
        args = self.args
        if args.checkpoint_frequency:
            ckpt.write_checkpoints(self.run_dirs, self.state(args.total_timesteps))
        self.pbar.close()
        if args.save_model:
            for k, run_dir in enumerate(self.run_dirs):
                model_path = os.path.join(run_dir, f"{args.exp_name}.cleanrl_model")
                torch.save(ckpt.model_of_seed(save, k, len(self.run_dirs)), model_path)
                tqdm.write(f"model saved to {model_path}")
        for env in [*self.env_list, *(eval_envs if isinstance(eval_envs, SeedEnvs) else [eval_envs] if eval_envs else [])]:
            env.close()
        for writer in self.writers:
            writer.close()
        return self.results()

    def results(self) -> dict:
        """What main returns about the runs: every seed's, and the first seed's as a single-seed run gives them."""
        return {
            "run_dir": self.run_dirs[0],
            "eval_returns": self.eval_returns[0],
            "run_dirs": self.run_dirs,
            "seeds_eval_returns": self.eval_returns,
        }
