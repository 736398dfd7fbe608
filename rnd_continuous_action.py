# RND (Burda et al. 2019, "Exploration by Random Network Distillation", https://arxiv.org/abs/1810.12894) on
# this repository's PPO (ppo_continuous_action.py), an exploration baseline of the OPARL paper (Section 5.2).
# CleanRL's ppo_rnd_envpool.py (Atari pixels) ported to states: a fixed random target network and a
# trained predictor, MLPs on the next observation; the predictor's error is an intrinsic reward with its
# own value head and its own non-episodic GAE. `diff ppo_continuous_action.py rnd_continuous_action.py`
# shows exactly what RND adds to PPO.
import os
import random
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
from torch.distributions.normal import Normal

from rl_utils import Run, check_finite, evaluate, make_env, parse_args
from rl_utils import at_least, positive, within


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
    """whether to save the agent and its normalisation statistics into the `runs/{run_name}` folder"""
    run_name: Optional[str] = None
    """name of the run folder under runs/ (default: {env_id}__{exp_name}__{seed}__{unix time})"""
    checkpoint_frequency: int = 0
    """write `checkpoint.pt` into the run folder at the first episode end after every this many steps, and at the end"""
    resume: Optional[str] = None
    """continue the run in this folder (e.g. runs/{run_name}) from its checkpoint; flags given with it must match the run's"""

    # Algorithm specific arguments
    env_id: str = "Hopper-v4"
    """the id of the environment: a Gymnasium id (Hopper-v4, ...) or dm_control/<domain>-<task>-v0"""
    total_timesteps: int = 1000000
    """total timesteps of the experiments"""
    learning_rate: float = 3e-4
    """the learning rate of the optimizer"""
    num_steps: int = 2048
    """the number of steps to run per policy rollout"""
    anneal_lr: bool = True
    """Toggle learning rate annealing for policy and value networks"""
    gamma: float = 0.99
    """the discount factor gamma"""
    gae_lambda: float = 0.95
    """the lambda for the general advantage estimation"""
    num_minibatches: int = 32
    """the number of mini-batches"""
    update_epochs: int = 10
    """the K epochs to update the policy"""
    norm_adv: bool = True
    """Toggles advantages normalization"""
    clip_coef: float = 0.2
    """the surrogate clipping coefficient"""
    clip_vloss: bool = True
    """Toggles whether or not to use a clipped loss for the value function, as per the paper."""
    ent_coef: float = 0.0
    """coefficient of the entropy"""
    vf_coef: float = 0.5
    """coefficient of the value function"""
    max_grad_norm: float = 0.5
    """the maximum norm for the gradient clipping"""
    target_kl: Optional[float] = None
    """the target KL divergence threshold"""

    # RND arguments (CleanRL's defaults)
    update_proportion: float = 0.25
    """the share of each minibatch the predictor trains on"""
    int_coef: float = 1.0
    """coefficient of the intrinsic advantage"""
    ext_coef: float = 2.0
    """coefficient of the extrinsic advantage"""
    int_gamma: float = 0.99
    """the discount factor of the intrinsic return"""
    num_iterations_obs_norm_init: int = 1
    """rollouts of --num-steps random actions that set the observation statistics before training (as CleanRL; not counted)"""

    # Evaluation (the metric the paper reports)
    eval_frequency: int = 5000
    """evaluate the deterministic policy (its mean action, with the training observation statistics) every this many steps"""
    eval_episodes: int = 10
    """the number of episodes per evaluation"""


