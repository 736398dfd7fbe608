# SAC (Haarnoja et al. 2018, https://arxiv.org/abs/1812.05905) with CleanRL's defaults, in the same
# single-file shape as td3_continuous_action.py: `diff td3_continuous_action.py sac_continuous_action.py`
# shows what SAC changes. The twin critics are one batched ensemble, the reported metric is a
# deterministic evaluation (the squashed mean action) every --eval-frequency steps.
import dataclasses
import difflib
import functools
import math
import os
import random
import sys
import time
from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

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
    """name of the run folder under runs/, with {seed} where the seed's number goes (default: {env_id}__{exp_name}__{seed}__{unix time})"""
    num_seeds: int = 1
    """train seeds seed, seed+1, ..., seed+num_seeds-1 side by side in this process, each an ordinary run in its own folder"""
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
    q_lr: float = 1e-3
    """the learning rate of the Q network network optimizer (and of the entropy coefficient)"""
    policy_frequency: int = 2
    """the frequency of training policy (delayed; each time it is trained this many times)"""
    target_network_frequency: int = 1
    """the frequency of updates for the target networks"""
    alpha: float = 0.2
    """Entropy regularization coefficient (its start value is 1 when --autotune is on)"""
    autotune: bool = True
    """automatic tuning of the entropy coefficient, towards an entropy of -|A|"""

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
# Every network below holds one copy per seed (--num-seeds), stacked along a leading dimension, and takes inputs
# [num_seeds, batch, features]; nothing in a computation mixes seeds, so each seed is an independent run. Every random
# draw is per seed too: `generators` holds one torch.Generator per seed (None: the global one), and seed k draws from
# its own exactly what a single-seed run of seed k draws, whichever seeds share its process.
class QEnsemble(nn.Module):
    """`num_q` critics per seed, concat(obs, action) -> 256 -> 256 -> 1, each layer's weights stacked into one
    [num_seeds * num_q, in, out] tensor (seed after seed) so that one batched matmul evaluates every member."""

    def __init__(self, obs_dim: int, action_dim: int, num_q: int = 2, hidden: int = 256, generators: Sequence = (None,)):
        super().__init__()
        self.num_q = num_q

        def uniform(fan_in, *shape):  # the default init of nn.Linear, drawn independently per member
            p = torch.empty(len(generators), num_q, *shape)  # each seed's members from its own generator
            for members, g in zip(p, generators):
                members.uniform_(-(fan_in**-0.5), fan_in**-0.5, generator=g)
            return nn.Parameter(p.flatten(0, 1))

        in_dim = obs_dim + action_dim
        self.w1, self.b1 = uniform(in_dim, in_dim, hidden), uniform(in_dim, 1, hidden)
        self.w2, self.b2 = uniform(hidden, hidden, hidden), uniform(hidden, 1, hidden)
        self.w3, self.b3 = uniform(hidden, 1, hidden), uniform(hidden, 1)  # the output layer, as rows

    def forward(self, obs, actions, detach_params=False):
        """Q-values [num_seeds, num_q, batch] ([num_q, batch] for inputs without the seeds dimension, one seed).
        `detach_params` lets gradients reach the actions only, which is all an actor loss needs."""
        params = list(self.parameters())
        w1, b1, w2, b2, w3, b3 = [p.detach() for p in params] if detach_params else params
        x = torch.cat([obs, actions], -1)
        seeds, (batch, width) = x.shape[:-2], x.shape[-2:]
        x = x.reshape(-1, 1, batch, width).expand(-1, len(w1) // math.prod(seeds), -1, -1).reshape(len(w1), batch, width)
        x = F.relu(torch.baddbmm(b1, x, w1))
        x = F.relu(torch.baddbmm(b2, x, w2))
        return ((x * w3).sum(-1) + b3).view(*seeds, -1, batch)  # a dot product per member: cheaper than a matmul


LOG_STD_MAX = 2
LOG_STD_MIN = -5


class SeedLinear(nn.Module):
    """nn.Linear once per seed, the seeds' weights stacked: x [num_seeds, ..., in] -> [num_seeds, ..., out] in one
    batched matmul. Each seed's layer starts as an nn.Linear does."""

    def __init__(self, in_features: int, out_features: int, generators: Sequence = (None,)):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(len(generators), out_features, in_features))
        self.bias = nn.Parameter(torch.empty(len(generators), out_features))
        for weight, bias, g in zip(self.weight.data, self.bias.data, generators):
            nn.init.kaiming_uniform_(weight, a=math.sqrt(5), generator=g)
            nn.init.uniform_(bias, -1 / math.sqrt(in_features), 1 / math.sqrt(in_features), generator=g)

    def forward(self, x):
        if len(self.weight) == 1:  # nn.Linear's own kernel: one seed computes exactly what a single-seed network does
            return F.linear(x, self.weight[0], self.bias[0])
        out = torch.baddbmm(self.bias.unsqueeze(1), x.reshape(len(x), -1, x.shape[-1]), self.weight.transpose(1, 2))
        return out.view(*x.shape[:-1], -1)


