# REDQ (Chen et al. 2021, "Randomized Ensembled Double Q-Learning", https://arxiv.org/abs/2101.05982),
# a baseline of the OPARL paper, as a copy of sac_continuous_action.py: `diff sac_continuous_action.py
# redq_continuous_action.py` shows what REDQ changes: an ensemble of 10 critics, a target that takes
# the min over a random subset of 2 of them, 20 critic updates per environment step, and an actor
# trained on the mean of all critics. At that update-to-data ratio a step costs ~40 SAC steps (docs/speed.md).
import dataclasses
import difflib
import functools
import math
import os
import random
import sys
import time
from dataclasses import dataclass
from typing import NamedTuple, Optional

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import torch.optim as optim
import tyro
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """whether to set `torch.backends.cudnn.deterministic` (`--no-torch-deterministic` leaves it off)"""
    cuda: bool = True
    """if toggled, cuda will be enabled by default (falls back to the CPU when no GPU is found)"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "cleanRL"
    """the wandb's project name"""
    wandb_entity: Optional[str] = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to record videos of evaluation episodes into `videos/{run_name}` (headless: set MUJOCO_GL=egl)"""
    save_model: bool = False
    """whether to save the actor and critics into the `runs/{run_name}` folder"""
    run_name: Optional[str] = None
    """name of the run folder under runs/ (default: {env_id}__{exp_name}__{seed}__{unix time})"""
    checkpoint_frequency: int = 0
    """write `checkpoint.pt` into the run folder at the first episode end after every this many steps, and at the end (0: never)"""
    resume: Optional[str] = None
    """continue the run in this folder (e.g. runs/{run_name}) from its checkpoint; flags given with it must match the run's"""

    # Algorithm specific arguments
    env_id: str = "Hopper-v4"
    """the id of the environment: a Gymnasium id (Hopper-v4, ...) or dm_control/<domain>-<task>-v0"""
    total_timesteps: int = 1000000
    """total timesteps of the experiments"""
    buffer_size: int = int(1e6)
    """the replay memory buffer size"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient (default: 0.005)"""
    batch_size: int = 256
    """the batch size of sample from the reply memory"""
    learning_starts: int = 5000
    """timestep to start learning"""
    policy_lr: float = 3e-4
    """the learning rate of the policy network optimizer"""
    q_lr: float = 3e-4
    """the learning rate of the Q network network optimizer (and of the entropy coefficient)"""
    num_q: int = 10
    """the number of critics in the ensemble (N)"""
    num_min: int = 2
    """the size of the random subset of target critics the target takes the min over (M)"""
    utd_ratio: int = 20
    """critic updates per environment step (G), each on a fresh batch and followed by a target update"""
    alpha: float = 0.2
    """Entropy regularization coefficient (its start value is 1 when --autotune is on)"""
    autotune: bool = True
    """automatic tuning of the entropy coefficient, towards an entropy of --target-entropy"""
    target_entropy: Optional[float] = None
    """the entropy --autotune steers towards (default: REDQ's release's per-task value where it has one, else -|A|)"""

    # Evaluation (the metric the paper reports)
    eval_frequency: int = 5000
    """evaluate the deterministic actor every this many environment steps"""
    eval_episodes: int = 10
    """the number of episodes per evaluation"""
    bf16: bool = False
    """run the training matmuls in bfloat16 (autocast; weights, losses and optimizer states stay float32)"""
    cudagraphs: bool = False
    """record each kind of training update once as a CUDA graph and replay it (needs a CUDA GPU); losses are checked for NaN every 100 steps"""


# ALGO LOGIC: initialize agent here:
class QEnsemble(nn.Module):
    """`num_q` critics concat(obs, action) -> 256 -> 256 -> 1, each layer's weights stacked into one
    [num_q, in, out] tensor so that one batched matmul evaluates every member."""

    def __init__(self, obs_dim: int, action_dim: int, num_q: int = 2, hidden: int = 256):
        super().__init__()

        def uniform(fan_in, *shape):  # the default init of nn.Linear, drawn independently per member
            return nn.Parameter(torch.empty(num_q, *shape).uniform_(-(fan_in**-0.5), fan_in**-0.5))

        in_dim = obs_dim + action_dim
        self.w1, self.b1 = uniform(in_dim, in_dim, hidden), uniform(in_dim, 1, hidden)
        self.w2, self.b2 = uniform(hidden, hidden, hidden), uniform(hidden, 1, hidden)
        self.w3, self.b3 = uniform(hidden, 1, hidden), uniform(hidden, 1)  # the output layer, as rows

    def forward(self, obs, actions, members=None, detach_params=False):
        """Q-values [num_q, batch]. `detach_params` lets gradients reach the actions only, which is all an actor
        loss needs."""
        params = list(self.parameters())
        if members is not None:  # a subset of the critics (only then: a full slice would copy each weight's gradient)
            params = [p[members] for p in params]
        w1, b1, w2, b2, w3, b3 = [p.detach() for p in params] if detach_params else params
        x = torch.cat([obs, actions], -1)
        x = F.relu(torch.baddbmm(b1, x.expand(len(w1), -1, -1), w1))
        x = F.relu(torch.baddbmm(b2, x, w2))
        return (x * w3).sum(-1) + b3  # a dot product per member: cheaper than a matmul with one output