# ALGO LOGIC: initialize agent here:
def layer_init(layer, std=np.sqrt(2), bias_const=0.0):
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int):
        super().__init__()
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 64)),
            nn.Tanh(),
        )
        # one head for the extrinsic return, one for the intrinsic return (CleanRL's critic_ext and critic_int)
        self.critic_ext = layer_init(nn.Linear(64, 1), std=1.0)
        self.critic_int = layer_init(nn.Linear(64, 1), std=1.0)
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, action_dim), std=0.01),
        )
        self.actor_logstd = nn.Parameter(torch.zeros(action_dim))

    def get_value(self, x):
        hidden = self.critic(x)
        return self.critic_ext(hidden).squeeze(-1), self.critic_int(hidden).squeeze(-1)

    def get_action_and_value(self, x, action=None):
        action_mean = self.actor_mean(x)
        action_std = torch.exp(self.actor_logstd.expand_as(action_mean))
        # unvalidated: a collapsed std becomes a non-finite loss, which the NaN guard reports with its step
        probs = Normal(action_mean, action_std, validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(-1), probs.entropy().sum(-1), *self.get_value(x)


# RND's networks act on the state, not on pixels, so MLPs replace CleanRL's conv nets: 256 units, as the
# off-policy scripts' networks (ample for a random function of a state of up to Humanoid's 376 numbers),
# 128 output features (CleanRL: 512 from an image; a state needs fewer) and, as in CleanRL, a predictor
# deeper than its target, so that it can fit it.
class RNDModel(nn.Module):
    def __init__(self, obs_dim: int, features: int = 128, hidden: int = 256):
        super().__init__()
        self.target = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden)),
            nn.LeakyReLU(),
            layer_init(nn.Linear(hidden, hidden)),
            nn.LeakyReLU(),
            layer_init(nn.Linear(hidden, features)),
        )
        self.predictor = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden)),
            nn.LeakyReLU(),
            layer_init(nn.Linear(hidden, hidden)),
            nn.LeakyReLU(),
            layer_init(nn.Linear(hidden, hidden)),
            nn.ReLU(),
            layer_init(nn.Linear(hidden, features)),
        )
        self.target.requires_grad_(False)  # the target stays as it was initialised

    def bonus(self, rnd_obs):
        """The raw intrinsic reward of each observation: the predictor's squared error, summed over features / 2 (CleanRL)."""
        return (self.target(rnd_obs) - self.predictor(rnd_obs)).pow(2).sum(-1) / 2

    def loss(self, rnd_obs, update_proportion: float):
        """The predictor's MSE on a random `update_proportion` of the samples (CleanRL), so it does not learn too fast."""
        per_sample = (self.predictor(rnd_obs) - self.target(rnd_obs)).pow(2).mean(-1)
        mask = (torch.rand(len(per_sample), device=per_sample.device) < update_proportion).float()
        return (per_sample * mask).sum() / mask.sum().clamp(min=1.0)


class RunningMeanStd:
    """Running mean and variance of a stream, updated one sample at a time, as Gymnasium's
    NormalizeObservation and NormalizeReward keep them (parallel-variance update, count from 1e-4)."""

    def __init__(self, shape=()):
        self.mean, self.var, self.count = np.zeros(shape), np.ones(shape), 1e-4

    def update(self, x):
        delta = x - self.mean
        total = self.count + 1
        self.mean = self.mean + delta / total
        self.var = (self.var * self.count + delta**2 * self.count / total) / total
        self.count = total

    def update_batch(self, batch):
        """The same update from a whole batch at once (parallel variance, as CleanRL's update_from_moments)."""
        batch_mean, batch_var, n = batch.mean(0), batch.var(0), len(batch)
        delta, total = batch_mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        self.var = (self.var * self.count + batch_var * n + delta**2 * self.count * n / total) / total
        self.count = total