class Actor(nn.Module):
    """A Gaussian policy squashed by tanh into the action bounds."""

    def __init__(self, obs_dim: int, action_space: gym.spaces.Box, generators: Sequence = (None,)):
        super().__init__()
        self.fc1 = SeedLinear(obs_dim, 256, generators)
        self.fc2 = SeedLinear(256, 256, generators)
        self.fc_mean = SeedLinear(256, int(np.prod(action_space.shape)), generators)
        self.fc_logstd = SeedLinear(256, int(np.prod(action_space.shape)), generators)
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

    def get_action(self, x, generators=None):
        """A sampled action, its log-probability (summed over dimensions) and the deterministic action; x [num_seeds, ...],
        each seed's noise drawn from its own generator."""
        mean, log_std = self(x)
        std = log_std.exp()
        normal = torch.distributions.Normal(mean, std, validate_args=False)  # validation syncs with the host
        x_t = mean + randn_like(mean, generators) * std  # for reparameterization trick (mean + std * N(0,1))
        y_t = torch.tanh(x_t)
        action = y_t * self.action_scale + self.action_bias
        # change of variables through the squashing, a = scale * tanh(x) + bias; 1e-6 keeps the log finite
        log_prob = (normal.log_prob(x_t) - torch.log(self.action_scale * (1 - y_t.pow(2)) + 1e-6)).sum(-1)
        return action, log_prob, torch.tanh(mean) * self.action_scale + self.action_bias

    def sampled_action(self, x, generators=None):
        """get_action's sampled action alone, from the same draws: what acting takes, without the log-probability and
        deterministic action it would discard (on a GPU each of their kernels is one more launch in every step)."""
        mean, log_std = self(x)
        return torch.tanh(mean + randn_like(mean, generators) * log_std.exp()) * self.action_scale + self.action_bias

    def deterministic_action(self, x):
        """The squashed mean action (what get_action returns last), without drawing noise: what evaluations take."""
        mean, _ = self(x)
        return torch.tanh(mean) * self.action_scale + self.action_bias


class Batch(NamedTuple):
    observations: torch.Tensor
    actions: torch.Tensor
    next_observations: torch.Tensor
    rewards: torch.Tensor
    terminations: torch.Tensor


class ReplayBuffer:
    """Each seed's transitions in one preallocated [num_seeds, capacity, fields] tensor: one row per seed per add, one
    gather per batch (each seed's batch drawn from its own transitions, with its own generator)."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, device: torch.device, generators: Sequence = (None,)):
        self.capacity, self.pos, self.size, self.generators = capacity, 0, 0, generators
        self.widths = [obs_dim, action_dim, obs_dim, 1, 1]  # the fields of `Batch`, in order
        self.storage = torch.zeros((len(generators), capacity, sum(self.widths)), dtype=torch.float32, device=device)

    def add(self, obs, action, next_obs, reward, termination):
        """One transition per seed: obs [num_seeds, obs_dim], ..., reward and termination [num_seeds]."""
        scalars = np.stack([reward, termination], -1)
        row = np.concatenate([obs, action, next_obs, scalars], -1, dtype=np.float32)
        self.storage[:, self.pos] = torch.from_numpy(row)
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, *shape: int) -> Batch:
        """Transitions drawn uniformly with replacement, for each seed a batch of this shape: `sample(256)` gives
        fields [num_seeds, 256, width], `sample(20, 256)` twenty batches each ([num_seeds, 20, 256, width])."""
        device = self.storage.device
        indices = torch.stack([torch.randint(self.size, shape, generator=g, device=device) for g in self.generators])
        seed = torch.arange(len(self.generators), device=device).view(-1, *[1] * len(shape))
        obs, actions, next_obs, rewards, terminations = self.storage[seed, indices].split(self.widths, dim=-1)
        return Batch(obs, actions, next_obs, rewards.squeeze(-1), terminations.squeeze(-1))

    def state_dict(self) -> dict:
        return {"rows": self.storage[:, : self.size].cpu().clone(), "pos": self.pos}

    def load_state_dict(self, state: dict):
        self.storage[:, : state["rows"].shape[1]] = state["rows"].to(self.storage.device)
        self.size, self.pos = state["rows"].shape[1], state["pos"]


def randn_like(x: torch.Tensor, generators: Optional[Sequence] = None) -> torch.Tensor:
    """torch.randn_like(x); given generators (one per seed, x [num_seeds, ...]), each seed's share drawn from its own."""
    if generators is None:
        return torch.randn_like(x)
    assert len(x) == len(generators), f"a draw for {len(generators)} seeds needs x [num_seeds, ...], got {tuple(x.shape)}"
    return torch.stack([torch.randn(x.shape[1:], generator=g, dtype=x.dtype, device=x.device) for g in generators])


@torch.no_grad()
def noisy_action(obs, actor: Actor, generators=None) -> torch.Tensor:
    """Each seed's action (obs [num_seeds, obs_dim]) sampled from its policy: SAC explores with the policy's own randomness."""
    return actor.sampled_action(to_device(obs, actor.action_scale.device), generators)