LOG_STD_MAX = 2
LOG_STD_MIN = -5
# REDQ's release (redq/algos/core.py, from MBPO) steers alpha towards these entropies on its MuJoCo tasks
RELEASE_TARGET_ENTROPY = {"Hopper-v4": -1.0, "HalfCheetah-v4": -3.0, "Walker2d-v4": -3.0, "Ant-v4": -4.0, "Humanoid-v4": -2.0}


class Actor(nn.Module):
    """A Gaussian policy squashed by tanh into the action bounds."""

    def __init__(self, obs_dim: int, action_space: gym.spaces.Box):
        super().__init__()
        self.fc1 = nn.Linear(obs_dim, 256)
        self.fc2 = nn.Linear(256, 256)
        self.fc_mean = nn.Linear(256, int(np.prod(action_space.shape)))
        self.fc_logstd = nn.Linear(256, int(np.prod(action_space.shape)))
        # action rescaling
        low, high = (torch.as_tensor(bound, dtype=torch.float32) for bound in (action_space.low, action_space.high))
        self.register_buffer("action_scale", (high - low) / 2.0)
        self.register_buffer("action_bias", (high + low) / 2.0)
        self.register_buffer("action_low", low)
        self.register_buffer("action_high", high)

    def forward(self, x):
        x = F.relu(self.fc1(x))
        x = F.relu(self.fc2(x))
        mean = self.fc_mean(x)
        log_std = torch.tanh(self.fc_logstd(x))
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (log_std + 1)  # From SpinUp / Denis Yarats
        return mean, log_std

    def get_action(self, x):
        """A sampled action, its log-probability (summed over dimensions) and the deterministic action."""
        mean, log_std = self(x)
        normal = torch.distributions.Normal(mean, log_std.exp(), validate_args=False)  # validation syncs with the host
        x_t = normal.rsample()  # for reparameterization trick (mean + std * N(0,1))
        y_t = torch.tanh(x_t)
        action = y_t * self.action_scale + self.action_bias
        # change of variables through the squashing, a = scale * tanh(x) + bias; 1e-6 keeps the log finite
        log_prob = (normal.log_prob(x_t) - torch.log(self.action_scale * (1 - y_t.pow(2)) + 1e-6)).sum(-1)
        return action, log_prob, torch.tanh(mean) * self.action_scale + self.action_bias


class Batch(NamedTuple):
    observations: torch.Tensor
    actions: torch.Tensor
    next_observations: torch.Tensor
    rewards: torch.Tensor
    terminations: torch.Tensor


class ReplayBuffer:
    """Transitions in one preallocated [capacity, fields] tensor: one row per add, one gather per batch."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, device: torch.device):
        self.capacity, self.pos, self.size = capacity, 0, 0
        self.widths = [obs_dim, action_dim, obs_dim, 1, 1]  # the fields of `Batch`, in order
        self.storage = torch.zeros((capacity, sum(self.widths)), dtype=torch.float32, device=device)

    def add(self, obs, action, next_obs, reward, termination):
        row = np.concatenate([obs, action, next_obs, [reward, termination]], dtype=np.float32)
        self.storage[self.pos] = torch.from_numpy(row)
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, *shape: int) -> Batch:
        """Transitions drawn uniformly with replacement, as a batch of this shape: `sample(256)` is one
        batch of 256, `sample(20, 256)` twenty of them stacked (each field [20, 256, width])."""
        indices = torch.randint(self.size, shape, device=self.storage.device)
        obs, actions, next_obs, rewards, terminations = self.storage[indices].split(self.widths, dim=-1)
        return Batch(obs, actions, next_obs, rewards.squeeze(-1), terminations.squeeze(-1))

    def state_dict(self) -> dict:
        return {"rows": self.storage[: self.size].cpu().clone(), "pos": self.pos}

    def load_state_dict(self, state: dict):
        self.storage[: len(state["rows"])] = state["rows"].to(self.storage.device)
        self.size, self.pos = len(state["rows"]), state["pos"]


@torch.no_grad()
def noisy_action(obs, actor: Actor) -> torch.Tensor:
    """An action sampled from the policy: SAC explores with the policy's own randomness."""
    return actor.get_action(torch.as_tensor(obs, device=actor.action_scale.device))[0]


