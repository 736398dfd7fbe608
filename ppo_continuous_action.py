# PPO (Schulman et al. 2017, https://arxiv.org/abs/1707.06347) for continuous actions with CleanRL's
# defaults (ppo_continuous_action.py), a baseline of the OPARL paper, on this repository's environment
# layer and evaluation: a Gaussian policy with a state-independent log-std, GAE, the clipped
# objective, observation and reward normalisation. Unlike CleanRL, a time-limit truncation
# bootstraps from the value of its last observation, as everywhere in this repository.
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
            layer_init(nn.Linear(64, 1), std=1.0),
        )
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, action_dim), std=0.01),
        )
        self.actor_logstd = nn.Parameter(torch.zeros(action_dim))

    def get_value(self, x):
        return self.critic(x).squeeze(-1)

    def get_action_and_value(self, x, action=None):
        action_mean = self.actor_mean(x)
        action_std = torch.exp(self.actor_logstd.expand_as(action_mean))
        # unvalidated: a collapsed std becomes a non-finite loss, which the NaN guard reports with its step
        probs = Normal(action_mean, action_std, validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(-1), probs.entropy().sum(-1), self.get_value(x)


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


class Rollout:
    """One rollout of num_steps transitions in preallocated tensors. `episode_ends[t]` marks a step that
    ended an episode (terminated or truncated); a truncated step's bootstrap value is in its reward."""

    def __init__(self, num_steps: int, obs_dim: int, action_dim: int, device: torch.device):
        self.obs = torch.zeros((num_steps, obs_dim), device=device)
        self.actions = torch.zeros((num_steps, action_dim), device=device)
        self.logprobs, self.rewards, self.episode_ends, self.values = (torch.zeros(num_steps, device=device) for _ in range(4))

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


def ppo_loss(agent: Agent, obs, actions, old_logprobs, advantages, returns, old_values, args: Args):
    """The clipped surrogate objective, the (clipped) value loss and the entropy bonus of one minibatch."""
    _, newlogprob, entropy, newvalue = agent.get_action_and_value(obs, actions)
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


def update_policy(rollout: Rollout, advantages, returns, agent: Agent, optimizer, args: Args) -> dict:
    """update_epochs passes over the rollout in num_minibatches shuffled minibatches."""
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
                args,
            )
            check_finite(loss, "loss")
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
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
        *within(args, "[0, 1]", "gamma", "gae_lambda"),
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
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    normalizer = Normalizer(obs_dim, args.gamma)
    rollout = Rollout(args.num_steps, obs_dim, action_dim, device)
    num_iterations = args.total_timesteps // args.num_steps  # a last partial rollout is collected but not learned from

    @torch.no_grad()
    def policy(obs):  # the mean action on the training statistics (not updated), clipped: what evaluations report
        action = agent.actor_mean(torch.as_tensor(normalizer.observation(obs, update=False), device=device)).cpu().numpy()
        return action.clip(env.action_space.low, env.action_space.high)

    nets, optimizers = {"agent": agent}, {"optimizer": optimizer}
    # what a checkpoint holds (with the env), restored on --resume; checkpoints fall between episodes, so a run
    # (fresh or resumed) starts with an episode: obs None
    obs = run.start(env, device, nets, optimizers, rollout=rollout, normalizer=normalizer)
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
            action, logprob, _, value = agent.get_action_and_value(obs)

        # execute the game and log data
        clipped_action = action.cpu().numpy().clip(env.action_space.low, env.action_space.high)
        next_raw_obs, reward, terminated, truncated, info = env.step(clipped_action)
        next_obs = torch.as_tensor(normalizer.observation(next_raw_obs), device=device)
        reward = normalizer.reward(reward, terminated)
        if truncated and not terminated:  # a time-limit cut: the value of the last observation stands in for the rest
            with torch.no_grad():
                reward += args.gamma * agent.get_value(next_obs).item()
        rollout.add(step_in_rollout, obs=obs, actions=action, logprobs=logprob, values=value)
        rollout.add(step_in_rollout, rewards=reward, episode_ends=float(terminated or truncated))
        obs = None if terminated or truncated else next_obs
        run.log_episodes([info], global_step)

        # ALGO LOGIC: training, once a rollout is full
        if step_in_rollout == args.num_steps - 1 and iteration <= num_iterations:
            with torch.no_grad():
                next_value = agent.get_value(obs) if obs is not None else torch.zeros((), device=device)
                advantages, returns = compute_gae(
                    rollout.rewards, rollout.values, rollout.episode_ends, next_value, args.gamma, args.gae_lambda
                )
            with run.stop_on_nan(global_step):
                stats = update_policy(rollout, advantages, returns, agent, optimizer, args)
            var_y = returns.var()
            explained_var = (1 - (returns - rollout.values).var() / var_y).item() if var_y > 0 else float("nan")
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            for name, value_t in stats.items():
                writer.add_scalar(f"losses/{name}", value_t.item(), global_step)
            writer.add_scalar("losses/explained_variance", explained_var, global_step)
        run.end_step(global_step, can_checkpoint=obs is None)  # speed, progress bar; checkpoints between episodes

    run.evaluate(args.total_timesteps, evaluate(policy, [eval_env], [eval_seed], args.eval_episodes))
    results = run.finish(save={"actor": agent, "normalizer": normalizer}, eval_envs=eval_env, policy=policy)
    return {**nets, **optimizers, "rollout": rollout, "normalizer": normalizer, **results}


if __name__ == "__main__":
    main(parse_args(Args, check_args))