def td_target(batch: Batch, actor: Actor, qf_target: QEnsemble, alpha: torch.Tensor, args: Args, generators=None):
    """The entropy-regularised target y = r + gamma * (1 - terminated) * (min_i Q'_i(s', a') - alpha * log pi(a'|s')),
    a' ~ pi(.|s') from the current actor (SAC has no target actor)."""
    with torch.no_grad():
        next_actions, next_log_pi, _ = actor.get_action(batch.next_observations, generators)
        min_qf_next_target = qf_target(batch.next_observations, next_actions).min(-2).values - alpha * next_log_pi
        return batch.rewards + (1 - batch.terminations) * args.gamma * min_qf_next_target


def update_critic(
    batch: Batch, qf: QEnsemble, q_optimizer, actor: Actor, qf_target: QEnsemble, alpha, args: Args, generators=None
):
    next_q_value = td_target(batch, actor, qf_target, alpha, args, generators)
    qf_a_values = qf(batch.observations, batch.actions)
    qf_loss = ((qf_a_values - next_q_value.unsqueeze(-2)) ** 2).mean(-1).sum(-1)  # per seed, the sum of each critic's MSE
    check_finite(qf_loss.sum(), "qf_loss")
    q_optimizer.zero_grad()
    qf_loss.sum().backward()  # a sum over seeds: each seed's weights get their own seed's gradient, unscaled
    q_optimizer.step()
    return qf_loss.detach(), qf_a_values.detach()


def update_actor(batch: Batch, actor: Actor, actor_optimizer, qf: QEnsemble, alpha: torch.Tensor, generators=None):
    # maximise min_i Q_i(s, a) + alpha * entropy, a ~ pi(.|s) reparameterised; the critic's weights get no gradient
    pi, log_pi, _ = actor.get_action(batch.observations, generators)
    actor_loss = (alpha * log_pi - qf(batch.observations, pi, detach_params=True).min(-2).values).mean(-1)  # per seed
    check_finite(actor_loss.sum(), "actor_loss")
    actor_optimizer.zero_grad()
    actor_loss.sum().backward()
    actor_optimizer.step()
    return actor_loss.detach()


def update_alpha(batch: Batch, actor: Actor, log_alpha: torch.Tensor, a_optimizer, target_entropy: float, generators=None):
    """Moves alpha up when the policy's entropy is below the target, down when above."""
    with torch.no_grad():
        _, log_pi, _ = actor.get_action(batch.observations, generators)
    alpha_loss = (-log_alpha.exp() * (log_pi + target_entropy)).mean(-1)  # per seed
    check_finite(alpha_loss.sum(), "alpha_loss")
    a_optimizer.zero_grad()
    alpha_loss.sum().backward()
    a_optimizer.step()
    return alpha_loss.detach()


@torch.no_grad()
def soft_update(targets: list, sources: list, tau: float):
    """target <- tau * source + (1 - tau) * target for every parameter, in one fused call."""
    target_params = [p for net in targets for p in net.parameters()]
    source_params = [p for net in sources for p in net.parameters()]
    torch._foreach_lerp_(target_params, source_params, tau)


@torch.no_grad()
def evaluate(actor: Actor, envs: list, num_episodes: int, seeds: list) -> np.ndarray:
    """Undiscounted returns [num_seeds, num_episodes] of the noiseless actor, each seed's in its own env, stepped side
    by side. The envs are re-seeded each time, so every evaluation sees the same start states."""
    device = actor.action_scale.device
    returns = np.zeros((len(envs), num_episodes))
    obs = [env.reset(seed=seed)[0] for env, seed in zip(envs, seeds)]
    episode = [0] * len(envs)
    while min(episode) < num_episodes:
        actions = actor.deterministic_action(torch.as_tensor(np.stack(obs), device=device)).cpu().numpy()
        for k, env in enumerate(envs):
            if episode[k] == num_episodes:  # this seed is done; the others go on
                continue
            obs[k], reward, terminated, truncated, _ = env.step(actions[k])
            returns[k, episode[k]] += reward
            if terminated or truncated:
                episode[k] += 1
                if episode[k] < num_episodes:
                    obs[k], _ = env.reset()
    return returns


