# PPO (Schulman et al. 2017, https://arxiv.org/abs/1707.06347) for continuous actions with CleanRL's
# defaults (ppo_continuous_action.py), a baseline of the OPARL paper, on this repository's environment
# layer and evaluation: a Gaussian policy with a state-independent log-std, GAE, the clipped
# objective, observation and reward normalisation. Unlike CleanRL, a time-limit truncation
# bootstraps from the value of its last observation, as everywhere in this repository.
import dataclasses
import difflib
import os
import random
import sys
import time
from dataclasses import dataclass
from typing import Optional

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
import tyro
from torch.distributions.normal import Normal
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
    """whether to save the agent and its normalisation statistics into the `runs/{run_name}` folder"""
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


@torch.no_grad()
def evaluate(agent: Agent, normalizer: Normalizer, env: gym.Env, num_episodes: int, seed: int) -> np.ndarray:
    """Undiscounted returns of `num_episodes` episodes of the policy's mean action, clipped to the bounds,
    on observations normalised with the training statistics (not updated). The env is re-seeded each
    time, so every evaluation sees the same start states."""
    device = agent.actor_logstd.device
    returns = np.zeros(num_episodes)
    obs, _ = env.reset(seed=seed)
    for episode in range(num_episodes):
        if episode > 0:
            obs, _ = env.reset()
        done = False
        while not done:
            action = agent.actor_mean(torch.as_tensor(normalizer.observation(obs, update=False), device=device)).cpu().numpy()
            obs, reward, terminated, truncated, _ = env.step(action.clip(env.action_space.low, env.action_space.high))
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

    agent = Agent(obs_dim, action_dim).to(device)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    normalizer = Normalizer(obs_dim, args.gamma)
    rollout = Rollout(args.num_steps, obs_dim, action_dim, device)
    num_iterations = args.total_timesteps // args.num_steps  # a last partial rollout is collected but not learned from

    nets, optimizers = {"agent": agent}, {"optimizer": optimizer}
    # with the networks and optimizers, what a checkpoint holds
    parts = {"rollout": rollout, "normalizer": normalizer}
    start_step, eval_returns = 0, []  # eval_returns: (step, mean return) of every evaluation
    if checkpoint:
        restore(checkpoint, [env], nets, optimizers, **parts)
        start_step, eval_returns = checkpoint["global_step"], checkpoint["eval_returns"]

    def state(step: int) -> dict:  # a checkpoint
        return snapshot(args, [env], step, nets, optimizers, **parts, eval_returns=eval_returns)

    (writer,), pbar = start_logging(args, [run_dir], start_step, device)
    sps_time, sps_step, sps = time.time(), start_step, 0.0
    next_checkpoint = start_step + args.checkpoint_frequency

    def run_evaluation(step: int):
        returns = evaluate(agent, normalizer, eval_env, args.eval_episodes, eval_seed)
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
        obs = next_obs
        if terminated or truncated:
            writer.add_scalar("charts/episodic_return", info["episode"]["r"], global_step)
            writer.add_scalar("charts/episodic_length", info["episode"]["l"], global_step)
            obs = None

        # ALGO LOGIC: training, once a rollout is full
        if step_in_rollout == args.num_steps - 1 and iteration <= num_iterations:
            with torch.no_grad():
                next_value = agent.get_value(obs) if obs is not None else torch.zeros((), device=device)
                advantages, returns = compute_gae(
                    rollout.rewards, rollout.values, rollout.episode_ends, next_value, args.gamma, args.gae_lambda
                )
            try:
                stats = update_policy(rollout, advantages, returns, agent, optimizer, args)
            except NonFiniteError as quantity:
                stop_non_finite(quantity, global_step, run_dir, lambda: state(global_step))
            var_y = returns.var()
            explained_var = (1 - (returns - rollout.values).var() / var_y).item() if var_y > 0 else float("nan")
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            for name, value_t in stats.items():
                writer.add_scalar(f"losses/{name}", value_t.item(), global_step)
            writer.add_scalar("losses/explained_variance", explained_var, global_step)

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
        saved = {"actor": agent.state_dict(), "normalizer": normalizer.state_dict()}
        torch.save(saved, model_path)
        tqdm.write(f"model saved to {model_path}")
    env.close()
    eval_env.close()
    writer.close()
    return {**nets, **optimizers, **parts, "run_dir": run_dir, "eval_returns": eval_returns}