def td_target(batch: Batch, actor: Actor, qf_target: QEnsemble, alpha: torch.Tensor, args: Args):
    """y = r + gamma * (1 - terminated) * (min_{i in M} Q'_i(s', a') - alpha * log pi(a'|s')), a' ~ pi(.|s'),
    with M a random subset of num_min of the num_q target critics, drawn anew for every update."""
    with torch.no_grad():
        next_actions, next_log_pi, _ = actor.get_action(batch.next_observations)
        subset = torch.randperm(args.num_q, device=next_actions.device)[: args.num_min]
        min_qf_next_target = qf_target(batch.next_observations, next_actions, subset).min(0).values - alpha * next_log_pi
        return batch.rewards + (1 - batch.terminations) * args.gamma * min_qf_next_target


def update_critic(batch: Batch, qf: QEnsemble, q_optimizer, actor: Actor, qf_target: QEnsemble, alpha, args: Args):
    next_q_value = td_target(batch, actor, qf_target, alpha, args)
    qf_a_values = qf(batch.observations, batch.actions)
    qf_loss = ((qf_a_values - next_q_value) ** 2).mean(1).sum()  # the sum of each critic's MSE
    check_finite(qf_loss, "qf_loss")
    q_optimizer.zero_grad()
    qf_loss.backward()
    q_optimizer.step()
    return qf_loss.detach(), qf_a_values.detach()


def update_actor(batch: Batch, actor: Actor, actor_optimizer, qf: QEnsemble, alpha: torch.Tensor):
    # maximise the mean over all critics of Q_i(s, a) + alpha * entropy; the critics' weights get no gradient
    pi, log_pi, _ = actor.get_action(batch.observations)
    actor_loss = (alpha * log_pi - qf(batch.observations, pi, detach_params=True).mean(0)).mean()
    check_finite(actor_loss, "actor_loss")
    actor_optimizer.zero_grad()
    actor_loss.backward()
    actor_optimizer.step()
    return actor_loss.detach()


def update_alpha(batch: Batch, actor: Actor, log_alpha: torch.Tensor, a_optimizer, target_entropy: float):
    """Moves alpha up when the policy's entropy is below the target, down when above."""
    with torch.no_grad():
        _, log_pi, _ = actor.get_action(batch.observations)
    alpha_loss = (-log_alpha.exp() * (log_pi + target_entropy)).mean()
    check_finite(alpha_loss, "alpha_loss")
    a_optimizer.zero_grad()
    alpha_loss.backward()
    a_optimizer.step()
    return alpha_loss.detach()


@torch.no_grad()
def soft_update(targets: list, sources: list, tau: float):
    """target <- tau * source + (1 - tau) * target for every parameter, in one fused call."""
    target_params = [p for net in targets for p in net.parameters()]
    source_params = [p for net in sources for p in net.parameters()]
    torch._foreach_lerp_(target_params, source_params, tau)


@torch.no_grad()
def evaluate(actor: Actor, env: gym.Env, num_episodes: int, seed: int) -> np.ndarray:
    """Undiscounted returns of `num_episodes` episodes of the noiseless actor. The env is re-seeded
    each time, so every evaluation sees the same start states."""
    device = actor.action_scale.device
    returns = np.zeros(num_episodes)
    obs, _ = env.reset(seed=seed)
    for episode in range(num_episodes):
        if episode > 0:
            obs, _ = env.reset()
        done = False
        while not done:
            action = actor.get_action(torch.as_tensor(obs, device=device))[2].cpu().numpy()
            obs, reward, terminated, truncated, _ = env.step(action)
            returns[episode] += reward
            done = terminated or truncated
    return returns