def main(args: Args):
    seeds = list(range(args.seed, args.seed + args.num_seeds))  # independent runs, trained side by side
    checkpoints = load_checkpoints(args.resume) if args.resume else None  # one per seed
    run_dirs = run_folders(args, seeds, checkpoints)
    if checkpoints and checkpoints[0]["global_step"] >= args.total_timesteps:
        print(f"{', '.join(run_dirs)} had already finished its {args.total_timesteps} steps")
        return results(run_dirs, [checkpoint["eval_returns"] for checkpoint in checkpoints])

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic

    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    # Each seed's own generators, seeded as torch.manual_seed seeds a single-seed run's: its initial weights (drawn on
    # the CPU) and its batches and noise (drawn on the device) are those of a single-seed run of that seed.
    init_generators = [torch.Generator().manual_seed(seed) for seed in seeds]
    generators = init_generators if device.type == "cpu" else [torch.Generator(device).manual_seed(seed) for seed in seeds]
    if not args.capture_video:  # nothing renders: spare dm_control its probe for a display (and its warning)
        os.environ.setdefault("MUJOCO_GL", "disable")

    # env setup: one env per seed; the evaluation envs are seeded apart from the training envs
    envs = [make_env(args.env_id, seed) for seed in seeds]
    eval_seeds = [seed + 100 for seed in seeds]
    video_folders = [f"videos/{os.path.basename(run_dir)}" if args.capture_video else None for run_dir in run_dirs]
    eval_envs = [make_env(args.env_id, s, v, video_every=args.eval_episodes) for s, v in zip(eval_seeds, video_folders)]
    obs_dim = int(np.prod(envs[0].observation_space.shape))
    action_dim = int(np.prod(envs[0].action_space.shape))

    actor = Actor(obs_dim, envs[0].action_space, init_generators).to(device)
    qf = QEnsemble(obs_dim, action_dim, num_q=2, generators=init_generators).to(device)
    qf_target = QEnsemble(obs_dim, action_dim, num_q=2, generators=init_generators).to(device)
    qf_target.load_state_dict(qf.state_dict())
    # fused Adam; capturable, so that --cudagraphs can record the optimizer step in its graph
    adam = functools.partial(optim.Adam, fused=True, capturable=args.cudagraphs)
    q_optimizer = adam(qf.parameters(), lr=args.q_lr)
    actor_optimizer = adam(actor.parameters(), lr=args.policy_lr)

    # Automatic entropy tuning
    target_entropy = -float(action_dim)
    log_alpha = torch.zeros(args.num_seeds, 1, requires_grad=True, device=device)  # alpha starts at 1, as in CleanRL
    a_optimizer = adam([log_alpha], lr=args.q_lr)
    alpha = log_alpha.detach().exp() if args.autotune else torch.full((args.num_seeds, 1), args.alpha, device=device)

    rb = ReplayBuffer(min(args.buffer_size, args.total_timesteps), obs_dim, action_dim, device, generators)

    def update(batch: Batch, policy_step: bool, target_step: bool) -> dict:
        """One training iteration: the critics; every --policy-frequency steps the actor and alpha; every
        --target-network-frequency the targets. Returns what gets logged, by TensorBoard tag, one value per seed."""
        with bf16_autocast(device, args.bf16):
            qf_loss, qf_a_values = update_critic(batch, qf, q_optimizer, actor, qf_target, alpha, args, generators)
            if policy_step:  # TD3 Delayed update support
                # compensate for the delay by doing 'actor_update_interval' instead of 1
                for _ in range(args.policy_frequency):
                    actor_loss = update_actor(batch, actor, actor_optimizer, qf, alpha, generators)
                    if args.autotune:
                        alpha_loss = update_alpha(batch, actor, log_alpha, a_optimizer, target_entropy, generators)
                        alpha.copy_(log_alpha.detach().exp())  # in place: a graph reads alpha where it was
            if target_step:
                soft_update([qf_target], [qf], args.tau)
        logs = {"losses/qf_values": qf_a_values.mean((-2, -1)), "losses/qf_loss": qf_loss / qf.num_q}  # per critic, as CleanRL
        if policy_step:
            logs["losses/actor_loss"], logs["losses/alpha"] = actor_loss, alpha
            if args.autotune:
                logs["losses/alpha_loss"] = alpha_loss
        return logs

    update = CudaGraph(update, generators) if args.cudagraphs else update  # one graph per (policy_step, target_step)

    nets = {"actor": actor, "qf": qf, "qf_target": qf_target}
    optimizers = {"q_optimizer": q_optimizer, "actor_optimizer": actor_optimizer, "a_optimizer": a_optimizer}
    parts = {"buffer": rb}  # with the networks and optimizers, what a checkpoint holds
    start_step, eval_returns = 0, [[] for _ in seeds]  # eval_returns: each seed's (step, mean return) of every evaluation
    obs = [None] * args.num_seeds  # None: that seed's episode starts at this step
    if checkpoints:
        checkpoint = join_seeds(checkpoints, nets)
        obs = restore(checkpoint, envs, nets, optimizers, **parts)
        start_step, eval_returns = checkpoint["global_step"], checkpoint["eval_returns"]
        restore_generators(generators, checkpoint["generators"], start_step)
        with torch.no_grad():
            log_alpha.copy_(checkpoint["log_alpha"])
        if args.autotune:
            alpha.copy_(log_alpha.detach().exp())

    def state(step: int) -> list:  # one checkpoint per seed
        extra = {"eval_returns": eval_returns, "generators": torch.stack([g.get_state() for g in generators])}  # plain values
        extra["log_alpha"] = log_alpha.detach().cpu()
        return split_seeds(snapshot(args, envs, step, nets, optimizers, **parts, **extra), nets, run_dirs)

    writers, pbar = start_logging(args, run_dirs, start_step, device)
    sps_time, sps_step, sps = time.time(), start_step, 0.0
    next_checkpoint = start_step + args.checkpoint_frequency

    def run_evaluation(step: int):
        returns = evaluate(actor, eval_envs, args.eval_episodes, eval_seeds)
        log_evaluation(writers, pbar, step, returns, sps, eval_returns, seeds)

    for global_step in range(start_step, args.total_timesteps):
        if global_step % args.eval_frequency == 0:
            run_evaluation(global_step)
            sps_time = time.time()
        obs = [
            env.reset(seed=seed if global_step == 0 else None)[0] if o is None else o for o, env, seed in zip(obs, envs, seeds)
        ]

        # ALGO LOGIC: put action logic here
        if global_step < args.learning_starts:
            actions = np.stack([env.action_space.sample() for env in envs])
        else:
            actions = noisy_action(np.stack(obs), actor, generators).cpu().numpy()

        # execute the game and log data; a time-limit truncation is stored as not terminated, so its target bootstraps
        next_obs, rewards, terminations, truncations, infos = zip(*(env.step(a) for env, a in zip(envs, actions)))
        rb.add(np.stack(obs), actions, np.stack(next_obs), rewards, terminations)
        obs = list(next_obs)
        for k, (writer, info) in enumerate(zip(writers, infos)):
            if terminations[k] or truncations[k]:
                writer.add_scalar("charts/episodic_return", info["episode"]["r"], global_step)
                writer.add_scalar("charts/episodic_length", info["episode"]["l"], global_step)
                obs[k] = None

        # ALGO LOGIC: training.
        if global_step >= args.learning_starts:
            batch = rb.sample(args.batch_size)
            policy_step = global_step % args.policy_frequency == 0
            try:
                logs = update(batch, policy_step, global_step % args.target_network_frequency == 0)
                if policy_step and global_step % 100 == 0:
                    log_scalars(writers, logs, global_step)
            except NonFiniteError as quantity:
                stop_non_finite(quantity, global_step, run_dirs, args.cudagraphs, lambda: state(global_step))

        if (global_step + 1) % 1000 == 0:  # training speed, evaluation time excluded
            sps = (global_step + 1 - sps_step) / (time.time() - sps_time)
            for writer in writers:
                writer.add_scalar("charts/SPS", sps, global_step)
            sps_time, sps_step = time.time(), global_step + 1
        pbar.update(1)
        if args.checkpoint_frequency and next_checkpoint <= global_step + 1 < args.total_timesteps:  # the last one: below
            write_checkpoints(run_dirs, state(global_step + 1))
            next_checkpoint = global_step + 1 + args.checkpoint_frequency

    run_evaluation(args.total_timesteps)
    if args.checkpoint_frequency:
        write_checkpoints(run_dirs, state(args.total_timesteps))
    pbar.close()
    if args.save_model:
        save_models(args, run_dirs, {"actor": actor, "qf": qf, "log_alpha": log_alpha})
    for env in envs + eval_envs:
        env.close()
    for writer in writers:
        writer.close()
    returned = {**nets, **optimizers, "update": update, "rb": rb, "alpha": alpha, "generators": generators}
    return {**returned, **results(run_dirs, eval_returns)}


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
        (args.policy_frequency > 0, f"--policy-frequency must be > 0, got {args.policy_frequency}"),
        (args.target_network_frequency > 0, f"--target-network-frequency must be > 0, got {args.target_network_frequency}"),
        (args.eval_frequency > 0, f"--eval-frequency must be > 0, got {args.eval_frequency}"),
        (args.eval_episodes > 0, f"--eval-episodes must be > 0, got {args.eval_episodes}"),
        (args.checkpoint_frequency >= 0, f"--checkpoint-frequency must be >= 0, got {args.checkpoint_frequency}"),
        (args.num_seeds >= 1, f"--num-seeds must be >= 1, got {args.num_seeds}"),
        (
            args.num_seeds == 1 or not args.run_name or "{seed}" in os.path.basename(args.run_name),
            f"--run-name {args.run_name} names one folder for {args.num_seeds} seeds; write {{seed}} in its last part, where each seed's number goes",
        ),
        (args.num_seeds == 1 or not args.track, "--track follows one run per process; drop it or use --num-seeds 1"),
    ]
    for ok, message in checks:
        if not ok:
            fail(message)
    if args.cudagraphs and not (args.cuda and torch.cuda.is_available()):
        reason = " and drops --no-cuda" if torch.cuda.is_available() else "; torch finds none here"
        fail("--cudagraphs needs a CUDA GPU" + reason)
    if args.learning_starts >= args.total_timesteps:  # allowed (a quick check of the wiring), but said: nothing is learned
        steps = f"--learning-starts ({args.learning_starts}) >= --total-timesteps ({args.total_timesteps})"
        print(f"note: {steps}: every step acts at random and the networks are never trained", file=sys.stderr)


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
    env = EpisodeRecord(env)
    env.action_space.seed(seed)
    return env