class Normalizer:
    """CleanRL's PPO wrappers (NormalizeObservation, clip to +-10, NormalizeReward, clip to +-10) as one
    object, so that evaluation uses the training statistics and checkpoints can hold them."""

    def __init__(self, obs_dim: int, gamma: float):
        self.obs_rms, self.return_rms = RunningMeanStd((obs_dim,)), RunningMeanStd()
        self.gamma, self.discounted_return = gamma, 0.0

    def observation(self, obs, update: bool = True) -> np.ndarray:
        if update:
            self.obs_rms.update(obs)
        return np.clip((obs - self.obs_rms.mean) / np.sqrt(self.obs_rms.var + 1e-8), -10, 10).astype(np.float32)

    def reward(self, reward: float, terminated: bool) -> float:
        # scaled by the std of a discounted return (not centred), as Gymnasium's NormalizeReward
        self.discounted_return = self.discounted_return * self.gamma * (1 - terminated) + reward
        self.return_rms.update(self.discounted_return)
        return float(np.clip(reward / np.sqrt(self.return_rms.var + 1e-8), -10, 10))

    def state_dict(self) -> dict:
        return {
            "obs": [torch.from_numpy(self.obs_rms.mean), torch.from_numpy(self.obs_rms.var), self.obs_rms.count],
            "return": [float(self.return_rms.mean), float(self.return_rms.var), self.return_rms.count],
            "discounted_return": float(self.discounted_return),
        }

    def load_state_dict(self, state: dict):
        mean, var, self.obs_rms.count = state["obs"]
        self.obs_rms.mean, self.obs_rms.var = mean.numpy().astype(np.float64), var.numpy().astype(np.float64)
        self.return_rms.mean, self.return_rms.var, self.return_rms.count = state["return"]
        self.discounted_return = state["discounted_return"]


class IntrinsicNormalizer:
    """The intrinsic reward's own statistics (CleanRL's obs_rms, RewardForwardFilter and reward_rms): observations
    normalised by their running mean and std and clipped to [-5, 5], updated once per rollout; intrinsic rewards
    divided by the running std of their discounted sum, which runs on across episode ends (the intrinsic return
    is non-episodic)."""

    def __init__(self, obs_dim: int, int_gamma: float):
        self.obs_rms, self.int_rms = RunningMeanStd((obs_dim,)), RunningMeanStd()
        self.int_gamma, self.discounted_int = int_gamma, 0.0

    def observation(self, obs: torch.Tensor) -> torch.Tensor:
        mean = torch.as_tensor(self.obs_rms.mean, dtype=obs.dtype, device=obs.device)
        std = torch.as_tensor(np.sqrt(self.obs_rms.var + 1e-8), dtype=obs.dtype, device=obs.device)
        return ((obs - mean) / std).clamp(-5, 5)

    def intrinsic(self, rewards: torch.Tensor) -> torch.Tensor:
        """One rollout's raw intrinsic rewards, divided by the std of the discounted intrinsic return."""
        discounted = np.zeros(len(rewards))
        for t, reward in enumerate(rewards.tolist()):
            self.discounted_int = self.discounted_int * self.int_gamma + reward
            discounted[t] = self.discounted_int
        self.int_rms.update_batch(discounted)
        return rewards / float(np.sqrt(self.int_rms.var + 1e-8))

    def state_dict(self) -> dict:
        return {
            "obs": [torch.from_numpy(self.obs_rms.mean), torch.from_numpy(self.obs_rms.var), self.obs_rms.count],
            "int": [float(self.int_rms.mean), float(self.int_rms.var), self.int_rms.count],
            "discounted_int": float(self.discounted_int),
        }

    def load_state_dict(self, state: dict):
        mean, var, self.obs_rms.count = state["obs"]
        self.obs_rms.mean, self.obs_rms.var = mean.numpy().astype(np.float64), var.numpy().astype(np.float64)
        self.int_rms.mean, self.int_rms.var, self.int_rms.count = state["int"]
        self.discounted_int = state["discounted_int"]


class Rollout:
    """One rollout of num_steps transitions in preallocated tensors. `episode_ends[t]` marks a step that
    ended an episode (terminated or truncated); a truncated step's bootstrap value is in its reward.
    `raw_next_obs` holds the next observations as the env gave them, for RND."""

    def __init__(self, num_steps: int, obs_dim: int, action_dim: int, device: torch.device):
        self.obs = torch.zeros((num_steps, obs_dim), device=device)
        self.actions = torch.zeros((num_steps, action_dim), device=device)
        self.logprobs, self.rewards, self.episode_ends, self.values = (torch.zeros(num_steps, device=device) for _ in range(4))
        self.int_values = torch.zeros(num_steps, device=device)
        self.raw_next_obs = torch.zeros((num_steps, obs_dim), device=device)

    def add(self, t: int, **values):
        """Stores step t's values, by field name."""
        for name, value in values.items():
            getattr(self, name)[t] = value

    def state_dict(self) -> dict:
        return {name: field.cpu().clone() for name, field in vars(self).items()}

    def load_state_dict(self, state: dict):
        for name, field in vars(self).items():
            field.copy_(state[name])


