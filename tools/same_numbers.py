"""Do the scripts still compute the same numbers as the reference commit? Each script trains a short run (seed 1,
Pendulum-v1, a few hundred steps with learning), here and now, once with today's scripts and once with the
reference commit's, and every TensorBoard scalar both log but the speed is compared, bit for bit:

    python tools/same_numbers.py                          # against the reference commit (REFERENCE_FILE)
    python tools/same_numbers.py --against 1a2b3c4        # against another commit of this clone
    python tools/same_numbers.py --against ../old-checkout  # against another checkout's scripts

Float32 results differ between CPUs in their last bits (each CPU's kernels sum in their own order), so values
recorded on one machine cannot be checked on another; both sides run on this machine, in the same environment
(one thread each). The reference commit is the commit before the next deliberate numerical change: a change that
keeps the numbers must pass against it, and a commit that changes them on purpose moves it (docs/tests.md).
tests/test_same_numbers.py runs this for each script.
"""

import argparse
import os
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REFERENCE_FILE = os.path.join(REPO, "tests", "data", "same_numbers_reference.txt")
SHORT_OFF_POLICY = ["--total-timesteps", "600", "--learning-starts", "300", "--batch-size", "32"]
SHORT_ON_POLICY = ["--total-timesteps", "512", "--num-steps", "128", "--num-minibatches", "4", "--update-epochs", "2"]
EVAL = ["--eval-frequency", "300", "--eval-episodes", "1"]
# each script's short run: its defaults, shorter, with its own mechanisms reached (OPARL's reset and candidates)
RUNS = {
    "td3": SHORT_OFF_POLICY,
    "oparl": [*SHORT_OFF_POLICY, "--reset-frequency", "100", "--num-candidates", "3"],
    "sac": SHORT_OFF_POLICY,
    "redq": [*SHORT_OFF_POLICY, "--utd-ratio", "2", "--num-q", "4"],
    "ppo": SHORT_ON_POLICY,
    "rnd": SHORT_ON_POLICY,
    "ebd": SHORT_ON_POLICY,
}
ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}  # a reduction split over threads may sum in another order
NOT_COMPARED = {"charts/SPS"}  # wall-clock speed


class NoReference(Exception):
    """The reference's scripts cannot be had here (no git, a shallow clone without the commit)."""


def reference_commit() -> str:
    """The reference commit: the first word of REFERENCE_FILE that is not in a comment."""
    with open(REFERENCE_FILE) as f:
        return next(line.split()[0] for line in f if line.strip() and not line.startswith("#"))


def checkout(ref: str, into: str) -> str:
    """A folder with the scripts of `ref`: a folder as it is, or a commit of this clone, whose Python files are
    written into `into`."""
    if os.path.isdir(ref):
        return os.path.abspath(ref)
    try:
        found = subprocess.run(["git", "-C", REPO, "cat-file", "-e", f"{ref}^{{commit}}"], capture_output=True)
    except FileNotFoundError:
        raise NoReference(f"{ref}: no git on PATH to take that commit's scripts from") from None
    if found.returncode != 0:
        raise NoReference(f"{ref}: no such commit in this clone (a shallow clone? `git fetch --unshallow` brings it)")
    archive = subprocess.run(["git", "-C", REPO, "archive", ref], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", into, "--wildcards", "*.py"], input=archive, check=True)
    return into


def scalars(run_dir: str) -> dict:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(run_dir, size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [[e.step, e.value] for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"] if tag not in NOT_COMPARED}


def run(script: str, scripts_dir: str = REPO) -> dict:
    """The scalars of `script`'s short run, from the script in scripts_dir."""
    with tempfile.TemporaryDirectory() as tmp:
        flags = ["--env-id", "Pendulum-v1", "--seed", "1", *RUNS[script], *EVAL, "--run-name", "run", "--no-cuda"]
        command = [sys.executable, os.path.join(scripts_dir, f"{script}_continuous_action.py"), *flags]
        env = {**os.environ, **ONE_THREAD, "PYTHONPATH": scripts_dir}
        result = subprocess.run(command, cwd=tmp, env=env, capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")
        return scalars(os.path.join(tmp, "runs", "run"))


def differences(expected: dict, got: dict) -> list:
    """Where two runs' scalars differ: a tag one lacks, or the first step whose value differs."""
    found = []
    for tag in sorted(set(expected) | set(got)):
        if tag not in got or tag not in expected:
            found.append(f"{tag}: only in the {'reference' if tag in expected else 'new'} run")
            continue
        for (step, old), (new_step, new) in zip(expected[tag], got[tag]):
            if step != new_step or old != new:
                found.append(f"{tag}: step {step}: {old!r}, now step {new_step}: {new!r}")
                break
        else:
            if len(expected[tag]) != len(got[tag]):
                found.append(f"{tag}: {len(expected[tag])} values, now {len(got[tag])}")
    return found


def compare(script: str, reference_dir: str) -> list:
    """The differences between the reference's run of `script` and today's, both run here and now."""
    return differences(run(script, reference_dir), run(script))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--against", metavar="COMMIT_OR_CHECKOUT", help="default: the reference commit")
    parser.add_argument("--scripts", nargs="+", default=list(RUNS), choices=list(RUNS))
    args = parser.parse_args(argv)
    ref = args.against or reference_commit()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            reference_dir = checkout(ref, tmp)
        except NoReference as e:
            sys.exit(f"error: {e}")
        failed = False
        for script in args.scripts:
            found = compare(script, reference_dir)
            failed |= bool(found)
            print(f"{script}: " + ("the same numbers as " + ref if not found else "differs: " + "; ".join(found)))
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