class EpisodeRecord(gym.Wrapper):
    """Remembers how the current episode began (the reset's seed, or the env's random state before the reset) and
    the actions taken since, so that a checkpoint taken mid-episode rebuilds the env exactly by replaying them."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.episode = None  # None: between episodes

    def reset(self, *, seed=None, options=None):
        start = rng_state(self.env.unwrapped.np_random) if seed is None else None
        self.episode = {"seed": seed, "rng": start, "actions": []}
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        self.episode["actions"].append(np.array(action))
        result = self.env.step(action)
        if result[2] or result[3]:  # terminated or truncated
            self.episode = None
        return result

    def state_dict(self) -> Optional[dict]:
        if self.episode is None:
            return None
        actions = self.episode["actions"]
        return {**self.episode, "actions": torch.from_numpy(np.stack(actions)) if actions else torch.zeros(0)}

    def replay(self, state: Optional[dict]):
        """Rebuilds the episode of a state_dict(): its observation now, or None between episodes."""
        if state is None:
            self.episode = None
            return None
        if state["rng"] is not None:
            set_rng_state(self.env.unwrapped.np_random, state["rng"])
        obs, _ = self.reset(seed=state["seed"])
        for action in state["actions"].numpy():
            obs = self.step(action)[0]
        return obs


def start_logging(args: Args, run_dirs: list, start_step: int, device: torch.device):
    """TensorBoard, one writer per run folder (a resumed run hides what the killed process logged after its checkpoint),
    Weights and Biases with --track, and a progress bar on a terminal (in a log file the per-evaluation lines say the
    same). Each run's hyperparameters table gives its own seed."""
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
            config=vars(args),
            name=names[0],
            monitor_gym=True,
            save_code=True,
        )
    writers = [SummaryWriter(run_dir, purge_step=start_step if args.resume else None) for run_dir in run_dirs]
    for k, writer in enumerate(writers if not args.resume else []):
        hyperparameters = {**vars(args), "seed": args.seed + k}
        writer.add_text(
            "hyperparameters",
            "|param|value|\n|-|-|\n%s" % ("\n".join([f"|{key}|{value}|" for key, value in hyperparameters.items()])),
        )
    pbar = tqdm(total=args.total_timesteps, initial=start_step, unit="step", disable=not sys.stderr.isatty())
    resumed = f", resumed at step {start_step}" if args.resume else ""
    tqdm.write(f"{', '.join(names)}: {args.env_id} on {device}, logging to {', '.join(run_dirs)}{resumed}")
    return writers, pbar


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