def compute_gae(rewards, values, episode_ends, next_value, gamma: float, gae_lambda: float):
    """GAE(lambda) advantages and returns of one rollout; nothing flows across an episode end."""
    advantages = torch.zeros_like(rewards)
    last_advantage = 0.0
    for t in reversed(range(len(rewards))):
        next_values = next_value if t == len(rewards) - 1 else values[t + 1]
        nonterminal = 1.0 - episode_ends[t]
        delta = rewards[t] + gamma * next_values * nonterminal - values[t]
        advantages[t] = last_advantage = delta + gamma * gae_lambda * nonterminal * last_advantage
    return advantages, advantages + values


def advantages_and_returns(rollout: Rollout, int_rewards, next_values, args: Args):
    """The advantage PPO follows, ext_coef * A_ext + int_coef * A_int, and both returns. The extrinsic GAE
    stops at episode ends as PPO's; the intrinsic one does not (no episode end is marked): novelty is a
    stream over the agent's lifetime, and an episode's end should not look rewarding or costly to it
    (Burda et al. 2019, Section 2.3)."""
    next_ext_value, next_int_value = next_values
    ends, no_ends = rollout.episode_ends, torch.zeros_like(rollout.episode_ends)
    ext_adv, ext_ret = compute_gae(rollout.rewards, rollout.values, ends, next_ext_value, args.gamma, args.gae_lambda)
    int_adv, int_ret = compute_gae(int_rewards, rollout.int_values, no_ends, next_int_value, args.int_gamma, args.gae_lambda)
    return args.ext_coef * ext_adv + args.int_coef * int_adv, ext_ret, int_ret


def ppo_loss(agent: Agent, obs, actions, old_logprobs, advantages, returns, old_values, int_returns, args: Args):
    """The clipped surrogate objective, the (clipped) value loss of both heads and the entropy bonus of one minibatch."""
    _, newlogprob, entropy, newvalue, new_int_value = agent.get_action_and_value(obs, actions)
    logratio = newlogprob - old_logprobs
    ratio = logratio.exp()
    if args.norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

    # Policy loss
    pg_loss = torch.max(-advantages * ratio, -advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)).mean()

    # Value loss
    if args.clip_vloss:
        v_clipped = old_values + torch.clamp(newvalue - old_values, -args.clip_coef, args.clip_coef)
        v_loss = 0.5 * torch.max((newvalue - returns) ** 2, (v_clipped - returns) ** 2).mean()
    else:
        v_loss = 0.5 * ((newvalue - returns) ** 2).mean()
    v_loss = v_loss + 0.5 * ((new_int_value - int_returns) ** 2).mean()  # the intrinsic head, unclipped as in CleanRL

    entropy_loss = entropy.mean()
    loss = pg_loss - args.ent_coef * entropy_loss + v_loss * args.vf_coef
    with torch.no_grad():  # http://joschu.net/blog/kl-approx.html
        stats = {
            "policy_loss": pg_loss,
            "value_loss": v_loss,
            "entropy": entropy_loss,
            "old_approx_kl": (-logratio).mean(),
            "approx_kl": ((ratio - 1) - logratio).mean(),
            "clipfrac": ((ratio - 1.0).abs() > args.clip_coef).float().mean(),
        }
    return loss, stats