def main(args: Args):
    checkpoint = load_checkpoint(args.resume) if args.resume else None
    default_name = f"{args.env_id.replace('/', '-')}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_dir = os.path.normpath(args.resume) if args.resume else os.path.join("runs", args.run_name or default_name)
    run_name = os.path.basename(run_dir)
    if checkpoint and checkpoint["global_step"] >= args.total_timesteps:
        print(f"{run_dir} had already finished its {args.total_timesteps} steps")
        return {"run_dir": run_dir, "eval_returns": checkpoint["eval_returns"]}

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic

    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    if not args.capture_video:  # nothing renders: spare dm_control its probe for a display (and its warning)
        os.environ.setdefault("MUJOCO_GL", "disable")

    # env setup: the evaluation env is seeded apart from the training env
    env = make_env(args.env_id, args.seed)
    eval_seed = args.seed + 100
    video_folder = f"videos/{run_name}" if args.capture_video else None
    eval_env = make_env(args.env_id, eval_seed, video_folder, video_every=args.eval_episodes)
    obs_dim = int(np.prod(env.observation_space.shape))
    action_dim = int(np.prod(env.action_space.shape))

    actor = Actor(obs_dim, env.action_space).to(device)
    qf = QEnsemble(obs_dim, action_dim, num_q=args.num_q).to(device)
    qf_target = QEnsemble(obs_dim, action_dim, num_q=args.num_q).to(device)
    qf_target.load_state_dict(qf.state_dict())
    # fused Adam; capturable, so that --cudagraphs can record the optimizer step in its graph
    adam = functools.partial(optim.Adam, fused=True, capturable=args.cudagraphs)
    q_optimizer = adam(qf.parameters(), lr=args.q_lr)
    actor_optimizer = adam(actor.parameters(), lr=args.policy_lr)

    # Automatic entropy tuning
    target_entropy = args.target_entropy
    if target_entropy is None:  # REDQ's release's value on its tasks, -|A| (as SAC) on the others
        target_entropy = RELEASE_TARGET_ENTROPY.get(args.env_id, -float(action_dim))
    log_alpha = torch.zeros(1, requires_grad=True, device=device)  # alpha starts at 1, as in CleanRL
    a_optimizer = adam([log_alpha], lr=args.q_lr)
    alpha = log_alpha.detach().exp() if args.autotune else torch.tensor(args.alpha, device=device)

    rb = ReplayBuffer(min(args.buffer_size, args.total_timesteps), obs_dim, action_dim, device)

    def update(batches: Batch) -> dict:
        """One environment step's training: G critic updates, each on its own batch of `batches` and followed by
        a target update, then the actor and alpha. Returns what gets logged, by TensorBoard tag."""
        with bf16_autocast(device, args.bf16):
            for i in range(args.utd_ratio):  # G critic updates per environment step
                batch = Batch(*(field[i] for field in batches))
                qf_loss, qf_a_values = update_critic(batch, qf, q_optimizer, actor, qf_target, alpha, args)
                soft_update([qf_target], [qf], args.tau)
            # one actor (and alpha) update per environment step, on the last critic batch, as REDQ's code
            actor_loss = update_actor(batch, actor, actor_optimizer, qf, alpha)
            if args.autotune:
                alpha_loss = update_alpha(batch, actor, log_alpha, a_optimizer, target_entropy)
                alpha.copy_(log_alpha.detach().exp())  # in place: a graph reads alpha where it was
        logs = {"losses/qf_values": qf_a_values.mean(), "losses/qf_loss": qf_loss / len(qf_a_values)}  # per critic, as CleanRL
        logs["losses/actor_loss"], logs["losses/alpha"] = actor_loss, alpha
        if args.autotune:
            logs["losses/alpha_loss"] = alpha_loss
        return logs

    update = CudaGraph(update) if args.cudagraphs else update  # all G + 1 updates of a step in one graph

    nets = {"actor": actor, "qf": qf, "qf_target": qf_target}
    optimizers = {"q_optimizer": q_optimizer, "actor_optimizer": actor_optimizer, "a_optimizer": a_optimizer}
    parts = {"buffer": rb}  # with the networks and optimizers, what a checkpoint holds
    start_step, eval_returns = 0, []  # eval_returns: (step, mean return) of every evaluation
    if checkpoint:
        restore(checkpoint, env, nets, optimizers, **parts)
        start_step, eval_returns = checkpoint["global_step"], checkpoint["eval_returns"]
        with torch.no_grad():
            log_alpha.copy_(checkpoint["log_alpha"])
        if args.autotune:
            alpha.copy_(log_alpha.detach().exp())

    def state(step: int) -> dict:  # a checkpoint
        return snapshot(
            args, env, step, nets, optimizers, **parts, eval_returns=eval_returns, log_alpha=log_alpha.detach().cpu()
        )

    writer, pbar = start_logging(args, run_name, run_dir, start_step, device)
    sps_time, sps_step, sps = time.time(), start_step, 0.0
    next_checkpoint = start_step + args.checkpoint_frequency

    def run_evaluation(step: int):
        returns = evaluate(actor, eval_env, args.eval_episodes, eval_seed)
        eval_returns.append((step, float(returns.mean())))
        writer.add_scalar("eval/episodic_return", returns.mean(), step)
        pbar.set_postfix(eval_return=f"{returns.mean():.1f}")
        tqdm.write(f"step {step}: return {returns.mean():.1f} +- {returns.std():.1f}, {sps:.0f} steps/s")

    obs = None  # None: an episode starts at this step
    for global_step in range(start_step, args.total_timesteps):
        if global_step % args.eval_frequency == 0:
            run_evaluation(global_step)
            sps_time = time.time()
        if obs is None:
            obs, _ = env.reset(seed=args.seed if global_step == 0 else None)

        # ALGO LOGIC: put action logic here
        if global_step < args.learning_starts:
            actions = env.action_space.sample()
        else:
            actions = noisy_action(obs, actor).cpu().numpy()

        # execute the game and log data; a time-limit truncation is stored as not terminated, so its target bootstraps
        next_obs, reward, terminated, truncated, info = env.step(actions)
        rb.add(obs, actions, next_obs, reward, terminated)
        obs = next_obs
        if terminated or truncated:
            writer.add_scalar("charts/episodic_return", info["episode"]["r"], global_step)
            writer.add_scalar("charts/episodic_length", info["episode"]["l"], global_step)
            obs = None

        # ALGO LOGIC: training.
        if global_step >= args.learning_starts:
            batches = rb.sample(args.utd_ratio, args.batch_size)
            try:
                logs = update(batches)
                if global_step % 100 == 0:
                    log_scalars(writer, logs, global_step)
            except NonFiniteError as quantity:
                stop_non_finite(quantity, global_step, run_dir, args.cudagraphs, lambda: state(global_step))

        if (global_step + 1) % 1000 == 0:  # training speed, evaluation time excluded
            sps = (global_step + 1 - sps_step) / (time.time() - sps_time)
            writer.add_scalar("charts/SPS", sps, global_step)
            sps_time, sps_step = time.time(), global_step + 1
        pbar.update(1)
        if args.checkpoint_frequency and obs is None and global_step + 1 >= next_checkpoint:
            write_checkpoint(os.path.join(run_dir, CHECKPOINT), state(global_step + 1))
            next_checkpoint = global_step + 1 + args.checkpoint_frequency

    run_evaluation(args.total_timesteps)
    if args.checkpoint_frequency:
        write_checkpoint(os.path.join(run_dir, CHECKPOINT), state(args.total_timesteps))
    pbar.close()
    if args.save_model:
        model_path = os.path.join(run_dir, f"{args.exp_name}.cleanrl_model")
        torch.save({"actor": actor.state_dict(), "qf": qf.state_dict(), "log_alpha": log_alpha.detach().cpu()}, model_path)
        tqdm.write(f"model saved to {model_path}")
    env.close()
    eval_env.close()
    writer.close()
    return {**nets, **optimizers, "rb": rb, "run_dir": run_dir, "eval_returns": eval_returns, "alpha": alpha.item()}