def log_scalars(writers: list, logs: dict, step: int):
    """Writes {tag: tensor of one value per seed}, each seed's into its run; a non-finite value stops the run (where
    --cudagraphs catches a NaN)."""
    values = {tag: value.reshape(len(writers)).tolist() for tag, value in logs.items()}
    for tag, seed_values in values.items():
        if not all(math.isfinite(value) for value in seed_values):
            raise NonFiniteError(tag.split("/")[-1])
    for tag, seed_values in values.items():
        for writer, value in zip(writers, seed_values):
            writer.add_scalar(tag, value, step)


def log_evaluation(writers: list, pbar, step: int, returns: np.ndarray, sps: float, eval_returns: list, seeds: list):
    """Records each seed's evaluation returns [num_seeds, episodes]: in its eval_returns, its TensorBoard run and a line."""
    for k, (writer, seed_returns) in enumerate(zip(writers, returns)):
        eval_returns[k].append((step, float(seed_returns.mean())))
        writer.add_scalar("eval/episodic_return", seed_returns.mean(), step)
        label = f"seed {seeds[k]} " if len(seeds) > 1 else ""
        tqdm.write(f"{label}step {step}: return {seed_returns.mean():.1f} +- {seed_returns.std():.1f}, {sps:.0f} steps/s")
    pbar.set_postfix(eval_return=f"{returns.mean():.1f}")


def stop_non_finite(quantity: NonFiniteError, step: int, run_dirs: list, cudagraphs: bool, last_good_state):
    """Ends the run on a non-finite loss. An eager update stops before the optimizer step that the loss would
    have poisoned, so the state is still finite and is saved (each seed's in its folder); a recorded graph is
    checked only when it logs."""
    if cudagraphs:
        fail(
            f"{quantity} became non-finite by step {step} (--cudagraphs checks every 100 steps and keeps no last finite "
            "state; without it a run stops at the first bad update)"
        )
    paths = [os.path.join(run_dir, "last_good_state.pt") for run_dir in run_dirs]
    for path, state in zip(paths, last_good_state()):
        write_checkpoint(path, state)
    rates = [f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(Args) if f.name.endswith(("lr", "learning_rate"))]
    where = paths[0] if len(paths) == 1 else f"{paths[0]} and the other seeds' folders"
    fail(
        f"{quantity} became non-finite at step {step} (try a smaller {' or '.join(rates)}); the last finite state is in {where}"
    )


class CudaGraph:
    """--cudagraphs: `update = CudaGraph(update, generators)` runs `update(batch, policy_step)` as a CUDA graph, one graph
    per value of the arguments that are not tensors. The first `warmup` calls of each run eagerly on a side
    stream (they allocate the gradients and optimizer states the graph will reuse), the next one records the
    graph, and from then on a call copies its tensors (a tensor, or a NamedTuple of them such as a Batch) into
    the graph's own inputs and replays it: one launch instead of hundreds of small kernels, with no host
    synchronisation. What it returns is overwritten by its next replay. The generators `fn` draws from are
    registered with each graph, so that a replay draws anew from each and advances it as `fn` would."""

    def __init__(self, fn, generators: Sequence = (), warmup: int = 3):
        self.fn, self.generators, self.warmup = fn, generators, warmup
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
            for generator in self.generators:
                self.graphs[key].register_generator_state(generator)
            with torch.cuda.graph(self.graphs[key]):  # records the kernels without running them
                self.outputs[key] = self.fn(*self.inputs[key])
        self.graphs[key].replay()
        return self.outputs[key]