def update_policy(rollout, advantages, returns, int_returns, rnd_obs, agent, rnd_model, optimizer, args: Args) -> dict:
    """update_epochs passes over the rollout in num_minibatches shuffled minibatches; the predictor learns
    in the same steps, on its share of each minibatch, through the same optimizer (as CleanRL)."""
    minibatch_size = args.num_steps // args.num_minibatches
    clipfracs = []
    for epoch in range(args.update_epochs):
        order = torch.randperm(args.num_steps, device=advantages.device)
        for start in range(0, minibatch_size * args.num_minibatches, minibatch_size):
            mb = order[start : start + minibatch_size]
            loss, stats = ppo_loss(
                agent,
                rollout.obs[mb],
                rollout.actions[mb],
                rollout.logprobs[mb],
                advantages[mb],
                returns[mb],
                rollout.values[mb],
                int_returns[mb],
                args,
            )
            rnd_loss = rnd_model.loss(rnd_obs[mb], args.update_proportion)
            loss, stats["rnd_loss"] = loss + rnd_loss, rnd_loss.detach()
            check_finite(loss, "loss")
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(optimizer.param_groups[0]["params"], args.max_grad_norm)
            optimizer.step()
            clipfracs.append(stats["clipfrac"])
        if args.target_kl is not None and stats["approx_kl"] > args.target_kl:
            break
    return {**stats, "clipfrac": torch.stack(clipfracs).mean()}


def check_args(args: Args) -> list:
    """The flags' valid values, as (holds, message) pairs: parse_args refuses a run that breaks one."""
    return [
        *positive(args, "learning_rate", "num_steps", "update_epochs", "clip_coef", "max_grad_norm"),
        *positive(args, "eval_frequency", "eval_episodes"),
        *at_least(args, 0, "ent_coef", "vf_coef"),
        *within(args, "[0, 1]", "gamma", "gae_lambda", "int_gamma"),
        *at_least(args, 0, "int_coef", "ext_coef", "num_iterations_obs_norm_init"),
        *within(args, "(0, 1]", "update_proportion"),
        (args.target_kl is None or args.target_kl > 0, f"--target-kl must be > 0, got {args.target_kl}"),
        (
            1 <= args.num_minibatches <= max(args.num_steps, 1),
            f"--num-minibatches must be in [1, --num-steps ({args.num_steps})], got {args.num_minibatches}",
        ),
        (
            args.total_timesteps >= args.num_steps,
            f"--total-timesteps ({args.total_timesteps}) must be >= --num-steps ({args.num_steps}), one rollout",
        ),
    ]