# --------------------------------------------------------------------------------------------------
# Machinery. Nothing below changes what the algorithm computes: the command line and its checks, the
# environment layer, logging, the NaN guard, --cudagraphs, and the checkpoints behind exact resume.


def fail(message: str):
    """Stop with one line on stderr and exit status 1, no traceback."""
    raise SystemExit("error: " + " ".join(message.split()))


def parse_args(argv=None) -> Args:
    """The command line as checked Args. With --resume the run's own flags are the defaults, and a flag
    given now may differ from the run's only if it does not change what is learned."""
    args = tyro.cli(Args, args=argv)
    if args.resume:
        run_args = load_checkpoint(args.resume)["args"]
        args = tyro.cli(Args, args=argv, default=Args(**run_args))
        differing = [k for k, v in run_args.items() if k not in RESUMABLE_FLAGS and getattr(args, k) != v]
        if differing:
            flags = ", ".join(f"--{k.replace('_', '-')} {getattr(args, k)} (run: {run_args[k]})" for k in differing)
            fail(f"--resume {args.resume}: {flags}; a resumed run keeps its hyperparameters")
    check_args(args)
    return args


def check_args(args: Args):
    checks = [
        (args.total_timesteps > 0, f"--total-timesteps must be > 0, got {args.total_timesteps}"),
        (args.buffer_size > 0, f"--buffer-size must be > 0, got {args.buffer_size}"),
        (args.batch_size > 0, f"--batch-size must be > 0, got {args.batch_size}"),
        (
            args.learning_starts >= args.batch_size,
            f"--learning-starts ({args.learning_starts}) must be >= --batch-size ({args.batch_size})",
        ),
        (args.policy_lr > 0, f"--policy-lr must be > 0, got {args.policy_lr}"),
        (args.q_lr > 0, f"--q-lr must be > 0, got {args.q_lr}"),
        (0 <= args.gamma <= 1, f"--gamma must be in [0, 1], got {args.gamma}"),
        (0 < args.tau <= 1, f"--tau must be in (0, 1], got {args.tau}"),
        (args.alpha >= 0, f"--alpha must be >= 0, got {args.alpha}"),
        (args.num_q >= 1, f"--num-q must be >= 1, got {args.num_q}"),
        (1 <= args.num_min <= args.num_q, f"--num-min must be in [1, --num-q ({args.num_q})], got {args.num_min}"),
        (args.utd_ratio >= 1, f"--utd-ratio must be >= 1, got {args.utd_ratio}"),
        (args.eval_frequency > 0, f"--eval-frequency must be > 0, got {args.eval_frequency}"),
        (args.eval_episodes > 0, f"--eval-episodes must be > 0, got {args.eval_episodes}"),
        (args.checkpoint_frequency >= 0, f"--checkpoint-frequency must be >= 0, got {args.checkpoint_frequency}"),
    ]
    for ok, message in checks:
        if not ok:
            fail(message)
    if args.cudagraphs and not (args.cuda and torch.cuda.is_available()):
        reason = " and drops --no-cuda" if torch.cuda.is_available() else "; torch finds none here"
        fail("--cudagraphs needs a CUDA GPU" + reason)