# --------------------------------------------------------------------------------------------------
# Machinery. Nothing below changes what the algorithm computes: the command line and its checks, the
# environment layer, logging, the NaN guard and the checkpoints behind exact resume.


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
        (args.num_steps > 0, f"--num-steps must be > 0, got {args.num_steps}"),
        (
            args.total_timesteps >= args.num_steps,
            f"--total-timesteps ({args.total_timesteps}) must be >= --num-steps ({args.num_steps}), one rollout",
        ),
        (
            1 <= args.num_minibatches <= args.num_steps,
            f"--num-minibatches must be in [1, --num-steps ({args.num_steps})], got {args.num_minibatches}",
        ),
        (args.update_epochs > 0, f"--update-epochs must be > 0, got {args.update_epochs}"),
        (args.learning_rate > 0, f"--learning-rate must be > 0, got {args.learning_rate}"),
        (0 <= args.gamma <= 1, f"--gamma must be in [0, 1], got {args.gamma}"),
        (0 <= args.gae_lambda <= 1, f"--gae-lambda must be in [0, 1], got {args.gae_lambda}"),
        (args.clip_coef > 0, f"--clip-coef must be > 0, got {args.clip_coef}"),
        (args.ent_coef >= 0, f"--ent-coef must be >= 0, got {args.ent_coef}"),
        (args.vf_coef >= 0, f"--vf-coef must be >= 0, got {args.vf_coef}"),
        (args.max_grad_norm > 0, f"--max-grad-norm must be > 0, got {args.max_grad_norm}"),
        (args.target_kl is None or args.target_kl > 0, f"--target-kl must be > 0, got {args.target_kl}"),
        (args.eval_frequency > 0, f"--eval-frequency must be > 0, got {args.eval_frequency}"),
        (args.eval_episodes > 0, f"--eval-episodes must be > 0, got {args.eval_episodes}"),
        (args.checkpoint_frequency >= 0, f"--checkpoint-frequency must be >= 0, got {args.checkpoint_frequency}"),
    ]
    for ok, message in checks:
        if not ok:
            fail(message)


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


class NonFiniteError(Exception):
    """A loss became NaN or infinite; raised before the optimizer step it would have poisoned."""


def check_finite(value: torch.Tensor, name: str):
    if not torch.isfinite(value):
        raise NonFiniteError(name)


def stop_non_finite(quantity: NonFiniteError, step: int, run_dir: str, last_good_state):
    """Ends the run on a non-finite loss. The update stops before the optimizer step that the loss would have
    poisoned, so the state is still finite and is saved."""
    path = os.path.join(run_dir, "last_good_state.pt")
    write_checkpoint(path, last_good_state())
    rates = [f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(Args) if f.name.endswith(("lr", "learning_rate"))]
    fail(
        f"{quantity} became non-finite at step {step} (try a smaller {' or '.join(rates)}); the last finite state is in {path}"
    )


# Checkpoints: everything needed to continue a run exactly. An environment's state is its random generators and,
# mid-episode, how its episode began and the actions since, which EpisodeRecord replays to rebuild it.
CHECKPOINT = "checkpoint.pt"
# flags that may differ between a run and its resumption: they don't change what is learned
RESUMABLE_FLAGS = {"resume", "run_name", "checkpoint_frequency", "track", "wandb_project_name", "wandb_entity"}
RESUMABLE_FLAGS |= {"capture_video", "save_model", "cuda"}


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


if __name__ == "__main__":
    main(parse_args())