def main(args: Args):
    run = Run(args)  # the run folder; with --resume, the checkpoint it continues from
    if run.finished:
        return run.results()

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    # env setup: the evaluation env is seeded apart from the training env
    env = make_env(args.env_id, args.seed)
    eval_seed = args.seed + 100
    eval_env = make_env(args.env_id, eval_seed, run.video_folders[0], video_every=args.eval_episodes)
    obs_dim = int(np.prod(env.observation_space.shape))
    action_dim = int(np.prod(env.action_space.shape))

    agent = Agent(obs_dim, action_dim).to(device)
    rnd_model = RNDModel(obs_dim).to(device)
    optimizer = optim.Adam([*agent.parameters(), *rnd_model.predictor.parameters()], lr=args.learning_rate, eps=1e-5)
    normalizer = Normalizer(obs_dim, args.gamma)
    intrinsic_normalizer = IntrinsicNormalizer(obs_dim, args.int_gamma)
    rollout = Rollout(args.num_steps, obs_dim, action_dim, device)
    num_iterations = args.total_timesteps // args.num_steps  # a last partial rollout is collected but not learned from

    nets, optimizers = {"agent": agent, "rnd_model": rnd_model}, {"optimizer": optimizer}
    parts = {"rollout": rollout, "normalizer": normalizer, "intrinsic_normalizer": intrinsic_normalizer}
    # what a checkpoint holds (with the env), restored on --resume; checkpoints fall between episodes, so a run
    # (fresh or resumed) starts with an episode: obs None
    obs = run.start(env, device, nets, optimizers, **parts)
    if not run.checkpoints:  # CleanRL's warm-up: the observation statistics start from random actions' observations
        env.reset(seed=args.seed)
        warmup_obs = []
        for _ in range(args.num_iterations_obs_norm_init * args.num_steps):
            raw_obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
            warmup_obs.append(raw_obs)
            if terminated or truncated:
                env.reset()
        if warmup_obs:
            intrinsic_normalizer.obs_rms.update_batch(np.array(warmup_obs, dtype=np.float64))

    @torch.no_grad()
    def policy(obs):  # the mean action on the training statistics (not updated), clipped: what evaluations report
        action = agent.actor_mean(torch.as_tensor(normalizer.observation(obs, update=False), device=device)).cpu().numpy()
        return action.clip(env.action_space.low, env.action_space.high)

    writer = run.logs.writers[0]
    for global_step in range(run.start_step, args.total_timesteps):
        if global_step % args.eval_frequency == 0:
            run.evaluate(global_step, evaluate(policy, [eval_env], [eval_seed], args.eval_episodes))
        if obs is None:
            raw_obs, _ = env.reset(seed=args.seed if global_step == 0 else None)
            obs = torch.as_tensor(normalizer.observation(raw_obs), device=device)
        step_in_rollout = global_step % args.num_steps
        iteration = global_step // args.num_steps + 1
        if step_in_rollout == 0 and args.anneal_lr:  # Annealing the rate if instructed to do so.
            optimizer.param_groups[0]["lr"] = (1.0 - (iteration - 1.0) / num_iterations) * args.learning_rate

        # ALGO LOGIC: action logic
        with torch.no_grad():
            action, logprob, _, value, int_value = agent.get_action_and_value(obs)

        # execute the game and log data
        clipped_action = action.cpu().numpy().clip(env.action_space.low, env.action_space.high)
        next_raw_obs, reward, terminated, truncated, info = env.step(clipped_action)
        next_obs = torch.as_tensor(normalizer.observation(next_raw_obs), device=device)
        reward = normalizer.reward(reward, terminated)
        if truncated and not terminated:  # a time-limit cut: the value of the last observation stands in for the rest
            with torch.no_grad():
                reward += args.gamma * agent.get_value(next_obs)[0].item()
        rollout.add(step_in_rollout, obs=obs, actions=action, logprobs=logprob, values=value, int_values=int_value)
        rollout.add(step_in_rollout, rewards=reward, episode_ends=float(terminated or truncated))
        rollout.add(step_in_rollout, raw_next_obs=torch.as_tensor(next_raw_obs, device=device))
        obs = next_obs
        if terminated or truncated:
            obs = None
        run.log_episodes([info], global_step)

        # ALGO LOGIC: training, once a rollout is full
        if step_in_rollout == args.num_steps - 1 and iteration <= num_iterations:
            with torch.no_grad():
                # the predictor's error on this rollout's next observations, with the statistics before it
                bonus = rnd_model.bonus(intrinsic_normalizer.observation(rollout.raw_next_obs))
                int_rewards = intrinsic_normalizer.intrinsic(bonus)
                # after an episode end the extrinsic next value is not used; the intrinsic stream continues from it
                next_values = agent.get_value(next_obs)
                advantages, returns, int_returns = advantages_and_returns(rollout, int_rewards, next_values, args)
            intrinsic_normalizer.obs_rms.update_batch(rollout.raw_next_obs.double().cpu().numpy())
            # the predictor learns on the updated statistics, as CleanRL
            rnd_obs = intrinsic_normalizer.observation(rollout.raw_next_obs)
            with run.stop_on_nan(global_step):
                stats = update_policy(rollout, advantages, returns, int_returns, rnd_obs, agent, rnd_model, optimizer, args)
            var_y = returns.var()
            explained_var = (1 - (returns - rollout.values).var() / var_y).item() if var_y > 0 else float("nan")
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            for name, value_t in stats.items():
                writer.add_scalar(f"losses/{name}", value_t.item(), global_step)
            writer.add_scalar("losses/explained_variance", explained_var, global_step)
            writer.add_scalar("charts/intrinsic_reward", int_rewards.mean().item(), global_step)

        run.end_step(global_step, can_checkpoint=obs is None)  # speed, progress bar; checkpoints between episodes

    run.evaluate(args.total_timesteps, evaluate(policy, [eval_env], [eval_seed], args.eval_episodes))
    saved = {"actor": agent, "normalizer": normalizer, "rnd": rnd_model}
    results = run.finish(save=saved, eval_envs=eval_env, policy=policy)
    return {**nets, **optimizers, **parts, **results}


if __name__ == "__main__":
    main(parse_args(Args, check_args))