def float32_box(space: gym.spaces.Box) -> gym.spaces.Box:
    return gym.spaces.Box(space.low.astype(np.float32), space.high.astype(np.float32), dtype=np.float32)


def make_env(env_id: str, seed: int, video_folder: Optional[str] = None, video_every: int = 1):
    """One environment with a flat float32 observation and a float32 Box action space.

    A plain (not vectorised) env: the loop sees the true final observation of every episode and
    resets itself, so no autoreset step can end up in the replay buffer."""
    if env_id.startswith("dm_control/"):
        import shimmy  # registers the DeepMind Control tasks as dm_control/<domain>-<task>-v0

        gym.register_envs(shimmy)
    if env_id not in gym.registry:
        close = difflib.get_close_matches(env_id, list(gym.registry), n=3, cutoff=0.6)
        hint = f"did you mean {', '.join(close)}?" if close else "use e.g. Hopper-v4 or dm_control/cartpole-swingup-v0"
        fail(f"unknown --env-id {env_id!r}; {hint}")
    try:
        env = gym.make(env_id, render_mode="rgb_array" if video_folder else None)
    except Exception as e:  # a registered id whose dependencies are missing, e.g. Hopper-v3 (mujoco-py)
        fail(f"could not create --env-id {env_id!r}: {type(e).__name__}: {e}")
    if not isinstance(env.action_space, gym.spaces.Box):
        space = type(env.action_space).__name__
        fail(f"--env-id {env_id!r} has a {space} action space; only continuous (Box) actions are supported")
    if not (np.isfinite(env.action_space.low).all() and np.isfinite(env.action_space.high).all()):
        fail(f"--env-id {env_id!r} has unbounded actions; the policies here act within finite bounds")
    if isinstance(env.observation_space, gym.spaces.Dict):  # DeepMind Control observations are dicts of arrays
        env = gym.wrappers.FlattenObservation(env)
    env = gym.wrappers.TransformObservation(env, lambda obs: obs.astype(np.float32), float32_box(env.observation_space))
    if env.action_space.dtype != np.float32:  # DeepMind Control declares float64 actions
        to_env_dtype = lambda action, dtype=env.action_space.dtype: np.asarray(action, dtype=dtype)  # noqa: E731
        env = gym.wrappers.TransformAction(env, to_env_dtype, float32_box(env.action_space))
    env = gym.wrappers.RecordEpisodeStatistics(env)
    if video_folder:
        env = gym.wrappers.RecordVideo(env, video_folder, episode_trigger=lambda episode: episode % video_every == 0)
    env.action_space.seed(seed)
    return env