def to_device(x, device: torch.device) -> torch.Tensor:
    """x (an array or a tensor) on the device. To a GPU it goes through pinned memory without waiting for the GPU:
    a copy from ordinary (pageable) memory first waits for every kernel queued, a replaying --cudagraphs update's
    too, and only then could acting launch its kernels; this way they are queued behind the update while it runs."""
    x = torch.as_tensor(x)
    if device.type != "cuda" or x.is_cuda:
        return x.to(device)
    # pin_memory copies x (an already pinned x it returns as it is, which must then not change until the copy
    # has read it); the pinned block is not reused before that
    return x.pin_memory().to(device, non_blocking=True)


# Checkpoints: everything needed to continue a run exactly. An environment's state is its random generators and,
# mid-episode, how its episode began and the actions since, which EpisodeRecord replays to rebuild it.
CHECKPOINT = "checkpoint.pt"
# flags that may differ between a run and its resumption: they don't change what is learned
RESUMABLE_FLAGS = {"resume", "run_name", "checkpoint_frequency", "track", "wandb_project_name", "wandb_entity"}
RESUMABLE_FLAGS |= {"capture_video", "save_model", "cuda", "cudagraphs"}


def snapshot(args: Args, envs: list, global_step: int, nets: dict, optimizers: dict, **parts) -> dict:
    """A run's state at `global_step`: its flags, networks, optimizers and random generators, each env's state, and
    `parts` (objects with a state_dict(), such as the replay buffer, or plain values such as the evaluations)."""
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
        },
        "envs": [
            {
                "action_space": rng_state(env.action_space.np_random),
                "env": rng_state(env.unwrapped.np_random),
                "episode": env.state_dict(),
            }
            for env in envs
        ],
    }


def restore(checkpoint: dict, envs: list, nets: dict, optimizers: dict, **parts) -> list:
    """Loads a snapshot() into the objects it was taken of (its plain values are the caller's to read). Returns each
    env's observation now (None between episodes)."""
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
    observations = []
    for env, state in zip(envs, checkpoint["envs"]):
        observations.append(env.replay(state["episode"]))
        set_rng_state(env.action_space.np_random, state["action_space"])
        set_rng_state(env.unwrapped.np_random, state["env"])
    return observations


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


def load_checkpoint(run_dir: str, name: str = CHECKPOINT) -> dict:
    path = os.path.join(run_dir, name)
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
    if "envs" not in checkpoint:
        fail(f"{path} was written by an older {script}, before many-seed runs changed the format; resume it with that version")
    return checkpoint


# Many seeds in one process (--num-seeds): each seed is an ordinary run with its own folder, TensorBoard log,
# evaluations, checkpoint and saved model; these functions cut the stacked state into runs and join it back.
def run_folders(args: Args, seeds: list, checkpoints: Optional[list]) -> list:
    """Each seed's run folder: --resume's and those of the seeds that trained beside it, or runs/ + --run-name
    ({seed} replaced by each seed's number), by default {env_id}__{exp_name}__{seed}__{unix time}."""
    if checkpoints:
        parent = os.path.dirname(os.path.normpath(args.resume))
        return [os.path.join(parent, name) for name in checkpoints[0]["run_names"]]
    template = args.run_name or f"{args.env_id.replace('/', '-')}__{args.exp_name}__{{seed}}__{int(time.time())}"
    return [os.path.join("runs", template.replace("{seed}", str(seed))) for seed in seeds]


def results(run_dirs: list, eval_returns: list) -> dict:
    """What main returns about the runs: every seed's, and the first seed's as a single-seed run gives them."""
    return {"run_dir": run_dirs[0], "eval_returns": eval_returns[0], "run_dirs": run_dirs, "seeds_eval_returns": eval_returns}


def seed_share(net_state: dict, params: set, k: int, num_seeds: int) -> dict:
    """Seed k's share of a stacked network's state_dict: its cut of each parameter (buffers are every seed's)."""
    return {name: t.chunk(num_seeds)[k].clone() if name in params else t for name, t in net_state.items()}


# plain values of a checkpoint that hold one entry (or, for tensors, one cut of the leading dimension) per seed
PER_SEED = ("eval_returns", "generators", "log_alpha")


def split_seeds(state: dict, nets: dict, run_dirs: list) -> list:
    """One checkpoint per seed from a snapshot() of the stacked seeds: the seed's cut of every parameter, optimizer
    moment and replay buffer, its env, its evaluations and its own generators' states; the flags, the step and the
    process's global generators in all."""
    n = len(run_dirs)
    params = {name: {key for key, _ in net.named_parameters()} for name, net in nets.items()}
    checkpoints = []
    for k in range(n):
        checkpoint = {**state, "run_names": [os.path.basename(run_dir) for run_dir in run_dirs], "seed_index": k}
        checkpoint["nets"] = {name: seed_share(sd, params[name], k, n) for name, sd in state["nets"].items()}
        checkpoint["optimizers"] = {
            name: {
                **sd,
                "state": {
                    i: {key: t.chunk(n)[k].clone() if t.dim() else t for key, t in s.items()} for i, s in sd["state"].items()
                },
            }
            for name, sd in state["optimizers"].items()
        }
        checkpoint["buffer"] = {**state["buffer"], "rows": state["buffer"]["rows"][k : k + 1].clone()}
        checkpoint["envs"] = state["envs"][k : k + 1]
        for key in PER_SEED:
            if key in state:
                checkpoint[key] = state[key][k] if isinstance(state[key], list) else state[key].chunk(n)[k].clone()
        checkpoints.append(checkpoint)
    return checkpoints


