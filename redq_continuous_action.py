# REDQ (Chen et al. 2021, "Randomized Ensembled Double Q-Learning", https://arxiv.org/abs/2101.05982),
# a baseline of the OPARL paper, as a copy of sac_continuous_action.py: `diff sac_continuous_action.py
# redq_continuous_action.py` shows what REDQ changes: an ensemble of 10 critics, a target that takes
# the min over a random subset of 2 of them, 20 critic updates per environment step, and an actor
# trained on the mean of all critics. At that update-to-data ratio a step costs ~40 SAC steps (docs/speed.md).
# The machinery (checks, envs, logging, checkpoints, --num-seeds, --cudagraphs) is imported from rl_utils.
import functools
import os
import random
from dataclasses import dataclass
from typing import Optional

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import torch.optim as optim

from rl_utils import Batch, CudaGraph, ReplayBuffer, Run, SeedEnvs, bf16_autocast, check_finite, evaluate, frozen
from rl_utils import at_least, parse_args, per_seed, positive, stack_seeds, to_device, within


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
    """the run folder under runs/, {seed} where the seed goes (default: {env_id}__{exp_name}__{seed}__{unix time})"""
    num_seeds: int = 1
    """train seeds seed, ..., seed+num_seeds-1 side by side in this process, each in its own run folder (docs/usage.md)"""
    checkpoint_frequency: int = 0
    """write `checkpoint.pt` into each run folder every this many steps, and at the end (0: never)"""
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
    """record each kind of training update once as a CUDA graph and replay it (a CUDA GPU; NaN checks every 100 steps)"""


# ALGO LOGIC: initialize agent here:
class SoftQNetwork(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int):
        super().__init__()
        self.fc1 = nn.Linear(obs_dim + action_dim, 256)
        self.fc2 = nn.Linear(256, 256)
        self.fc3 = nn.Linear(256, 1)

    def forward(self, x, a):
        x = torch.cat([x, a], -1)
        x = F.relu(self.fc1(x))
        x = F.relu(self.fc2(x))
        return self.fc3(x).squeeze(-1)


class QEnsemble(nn.ModuleList):
    """num_q independent SoftQNetworks (REDQ's ensemble: 10); called, every critic's Q-values [num_q, batch]."""

    def __init__(self, obs_dim: int, action_dim: int, num_q: int = 10):
        super().__init__(SoftQNetwork(obs_dim, action_dim) for _ in range(num_q))

    def forward(self, obs, actions):
        return torch.stack([qf(obs, actions) for qf in self])


# REDQ's release (redq/algos/core.py, from MBPO) steers alpha towards these entropies on its MuJoCo tasks
RELEASE_TARGET_ENTROPY = {"Hopper-v4": -1.0, "HalfCheetah-v4": -3.0, "Walker2d-v4": -3.0, "Ant-v4": -4.0, "Humanoid-v4": -2.0}
LOG_STD_MAX = 2
LOG_STD_MIN = -5


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
        std = log_std.exp()
        normal = torch.distributions.Normal(mean, std, validate_args=False)  # validation syncs with the host
        x_t = mean + torch.randn_like(mean) * std  # for reparameterization trick (mean + std * N(0,1))
        y_t = torch.tanh(x_t)
        action = y_t * self.action_scale + self.action_bias
        # change of variables through the squashing, a = scale * tanh(x) + bias; 1e-6 keeps the log finite
        log_prob = (normal.log_prob(x_t) - torch.log(self.action_scale * (1 - y_t.pow(2)) + 1e-6)).sum(-1)
        return action, log_prob, torch.tanh(mean) * self.action_scale + self.action_bias

    def sampled_action(self, x):
        """get_action's sampled action alone, from the same draws: what acting takes, without the log-probability and
        deterministic action it would discard (on a GPU each of their kernels is one more launch in every step)."""
        mean, log_std = self(x)
        return torch.tanh(mean + torch.randn_like(mean) * log_std.exp()) * self.action_scale + self.action_bias

    def deterministic_action(self, x):
        """The squashed mean action (what get_action returns last), without drawing noise: what evaluations take."""
        mean, _ = self(x)
        return torch.tanh(mean) * self.action_scale + self.action_bias


@torch.no_grad()
def noisy_action(obs, actor: Actor) -> torch.Tensor:
    """An action sampled from the policy: SAC explores with the policy's own randomness."""
    return actor.sampled_action(obs)