def start_logging(args: Args, run_name: str, run_dir: str, start_step: int, device: torch.device):
    """TensorBoard (a resumed run hides what the killed process logged after its checkpoint), Weights and
    Biases with --track, and a progress bar on a terminal (in a log file the per-evaluation lines say the same)."""
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
            name=run_name,
            monitor_gym=True,
            save_code=True,
        )
    writer = SummaryWriter(run_dir, purge_step=start_step if args.resume else None)
    if not args.resume:
        writer.add_text(
            "hyperparameters",
            "|param|value|\n|-|-|\n%s" % ("\n".join([f"|{key}|{value}|" for key, value in vars(args).items()])),
        )
    pbar = tqdm(total=args.total_timesteps, initial=start_step, unit="step", disable=not sys.stderr.isatty())
    resumed = f", resumed at step {start_step}" if args.resume else ""
    tqdm.write(f"{run_name}: {args.env_id} on {device}, logging to {run_dir}{resumed}")
    return writer, pbar


def bf16_autocast(device: torch.device, enabled: bool):
    """--bf16: the matmuls of one training step in bfloat16. Autocast's cache of cast weights is off:
    an optimizer updates weights in place within the step, and a cached cast would keep the old values."""
    return torch.autocast(device.type, torch.bfloat16, enabled=enabled, cache_enabled=False)


class NonFiniteError(Exception):
    """A loss became NaN or infinite; raised before the optimizer step it would have poisoned."""


def check_finite(value: torch.Tensor, name: str):
    # a graph cannot stop on a value: under --cudagraphs the loop checks what it logs
    if value.is_cuda and torch.cuda.is_current_stream_capturing():
        return
    if not torch.isfinite(value):
        raise NonFiniteError(name)


def log_scalars(writer: SummaryWriter, logs: dict, step: int):
    """Writes {tag: scalar tensor}; a non-finite value stops the run (where --cudagraphs catches a NaN)."""
    values = {tag: value.item() for tag, value in logs.items()}
    for tag, value in values.items():
        if not math.isfinite(value):
            raise NonFiniteError(tag.split("/")[-1])
    for tag, value in values.items():
        writer.add_scalar(tag, value, step)


def stop_non_finite(quantity: NonFiniteError, step: int, run_dir: str, cudagraphs: bool, last_good_state):
    """Ends the run on a non-finite loss. An eager update stops before the optimizer step that the loss would
    have poisoned, so the state is still finite and is saved; a recorded graph is checked only when it logs."""
    if cudagraphs:
        fail(
            f"{quantity} became non-finite by step {step} (--cudagraphs checks every 100 steps and keeps no last finite "
            "state; without it a run stops at the first bad update)"
        )
    path = os.path.join(run_dir, "last_good_state.pt")
    write_checkpoint(path, last_good_state())
    rates = [f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(Args) if f.name.endswith(("lr", "learning_rate"))]
    fail(
        f"{quantity} became non-finite at step {step} (try a smaller {' or '.join(rates)}); the last finite state is in {path}"
    )


class CudaGraph:
    """--cudagraphs: `update = CudaGraph(update)` runs `update(batch, policy_step)` as a CUDA graph, one graph
    per value of the arguments that are not tensors. The first `warmup` calls of each run eagerly on a side
    stream (they allocate the gradients and optimizer states the graph will reuse), the next one records the
    graph, and from then on a call copies its tensors (a tensor, or a NamedTuple of them such as a Batch) into
    the graph's own inputs and replays it: one launch instead of hundreds of small kernels, with no host
    synchronisation. What it returns is overwritten by its next replay."""

    def __init__(self, fn, warmup: int = 3):
        self.fn, self.warmup = fn, warmup
        self.calls, self.graphs, self.inputs, self.outputs = {}, {}, {}, {}

    @staticmethod
    def key(*inputs) -> tuple:
        return tuple(x for x in inputs if not isinstance(x, (torch.Tensor, tuple)))

    @staticmethod
    def clone(x):  # a tensor, or a NamedTuple of them, copied; anything else as it is
        if isinstance(x, torch.Tensor):
            return x.clone()
        return type(x)(*map(torch.clone, x)) if isinstance(x, tuple) else x

    @staticmethod
    def tensors(inputs) -> list:
        return [t for x in inputs for t in ([x] if isinstance(x, torch.Tensor) else x if isinstance(x, tuple) else [])]

    def __call__(self, *inputs):
        key = self.key(*inputs)
        if key in self.graphs:
            for static, new in zip(self.tensors(self.inputs[key]), self.tensors(inputs)):
                static.copy_(new)
        else:
            self.calls[key] = self.calls.get(key, 0) + 1
            if self.calls[key] <= self.warmup:
                stream = torch.cuda.Stream()
                stream.wait_stream(torch.cuda.current_stream())
                with torch.cuda.stream(stream):
                    outputs = self.fn(*inputs)
                torch.cuda.current_stream().wait_stream(stream)
                return outputs
            self.inputs[key] = [self.clone(x) for x in inputs]
            self.graphs[key] = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graphs[key]):  # records the kernels without running them
                self.outputs[key] = self.fn(*self.inputs[key])
        self.graphs[key].replay()
        return self.outputs[key]


