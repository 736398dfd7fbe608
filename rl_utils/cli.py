"""The command line: a script's Args from its flags, checked, so that bad input stops with one line on stderr
(`error: ...`, exit status 1) instead of a traceback or a run that trains on something else."""

import os
import sys

import torch
import tyro

# flags that may differ between a run and its resumption: they don't change what is learned
RESUMABLE_FLAGS = {"resume", "run_name", "checkpoint_frequency", "track", "wandb_project_name", "wandb_entity"}
RESUMABLE_FLAGS |= {"capture_video", "save_model", "cuda", "cudagraphs"}

positive = (lambda v: v > 0, "must be > 0")
non_negative = (lambda v: v >= 0, "must be >= 0")
unit = (lambda v: 0 <= v <= 1, "must be in [0, 1]")
# the flags several scripts share, by name; a script checks its own flags with parse_args(Args, checks)
RULES = {
    **dict.fromkeys(["total_timesteps", "buffer_size", "batch_size", "learning_rate", "q_lr", "policy_lr"], positive),
    **dict.fromkeys(["policy_frequency", "target_network_frequency", "eval_frequency", "eval_episodes"], positive),
    **dict.fromkeys(["num_steps", "update_epochs", "clip_coef", "max_grad_norm"], positive),
    **dict.fromkeys(["policy_noise", "noise_clip", "exploration_noise", "alpha", "checkpoint_frequency"], non_negative),
    **dict.fromkeys(["ent_coef", "vf_coef"], non_negative),
    **dict.fromkeys(["gamma", "gae_lambda"], unit),
    "tau": (lambda v: 0 < v <= 1, "must be in (0, 1]"),
    "num_seeds": (lambda v: v >= 1, "must be >= 1"),
    "target_kl": (lambda v: v is None or v > 0, "must be > 0"),
    "num_q": (lambda v: v >= 1, "must be >= 1"),
    "utd_ratio": (lambda v: v >= 1, "must be >= 1"),
    # RND's and EBD's
    **dict.fromkeys(["int_coef", "ext_coef", "num_iterations_obs_norm_init"], non_negative),
    "int_gamma": unit,
    "update_proportion": (lambda v: 0 < v <= 1, "must be in (0, 1]"),
    "num_models": (lambda v: v >= 2, "must be >= 2 (a disagreement needs two)"),
    # OPARL's
    "q_num": (lambda v: v >= 2, "must be >= 2 (min and max need an ensemble)"),
    "optimistic_ratio": unit,
    "num_candidates": (lambda v: v >= 1, "must be >= 1"),
    "reset_frequency": (lambda v: v >= 0, "must be >= 0 (0: never)"),
}


def fail(message: str):
    """Stop with one line on stderr and exit status 1, no traceback."""
    raise SystemExit("error: " + " ".join(message.split()))


def script_of(Args) -> str:
    """The file name of the script that defines Args, which its checkpoints carry."""
    return os.path.basename(sys.modules[Args.__module__].__file__)


def parse_args(Args, checks=None, argv=None):
    """The command line as checked Args. `checks(args)` gives the script's own checks as (holds, message) pairs.
    With --resume the run's own flags are the defaults, and a flag given now may differ from the run's only if it
    does not change what is learned."""
    from rl_utils.checkpoints import load_checkpoint

    args = tyro.cli(Args, args=argv)
    if args.resume:
        run_args = load_checkpoint(args.resume, script_of(Args))["args"]
        args = tyro.cli(Args, args=argv, default=Args(**run_args))
        differing = [k for k, v in run_args.items() if k not in RESUMABLE_FLAGS and getattr(args, k) != v]
        if differing:
            flags = ", ".join(f"--{k.replace('_', '-')} {getattr(args, k)} (run: {run_args[k]})" for k in differing)
            fail(f"--resume {args.resume}: {flags}; a resumed run keeps its hyperparameters")
    validate(args, checks(args) if checks else [])
    return args


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def validate(args, own: list):
    """The checks every script shares (RULES, by flag name, and the pairs of flags), then the script's own."""
    values = vars(args)
    checks = [
        (ok(values[name]), f"{flag(name)} {rule}, got {values[name]}") for name, (ok, rule) in RULES.items() if name in values
    ]
    num_seeds = values.get("num_seeds", 1)
    if {"learning_starts", "batch_size"} <= values.keys():
        starts = f"--learning-starts ({args.learning_starts}) must be >= --batch-size ({args.batch_size})"
        checks.append((args.learning_starts >= args.batch_size, starts))
    if {"num_steps", "num_minibatches"} <= values.keys() and args.num_steps > 0:
        minibatches = f"--num-minibatches must be in [1, --num-steps ({args.num_steps})], got {args.num_minibatches}"
        checks.append((1 <= args.num_minibatches <= args.num_steps, minibatches))
        rollout = f"--total-timesteps ({args.total_timesteps}) must be >= --num-steps ({args.num_steps}), one rollout"
        checks.append((args.total_timesteps >= args.num_steps, rollout))
    checks += [
        (
            num_seeds == 1 or not args.run_name or "{seed}" in os.path.basename(args.run_name),
            f"--run-name {args.run_name} names one folder for {num_seeds} seeds; write {{seed}} in its last part, where "
            "each seed's number goes",
        ),
        (num_seeds == 1 or not args.track, "--track follows one run per process; drop it or use --num-seeds 1"),
        *own,
    ]
    for ok, message in checks:
        if not ok:
            fail(message)
    if values.get("cudagraphs") and not (args.cuda and torch.cuda.is_available()):
        reason = " and drops --no-cuda" if torch.cuda.is_available() else "; torch finds none here"
        fail("--cudagraphs needs a CUDA GPU" + reason)
    if "learning_starts" in values and args.learning_starts >= args.total_timesteps:  # allowed (a wiring check), but said
        steps = f"--learning-starts ({args.learning_starts}) >= --total-timesteps ({args.total_timesteps})"
        print(f"note: {steps}: every step acts at random and the networks are never trained", file=sys.stderr)
