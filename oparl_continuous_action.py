# OPARL (Yang et al., "Efficient Reinforcement Learning via Decoupling Exploration and Utilization"): TD3 with an
# ensemble of critics, a pessimistic actor trained on their min (the evaluated policy), an optimistic actor trained on
# their max (explores on a share of the steps), and a periodic copy of the pessimistic actor into the optimistic one.
# A copy of td3_continuous_action.py (`diff td3_continuous_action.py oparl_continuous_action.py`); where the paper and
# the authors' code (yydsok/OPARL) disagree it follows the code, whose critics are SiLU MLPs (--critic-style td3: TD3's).
# The machinery (checks, envs, logging, checkpoints, --num-seeds, --cudagraphs) is imported from rl_utils.
import functools
import math
import os
import random
from dataclasses import dataclass
from typing import Literal, Optional

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
    learning_rate: float = 3e-4
    """the learning rate of the optimizer"""
    buffer_size: int = int(1e6)
    """the replay memory buffer size"""
    gamma: float = 0.99
    """the discount factor gamma"""
    tau: float = 0.005
    """target smoothing coefficient (default: 0.005)"""
    batch_size: int = 256
    """the batch size of sample from the reply memory"""
    policy_noise: float = 0.2
    """the scale of policy noise"""
    exploration_noise: float = 0.1
    """the scale of exploration noise"""
    learning_starts: int = 25000
    """timestep to start learning"""
    policy_frequency: int = 2
    """the frequency of training policy (delayed)"""
    noise_clip: float = 0.5
    """noise clip parameter of the Target Policy Smoothing Regularization"""
    q_num: int = 5
    """the number of critics in the ensemble (2: the paper's "two Q values" ablation)"""
    optimistic_ratio: float = 0.5
    """share of the steps after learning starts acted by the optimistic actor (1: optimistic only, 0: pessimistic only)"""
    num_candidates: int = 1
    """noisy optimistic actions drawn per optimistic step; the one whose Q-values spread most across the ensemble is taken"""
    reset_frequency: int = 20000
    """copy the pessimistic actor into the optimistic actor every this many training iterations (0: never)"""
    critic_style: Literal["release", "td3"] = "release"
    """td3: ReLU, nn.Linear's init (TD3's); release: SiLU, truncated-normal weights, zero biases (OPARL's release)"""

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
class QNetwork(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int, style: str):
        super().__init__()
        self.fc1 = nn.Linear(obs_dim + action_dim, 256)
        self.fc2 = nn.Linear(256, 256)
        self.fc3 = nn.Linear(256, 1)
        self.activation = {"release": F.silu, "td3": F.relu}[style]
        if style == "release":  # the release's init: zero biases; weights normal, std 1/(2 sqrt(fan_in)), |w| <= 2
            for layer in (self.fc1, self.fc2, self.fc3):
                nn.init.trunc_normal_(layer.weight, std=0.5 * layer.in_features**-0.5)
                nn.init.zeros_(layer.bias)

    def forward(self, x, a):
        x = torch.cat([x, a], -1)
        x = self.activation(self.fc1(x))
        x = self.activation(self.fc2(x))
        return self.fc3(x).squeeze(-1)


class QEnsemble(nn.ModuleList):
    """num_q independent QNetworks (OPARL's ensemble: 5); called, every critic's Q-values [num_q, batch]."""

    def __init__(self, obs_dim: int, action_dim: int, num_q: int = 5, style: str = "release"):
        super().__init__(QNetwork(obs_dim, action_dim, style) for _ in range(num_q))

    def forward(self, obs, actions):
        return torch.stack([qf(obs, actions) for qf in self])


class Actor(nn.Module):
    def __init__(self, obs_dim: int, action_space: gym.spaces.Box):
        super().__init__()
        self.fc1 = nn.Linear(obs_dim, 256)
        self.fc2 = nn.Linear(256, 256)
        self.fc_mu = nn.Linear(256, int(np.prod(action_space.shape)))
        # action rescaling
        low, high = (torch.as_tensor(bound, dtype=torch.float32) for bound in (action_space.low, action_space.high))
        self.register_buffer("action_scale", (high - low) / 2.0)
        self.register_buffer("action_bias", (high + low) / 2.0)
        self.register_buffer("action_low", low)
        self.register_buffer("action_high", high)

    def forward(self, x):
        x = F.relu(self.fc1(x))
        x = F.relu(self.fc2(x))
        x = torch.tanh(self.fc_mu(x))
        return x * self.action_scale + self.action_bias


@torch.no_grad()
def noisy_action(obs, actor: Actor, exploration_noise: float) -> torch.Tensor:
    """For one observation [obs_dim], the actor's action plus noise of std exploration_noise * action_scale, clipped."""
    action = actor(obs)
    noise = torch.randn_like(action) * (actor.action_scale * exploration_noise)
    return (action + noise).clamp(actor.action_low, actor.action_high)