def td_target(batch: Batch, actor: Actor, qf_target: QEnsemble, alpha: torch.Tensor, args: Args):
    """y = r + gamma * (1 - terminated) * (min_{i in M} Q'_i(s', a') - alpha * log pi(a'|s')), a' ~ pi(.|s'),
    with M a random subset of num_min of the num_q target critics, drawn anew for every update."""
    with torch.no_grad():
        next_actions, next_log_pi, _ = actor.get_action(batch.next_observations)
        # a tensor (--cudagraphs draws anew at each replay), and under per_seed each seed's own
        subset = torch.randperm(args.num_q, device=next_actions.device)[: args.num_min]
        q_next = qf_target(batch.next_observations, next_actions)[subset]  # every critic's, the subset's kept
        min_qf_next_target = q_next.min(0).values - alpha * next_log_pi
        return batch.rewards + (1 - batch.terminations) * args.gamma * min_qf_next_target


def critic_loss(batch: Batch, qf: QEnsemble, actor: Actor, qf_target: QEnsemble, alpha: torch.Tensor, args: Args):
    """The sum of each critic's mean squared error against the TD target, and the Q-values."""
    qf_a_values = qf(batch.observations, batch.actions)
    qf_loss = ((qf_a_values - td_target(batch, actor, qf_target, alpha, args)) ** 2).mean(-1).sum()
    return qf_loss, qf_a_values.detach()


def policy_loss(batch: Batch, actor: Actor, qf: QEnsemble, alpha: torch.Tensor):
    # maximise the mean over all critics of Q_i(s, a) + alpha * entropy
    pi, log_pi, _ = actor.get_action(batch.observations)
    return (alpha * log_pi - qf(batch.observations, pi).mean(0)).mean()


def alpha_loss_fn(batch: Batch, actor: Actor, log_alpha: torch.Tensor, target_entropy: float):
    """Moves alpha up when the policy's entropy is below the target, down when above."""
    with torch.no_grad():
        _, log_pi, _ = actor.get_action(batch.observations)
    return (-log_alpha.exp() * (log_pi + target_entropy)).mean()


@torch.no_grad()
def soft_update(targets: list, sources: list, tau: float):
    """target <- tau * source + (1 - tau) * target for every parameter, in one fused call."""
    target_params = [p for net in targets for p in net.parameters()]
    source_params = [p for net in sources for p in net.parameters()]
    torch._foreach_lerp_(target_params, source_params, tau)


def optimize(loss: torch.Tensor, name: str, *optimizers):
    """One step of the optimizers on the loss (one per seed: their sum, so each seed's weights get their own gradient)."""
    check_finite(loss, name)
    for optimizer in optimizers:
        optimizer.zero_grad()
    loss.sum().backward()
    for optimizer in optimizers:
        optimizer.step()


def check_args(args: Args) -> list:
    """The flags' valid values, as (holds, message) pairs: parse_args refuses a run that breaks one."""
    return [
        *positive(args, "policy_lr", "q_lr", "buffer_size", "batch_size", "eval_frequency", "eval_episodes"),
        *at_least(args, 0, "alpha", "learning_starts"),
        *within(args, "[0, 1]", "gamma"),
        *within(args, "(0, 1]", "tau"),
        (
            args.learning_starts >= args.batch_size,
            f"--learning-starts ({args.learning_starts}) must be >= --batch-size ({args.batch_size})",
        ),
        *at_least(args, 1, "num_q", "utd_ratio"),
        (1 <= args.num_min <= args.num_q, f"--num-min must be in [1, --num-q ({args.num_q})], got {args.num_min}"),
    ]


