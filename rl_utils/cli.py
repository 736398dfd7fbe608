"""The command line: a script's Args from its flags, checked, so that bad input stops with one line on stderr
(`error: ...`, exit status 1) instead of a traceback or a run that trains on something else. rl_utils checks the
flags it reads itself; each script checks its own (`check_args`, with `positive`, `at_least` and `within`)."""

import os
import sys

import torch
import tyro

from rl_utils.checkpoints import load_checkpoint
from rl_utils.errors import fail

# flags that may differ between a run and its resumption: they don't change what is learned
RESUMABLE_FLAGS = {"resume", "run_name", "checkpoint_frequency", "track", "wandb_project_name", "wandb_entity"}
RESUMABLE_FLAGS |= {"capture_video", "save_model", "cuda", "cudagraphs"}


def script_of(Args) -> str:
    """The file name of the script that defines Args, which its checkpoints carry."""
    return os.path.basename(sys.modules[Args.__module__].__file__)


def parse_args(Args, checks=None, argv=None):
    """The command line as checked Args. `checks(args)` gives the script's own checks as (holds, message) pairs.
    With --resume the run's own flags are the defaults, and a flag given now may differ from the run's only if it
    does not change what is learned."""
    args = tyro.cli(Args, args=argv)
    if args.resume:
        checkpoint = load_checkpoint(args.resume, script_of(Args))
        run_args = checkpoint.get("args_given", checkpoint["args"])  # as main got them (rl_utils.run.Run)
        args = tyro.cli(Args, args=argv, default=Args(**run_args))
        differing = [k for k, v in run_args.items() if k not in RESUMABLE_FLAGS and getattr(args, k) != v]
        if differing:
            flags = ", ".join(f"--{k.replace('_', '-')} {getattr(args, k)} (run: {run_args[k]})" for k in differing)
            fail(f"--resume {args.resume}: {flags}; a resumed run keeps its hyperparameters")
    validate(args, checks(args) if checks else [])
    return args


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


# A script checks its own flags: check_args(args) returns (holds, message) pairs, built with these. A flag a fork adds
# has no rule until its author writes one.
def positive(args, *names) -> list:
    return [(getattr(args, name) > 0, f"{flag(name)} must be > 0, got {getattr(args, name)}") for name in names]


def at_least(args, minimum, *names, why: str = "") -> list:
    return [(getattr(args, n) >= minimum, f"{flag(n)} must be >= {minimum}{why}, got {getattr(args, n)}") for n in names]


def within(args, interval: str, *names) -> list:
    """interval: "[0, 1]", "(0, 1]", ...: its brackets say whether an end is included."""
    low, high = (float(end) for end in interval[1:-1].split(","))

    def inside(v):
        return (low <= v if interval[0] == "[" else low < v) and (v <= high if interval[-1] == "]" else v < high)

    return [(inside(getattr(args, name)), f"{flag(name)} must be in {interval}, got {getattr(args, name)}") for name in names]


def validate(args, own: list):
    """The flags rl_utils itself reads (steps, seeds, folders, checkpoints, tracking, --cudagraphs), then the script's
    own checks."""
    num_seeds = getattr(args, "num_seeds", 1)
    checks = [
        *positive(args, "total_timesteps"),
        *at_least(args, 1, *(["num_seeds"] if hasattr(args, "num_seeds") else [])),
        *at_least(args, 0, "checkpoint_frequency"),
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
    if getattr(args, "cudagraphs", False) and not (args.cuda and torch.cuda.is_available()):
        reason = " and drops --no-cuda" if torch.cuda.is_available() else "; torch finds none here"
        fail("--cudagraphs needs a CUDA GPU" + reason)
    learning_starts = getattr(args, "learning_starts", 0)
    if learning_starts >= args.total_timesteps:  # allowed (a wiring check), but said
        steps = f"--learning-starts ({learning_starts}) >= --total-timesteps ({args.total_timesteps})"
        print(f"note: {steps}: every step acts at random and the networks are never trained", file=sys.stderr)