def td_target(batch: Batch, target_actor: Actor, qf_target: QEnsemble, args: Args):
    """y = r + gamma * (1 - terminated) * min_i Q'_i(s', clip(pi_pes'(s') + clipped noise)), over all q_num critics."""
    with torch.no_grad():
        clipped_noise = (torch.randn_like(batch.actions) * args.policy_noise).clamp(-args.noise_clip, args.noise_clip)
        next_actions = target_actor(batch.next_observations) + clipped_noise * target_actor.action_scale
        next_actions = next_actions.clamp(target_actor.action_low, target_actor.action_high)
        min_qf_next_target = qf_target(batch.next_observations, next_actions).min(0).values
        return batch.rewards + (1 - batch.terminations) * args.gamma * min_qf_next_target


def critic_loss(batch: Batch, qf: QEnsemble, target_actor: Actor, qf_target: QEnsemble, args: Args):
    """The sum of each critic's mean squared error against the TD target, and the Q-values."""
    qf_a_values = qf(batch.observations, batch.actions)
    qf_loss = ((qf_a_values - td_target(batch, target_actor, qf_target, args)) ** 2).mean(-1).sum()
    return qf_loss, qf_a_values.detach()


def policy_losses(batch: Batch, actor: Actor, optimistic_actor: Actor, qf: QEnsemble):
    """The pessimistic actor ascends the min over the ensemble, the optimistic actor the max. Both
    go through one ensemble pass."""
    obs = batch.observations
    actions = torch.cat([actor(obs), optimistic_actor(obs)])
    q_pessimistic, q_optimistic = qf(torch.cat([obs, obs]), actions).chunk(2, dim=-1)
    return -q_pessimistic.min(0).values.mean(), -q_optimistic.max(0).values.mean()


def is_optimistic_step(global_step: int, optimistic_ratio: float) -> bool:
    """Spreads the optimistic steps evenly, step by step: with ratio 0.5 even steps are pessimistic
    and odd steps optimistic, as the release's `t % 2`; over n steps the share is within 1/n of the ratio."""
    return math.floor((global_step + 1) * optimistic_ratio) > math.floor(global_step * optimistic_ratio)


def optimistic_steps(global_step: int, args: Args) -> int:
    """How many of the steps --learning-starts ... global_step is_optimistic_step gave the optimistic actor."""
    return math.floor((global_step + 1) * args.optimistic_ratio) - math.floor(args.learning_starts * args.optimistic_ratio)