def main(args: Args):
    run = Run(args)  # the run folders, one per seed; with --resume, the checkpoints it continues from
    if run.finished:
        return run.results()

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    # env setup: one env per seed; the evaluation envs are seeded apart from the training envs
    envs = SeedEnvs(args.env_id, run.seeds)
    eval_seeds = [seed + 100 for seed in run.seeds]
    eval_envs = SeedEnvs(args.env_id, eval_seeds, run.video_folders, video_every=args.eval_episodes)
    obs_dim, action_dim = envs.obs_dim, envs.action_dim

    def networks():  # one seed's
        actor = Actor(obs_dim, envs.action_space)
        qf = QEnsemble(obs_dim, action_dim, num_q=args.num_q)
        qf_target = QEnsemble(obs_dim, action_dim, num_q=args.num_q)
        qf_target.load_state_dict(qf.state_dict())
        return actor, qf, qf_target

    actor, qf, qf_target = stack_seeds(networks, run.seeds, device)
    # fused Adam; capturable, so that --cudagraphs can record the optimizer step in its graph
    adam = functools.partial(optim.Adam, fused=True, capturable=args.cudagraphs)
    q_optimizer = adam(qf.parameters(), lr=args.q_lr)
    actor_optimizer = adam(actor.parameters(), lr=args.policy_lr)

    # Automatic entropy tuning
    target_entropy = args.target_entropy
    if target_entropy is None:  # REDQ's release's value on its tasks, -|A| (as SAC) on the others
        target_entropy = RELEASE_TARGET_ENTROPY.get(args.env_id, -float(action_dim))
    log_alpha = torch.zeros(len(run.seeds), 1, requires_grad=True, device=device)  # alpha starts at 1, as in CleanRL
    a_optimizer = adam([log_alpha], lr=args.q_lr)
    alpha = log_alpha.detach().exp() if args.autotune else torch.full((len(run.seeds), 1), args.alpha, device=device)
    rb = ReplayBuffer(min(args.buffer_size, args.total_timesteps), obs_dim, action_dim, len(run.seeds), device)

    def update(batches: Batch) -> dict:
        """One environment step's training: G critic updates, each on its own batch of `batches` and followed by
        a target update, then the actor and alpha. Returns what gets logged, by TensorBoard tag, one value per seed
        (per_seed's results carry a leading seeds dimension: losses [num_seeds], Q-values [num_seeds, num_q, batch])."""
        with bf16_autocast(device, args.bf16):
            for i in range(args.utd_ratio):  # G critic updates per environment step
                batch = Batch(*(field[:, i] for field in batches))
                qf_loss, qf_a_values = per_seed(critic_loss)(batch, qf, actor, qf_target, alpha, args)
                optimize(qf_loss, "qf_loss", q_optimizer)
                soft_update([qf_target], [qf], args.tau)
            # one actor (and alpha) update per environment step, on the last critic batch, as REDQ's code
            with frozen(qf):  # the actor's loss computes no gradient for the critics (SpinningUp's freeze)
                actor_loss = per_seed(policy_loss)(batch, actor, qf, alpha)
                optimize(actor_loss, "actor_loss", actor_optimizer)
            logs = {"losses/qf_values": qf_a_values.mean((-2, -1)), "losses/qf_loss": qf_loss.detach() / len(qf)}
            logs["losses/actor_loss"], logs["losses/alpha"] = actor_loss.detach(), alpha
            if args.autotune:
                alpha_loss = per_seed(alpha_loss_fn)(batch, actor, log_alpha, target_entropy)
                optimize(alpha_loss, "alpha_loss", a_optimizer)
                alpha.copy_(log_alpha.detach().exp())  # in place: a graph reads alpha where it was
                logs["losses/alpha_loss"] = alpha_loss.detach()
        return logs

    update = CudaGraph(update) if args.cudagraphs else update  # all G + 1 updates of a step in one graph

    @torch.no_grad()
    def policy(obs):  # the deterministic (mean) action: what the evaluations report
        return per_seed(actor.deterministic_action)(to_device(obs, device)).cpu().numpy()

    nets = {"actor": actor, "qf": qf, "qf_target": qf_target}
    optimizers = {"q_optimizer": q_optimizer, "actor_optimizer": actor_optimizer, "a_optimizer": a_optimizer}
    obs = run.start(envs, device, nets, optimizers, buffer=rb, log_alpha=log_alpha)  # restored on --resume, obs too
    obs = envs.reset() if obs is None else obs  # a fresh run: each env reset with its seed
    if args.autotune:
        alpha.copy_(log_alpha.detach().exp())  # log_alpha as restored
    for global_step in range(run.start_step, args.total_timesteps):
        if global_step % args.eval_frequency == 0:
            run.evaluate(global_step, evaluate(policy, eval_envs, eval_seeds, args.eval_episodes))

        # ALGO LOGIC: put action logic here
        if global_step < args.learning_starts:
            actions = envs.sample_actions()
        else:
            actions = per_seed(noisy_action)(to_device(obs, device), actor).cpu().numpy()

        # execute the game and log data; a time-limit truncation is stored as not terminated, so its target bootstraps
        next_obs, rewards, terminations, truncations, infos = envs.step(actions)
        rb.add(obs, infos["real_next_obs"], actions, rewards, terminations)
        obs = next_obs
        run.log_episodes(infos, global_step)

        # ALGO LOGIC: training.
        if global_step >= args.learning_starts:
            with run.stop_on_nan(global_step):
                logs = update(rb.sample(args.utd_ratio, args.batch_size))
                if global_step % 100 == 0:
                    run.log(logs, global_step)
        run.end_step(global_step)  # training speed, progress bar, checkpoints

    run.evaluate(args.total_timesteps, evaluate(policy, eval_envs, eval_seeds, args.eval_episodes))
    results = run.finish(save={"actor": actor, "qf": qf, "log_alpha": log_alpha}, eval_envs=eval_envs, policy=policy)
    return {**nets, **optimizers, "update": update, "rb": rb, "alpha": alpha, **results}


if __name__ == "__main__":
    main(parse_args(Args, check_args))