# Checkpoints: everything needed to continue a run exactly. They are taken at episode boundaries,
# where an environment holds no state but its random generators, so any env can be resumed.
CHECKPOINT = "checkpoint.pt"
# flags that may differ between a run and its resumption: they don't change what is learned
RESUMABLE_FLAGS = {"resume", "run_name", "checkpoint_frequency", "track", "wandb_project_name", "wandb_entity"}
RESUMABLE_FLAGS |= {"capture_video", "save_model", "cuda", "cudagraphs"}


def snapshot(args: Args, env: gym.Env, global_step: int, nets: dict, optimizers: dict, **parts) -> dict:
    """A run's state at `global_step`: its flags, networks, optimizers and random generators, and `parts`
    (objects with a state_dict(), such as the replay buffer, or plain values such as the evaluations)."""
    return {
        "script": os.path.basename(__file__),
        "args": vars(args),
        "global_step": global_step,
        "nets": {name: net.state_dict() for name, net in nets.items()},
        "optimizers": {name: opt.state_dict() for name, opt in optimizers.items()},
        **{name: part.state_dict() if hasattr(part, "state_dict") else part for name, part in parts.items()},
        "rng": {
            "python": random.getstate(),
            "numpy": rng_state(np.random.mtrand._rand),
            "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else [],
            "action_space": rng_state(env.action_space.np_random),
            "env": rng_state(env.unwrapped.np_random),
        },
    }


def restore(checkpoint: dict, env: gym.Env, nets: dict, optimizers: dict, **parts):
    """Loads a snapshot() into the objects it was taken of (its plain values are the caller's to read)."""
    for name, net in nets.items():
        net.load_state_dict(checkpoint["nets"][name])
    for name, opt in optimizers.items():
        state = checkpoint["optimizers"][name]
        for group, current in zip(state["param_groups"], opt.param_groups):  # --cudagraphs may differ from the run's
            group["capturable"] = current["capturable"]
        opt.load_state_dict(state)
    for name, part in parts.items():
        part.load_state_dict(checkpoint[name])
    rng = checkpoint["rng"]
    random.setstate(rng["python"])
    set_rng_state(np.random.mtrand._rand, rng["numpy"])
    torch.set_rng_state(rng["torch"])
    if rng["cuda"]:
        torch.cuda.set_rng_state_all(rng["cuda"])
    set_rng_state(env.action_space.np_random, rng["action_space"])
    set_rng_state(env.unwrapped.np_random, rng["env"])


def rng_state(rng) -> dict:
    """A numpy Generator's or RandomState's (dm_control's) state, in types `weights_only` loading accepts."""
    if isinstance(rng, np.random.RandomState):
        name, key, pos, has_gauss, gauss = rng.get_state()
        return {"legacy": (name, torch.from_numpy(key.astype(np.int64)), pos, has_gauss, gauss)}
    return {"generator": rng.bit_generator.state}


def set_rng_state(rng, state: dict):
    if "legacy" in state:
        name, key, pos, has_gauss, gauss = state["legacy"]
        rng.set_state((name, key.numpy().astype(np.uint32), pos, has_gauss, gauss))
    else:
        rng.bit_generator.state = state["generator"]


def write_checkpoint(path: str, state: dict):
    """Write atomically: a kill during the write leaves the previous file intact."""
    torch.save(state, path + ".tmp")
    os.replace(path + ".tmp", path)


def load_checkpoint(run_dir: str) -> dict:
    path = os.path.join(run_dir, CHECKPOINT)
    if not os.path.isdir(run_dir):
        fail(f"--resume {run_dir}: no such run folder")
    if not os.path.isfile(path):
        fail(f"--resume {run_dir}: it holds no {CHECKPOINT} (write one with --checkpoint-frequency N)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as e:  # truncated, foreign or corrupt files all land here
        fail(f"{path} is not a readable checkpoint ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'no detail'})")
    script = os.path.basename(__file__)
    if not isinstance(checkpoint, dict) or checkpoint.get("script") != script:
        found = checkpoint.get("script") if isinstance(checkpoint, dict) else None
        fail(f"{path} was not written by {script} (written by {found or 'something else'})")
    return checkpoint


if __name__ == "__main__":
    main(parse_args())