def join_seeds(checkpoints: list, nets: dict) -> dict:
    """split_seeds() undone: the seeds' checkpoints as one snapshot() of the stacked seeds, for restore()."""
    first = checkpoints[0]
    params = {name: {key for key, _ in net.named_parameters()} for name, net in nets.items()}
    state = dict(first)
    state["nets"] = {
        name: {
            key: torch.cat([c["nets"][name][key] for c in checkpoints]) if key in params[name] else t for key, t in sd.items()
        }
        for name, sd in first["nets"].items()
    }
    state["optimizers"] = {
        name: {
            **sd,
            "state": {
                i: {
                    key: torch.cat([c["optimizers"][name]["state"][i][key] for c in checkpoints]) if t.dim() else t
                    for key, t in s.items()
                }
                for i, s in sd["state"].items()
            },
        }
        for name, sd in first["optimizers"].items()
    }
    state["buffer"] = {**first["buffer"], "rows": torch.cat([c["buffer"]["rows"] for c in checkpoints])}
    state["envs"] = [env for c in checkpoints for env in c["envs"]]
    for key in PER_SEED:
        if key in first:
            state[key] = (
                [c[key] for c in checkpoints] if isinstance(first[key], list) else torch.cat([c[key] for c in checkpoints])
            )
    return state


def write_checkpoints(run_dirs: list, states: list):
    """Each seed's checkpoint into its run folder. All are written before any replaces its predecessor, so that a kill
    leaves either all the old ones or, for any seed still at the old step, its new one complete beside it."""
    paths = [os.path.join(run_dir, CHECKPOINT) for run_dir in run_dirs]
    for path, state in zip(paths, states):
        torch.save(state, path + ".tmp")
    for path in paths:
        os.replace(path + ".tmp", path)


def load_checkpoints(run_dir: str) -> list:
    """The checkpoints of the seeds that trained in one process with the run in run_dir, at one step, in seed order."""
    first = load_checkpoint(run_dir)
    if "generators" not in first:
        fail(
            f"--resume {run_dir} was written before each seed had generators of its own; resume it with that version (16c370a)"
        )
    run_dirs = [os.path.join(os.path.dirname(os.path.normpath(run_dir)), name) for name in first["run_names"]]
    checkpoints = [load_checkpoint(d) if os.path.isfile(os.path.join(d, CHECKPOINT)) else None for d in run_dirs]
    step = max(checkpoint["global_step"] for checkpoint in checkpoints if checkpoint)
    for k, d in enumerate(run_dirs):
        if checkpoints[k] is None or checkpoints[k]["global_step"] < step:  # killed between the renames: finish them
            tmp = os.path.join(d, CHECKPOINT + ".tmp")
            checkpoints[k] = load_checkpoint(d, CHECKPOINT + ".tmp") if os.path.isfile(tmp) else None
            if checkpoints[k] is None or checkpoints[k]["global_step"] != step:
                fail(f"--resume {run_dir}: {d} holds no checkpoint at step {step}, the step of the seeds beside it")
            os.replace(tmp, os.path.join(d, CHECKPOINT))
        if checkpoints[k]["seed_index"] != k:
            fail(f"--resume {run_dir}: {d} holds the checkpoint of another seed of the process")
    return checkpoints


def restore_generators(generators: list, states: torch.Tensor, step: int):
    """Each seed's generators as its checkpoint left them. A checkpoint from another kind of device (a GPU run resumed
    on a CPU, or the reverse) holds states of another kind of generator: those are seeded anew from the seed and the
    step, and the run goes on with other draws than an uninterrupted run's (as its kernels differ too)."""
    other_kind = [len(state) != len(generator.get_state()) for generator, state in zip(generators, states)]
    for generator, state, fresh in zip(generators, states, other_kind):
        if fresh:
            generator.manual_seed(generator.initial_seed() * 1_000_003 + step)
        else:
            generator.set_state(state.clone())  # a copy: set_state reads a row of a stacked tensor from the stack's start
    if any(other_kind):
        tqdm.write(f"the checkpoint's generators are not {generators[0].device.type} ones: new ones draw from step {step}")


def save_models(args: Args, run_dirs: list, saved: dict):
    """--save-model: each seed's cut of these networks (or tensors) into its run folder, as a one-seed run saves them."""
    for k, run_dir in enumerate(run_dirs):
        model = {}
        for name, x in saved.items():
            if isinstance(x, nn.Module):
                model[name] = seed_share(x.state_dict(), {key for key, _ in x.named_parameters()}, k, len(run_dirs))
            else:
                model[name] = x.detach().cpu().chunk(len(run_dirs))[k].clone()
        model_path = os.path.join(run_dir, f"{args.exp_name}.cleanrl_model")
        torch.save(model, model_path)
        tqdm.write(f"model saved to {model_path}")


if __name__ == "__main__":
    main(parse_args())