@torch.no_grad()
def optimistic_action(obs, optimistic_actor: Actor, qf: QEnsemble, args: Args):
    """For one observation [obs_dim], pi_opt(s) + Gaussian noise, drawn --num-candidates times; the candidate whose
    Q-values have the largest std across the ensemble is taken (paper, Setup). One candidate needs no critic pass."""
    candidates = optimistic_actor(obs).expand(args.num_candidates, -1)
    candidates = candidates + torch.randn_like(candidates) * (optimistic_actor.action_scale * args.exploration_noise)
    candidates = candidates.clamp(optimistic_actor.action_low, optimistic_actor.action_high)
    if args.num_candidates == 1:
        return candidates[0]
    return candidates[qf(obs.expand(args.num_candidates, -1), candidates).std(0).argmax()]


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
        *positive(args, "learning_rate", "buffer_size", "batch_size", "policy_frequency", "eval_frequency", "eval_episodes"),
        *at_least(args, 0, "policy_noise", "noise_clip", "exploration_noise", "learning_starts"),
        *within(args, "[0, 1]", "gamma"),
        *within(args, "(0, 1]", "tau"),
        (
            args.learning_starts >= args.batch_size,
            f"--learning-starts ({args.learning_starts}) must be >= --batch-size ({args.batch_size})",
        ),
        *at_least(args, 2, "q_num", why=" (min and max need an ensemble)"),
        *within(args, "[0, 1]", "optimistic_ratio"),
        *at_least(args, 1, "num_candidates"),
        *at_least(args, 0, "reset_frequency", why=" (0: never)"),
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
        actor = Actor(obs_dim, envs.action_space)  # the pessimistic actor, pi_pes: the evaluated policy
        optimistic_actor = Actor(obs_dim, envs.action_space)  # pi_opt, trained without a target network
        qf = QEnsemble(obs_dim, action_dim, args.q_num, args.critic_style)
        target_actor = Actor(obs_dim, envs.action_space)
        qf_target = QEnsemble(obs_dim, action_dim, args.q_num, args.critic_style)
        target_actor.load_state_dict(actor.state_dict())
        qf_target.load_state_dict(qf.state_dict())
        return actor, optimistic_actor, qf, target_actor, qf_target

    actor, optimistic_actor, qf, target_actor, qf_target = stack_seeds(networks, run.seeds, device)
    # fused Adam; capturable, so that --cudagraphs can record the optimizer step in its graph
    adam = functools.partial(optim.Adam, fused=True, capturable=args.cudagraphs)
    q_optimizer = adam(qf.parameters(), lr=args.learning_rate)
    actor_optimizer = adam(actor.parameters(), lr=args.learning_rate)
    optimistic_optimizer = adam(optimistic_actor.parameters(), lr=args.learning_rate)
    rb = ReplayBuffer(min(args.buffer_size, args.total_timesteps), obs_dim, action_dim, len(run.seeds), device)

    def update(batch: Batch, policy_step: bool) -> dict:
        """One training iteration: the critics; every --policy-frequency steps both actors and the target
        networks too. Returns what gets logged, by TensorBoard tag, one value per seed
        (per_seed's results carry a leading seeds dimension: losses [num_seeds], Q-values [num_seeds, num_q, batch])."""
        with bf16_autocast(device, args.bf16):
            qf_loss, qf_a_values = per_seed(critic_loss)(batch, qf, target_actor, qf_target, args)
            optimize(qf_loss, "qf_loss", q_optimizer)
            logs = {"losses/qf_values": qf_a_values.mean((-2, -1)), "losses/qf_loss": qf_loss.detach() / len(qf)}
            logs["charts/q_ensemble_std"] = qf_a_values.std(-2).mean(-1)
            if policy_step:
                with frozen(qf):  # the actor's loss computes no gradient for the critics (SpinningUp's freeze)
                    pessimistic_loss, optimistic_loss = per_seed(policy_losses)(batch, actor, optimistic_actor, qf)
                    # one backward pass: each actor gets only its own loss's gradient
                    optimize(pessimistic_loss + optimistic_loss, "actor_loss", actor_optimizer, optimistic_optimizer)
                soft_update([target_actor, qf_target], [actor, qf], args.tau)
                logs["losses/pessimistic_actor_loss"] = pessimistic_loss.detach()
                logs["losses/optimistic_actor_loss"] = optimistic_loss.detach()
        return logs

    update = CudaGraph(update) if args.cudagraphs else update  # one graph per value of policy_step

    @torch.no_grad()
    def policy(obs):  # the deterministic actor: what the evaluations report
        return per_seed(actor)(to_device(obs, device)).cpu().numpy()

    nets = {"actor": actor, "qf": qf, "target_actor": target_actor, "qf_target": qf_target}
    optimizers = {"q_optimizer": q_optimizer, "actor_optimizer": actor_optimizer}
    nets["optimistic_actor"], optimizers["optimistic_optimizer"] = optimistic_actor, optimistic_optimizer
    obs = run.start(envs, device, nets, optimizers, buffer=rb)  # restored on --resume, obs too
    obs = envs.reset() if obs is None else obs  # a fresh run: each env reset with its seed
    for global_step in range(run.start_step, args.total_timesteps):
        if global_step % args.eval_frequency == 0:
            run.evaluate(global_step, evaluate(policy, eval_envs, eval_seeds, args.eval_episodes))

        # ALGO LOGIC: put action logic here
        if global_step < args.learning_starts:
            actions = envs.sample_actions()
        elif is_optimistic_step(global_step, args.optimistic_ratio):  # explore with the optimistic actor
            actions = per_seed(optimistic_action)(to_device(obs, device), optimistic_actor, qf, args).cpu().numpy()
        else:
            actions = per_seed(noisy_action)(to_device(obs, device), actor, args.exploration_noise).cpu().numpy()

        # execute the game and log data; a time-limit truncation is stored as not terminated, so its target bootstraps
        next_obs, rewards, terminations, truncations, infos = envs.step(actions)
        rb.add(obs, infos["real_next_obs"], actions, rewards, terminations)
        obs = next_obs
        run.log_episodes(infos, global_step)

        # ALGO LOGIC: training.
        if global_step >= args.learning_starts:
            iteration = global_step - args.learning_starts + 1
            # Parameter reset, pi_opt <- pi_pes: Section 4.3 and the release (Algorithm 1 writes the reverse).
            # The critic update does not involve pi_opt, so copying before it equals copying after it.
            if args.reset_frequency and iteration % args.reset_frequency == 0:
                optimistic_actor.load_state_dict(actor.state_dict())  # in place: a graph sees it; Adam's state stays
            policy_step = global_step % args.policy_frequency == 0
            with run.stop_on_nan(global_step):
                logs = update(rb.sample(args.batch_size), policy_step)
                if policy_step and global_step % 100 == 0:
                    # set by the step alone, the same in every seed's run (run.log takes one value per seed)
                    logs["charts/optimistic_share"] = [optimistic_steps(global_step, args) / iteration] * args.num_seeds
                    logs["charts/resets"] = [args.reset_frequency and iteration // args.reset_frequency] * args.num_seeds
                    run.log(logs, global_step)
        run.end_step(global_step)  # training speed, progress bar, checkpoints

    run.evaluate(args.total_timesteps, evaluate(policy, eval_envs, eval_seeds, args.eval_episodes))
    results = run.finish(
        save={"actor": actor, "qf": qf, "optimistic_actor": optimistic_actor}, eval_envs=eval_envs, policy=policy
    )
    return {**nets, **optimizers, "update": update, "rb": rb, **results}


if __name__ == "__main__":
    main(parse_args(Args, check_args))
