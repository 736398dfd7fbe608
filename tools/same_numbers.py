"""Do the scripts still compute the same numbers? Each script trains a short run (seed 1, Pendulum-v1, about a
thousand steps with learning) and every TensorBoard scalar it logs but the speed is compared, bit for bit, with
the values recorded at an earlier commit, or with another checkout's scripts run here and now:

    python tools/same_numbers.py --check tests/data/same_numbers.json           # against the recorded values
    python tools/same_numbers.py --record tests/data/same_numbers.json          # record them anew
    python tools/same_numbers.py --against ../old-checkout                      # run both, compare

Float32 results depend on the CPU's kernels, so the runs pin MKL and PyTorch to their AVX2 code paths
(MKL_CBWR, ATEN_CPU_CAPABILITY), which every x86-64 CPU we run on has: recorded on one such CPU, the values hold
on another. tests/test_same_numbers.py runs the --check.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHORT_OFF_POLICY = ["--total-timesteps", "1000", "--learning-starts", "500", "--batch-size", "64"]
SHORT_ON_POLICY = ["--total-timesteps", "1024", "--num-steps", "256", "--num-minibatches", "4", "--update-epochs", "2"]
EVAL = ["--eval-frequency", "500", "--eval-episodes", "1"]
# each script's short run: its defaults, shorter, with its own mechanisms reached (OPARL's reset and candidates)
RUNS = {
    "td3": SHORT_OFF_POLICY,
    "oparl": [*SHORT_OFF_POLICY, "--reset-frequency", "200", "--num-candidates", "3"],
    "sac": SHORT_OFF_POLICY,
    "redq": [*SHORT_OFF_POLICY, "--utd-ratio", "2", "--num-q", "4"],
    "ppo": SHORT_ON_POLICY,
    "rnd": SHORT_ON_POLICY,
    "ebd": SHORT_ON_POLICY,
}
PINNED = {"MKL_CBWR": "AVX2", "ATEN_CPU_CAPABILITY": "avx2", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
NOT_COMPARED = {"charts/SPS"}  # wall-clock speed


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
        env = {**os.environ, **PINNED, "PYTHONPATH": scripts_dir}
        result = subprocess.run(command, cwd=tmp, env=env, capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")
        return scalars(os.path.join(tmp, "runs", "run"))


def differences(expected: dict, got: dict) -> list:
    """Where two runs' scalars differ: a tag one lacks, or the first step whose value differs."""
    found = []
    for tag in sorted(set(expected) | set(got)):
        if tag not in got or tag not in expected:
            found.append(f"{tag}: only in the {'recorded' if tag in expected else 'new'} run")
            continue
        for (step, old), (new_step, new) in zip(expected[tag], got[tag]):
            if step != new_step or old != new:
                found.append(f"{tag}: step {step}: {old!r}, now step {new_step}: {new!r}")
                break
        else:
            if len(expected[tag]) != len(got[tag]):
                found.append(f"{tag}: {len(expected[tag])} values, now {len(got[tag])}")
    return found


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--record", metavar="JSON", help="write the scripts' values here")
    what.add_argument("--check", metavar="JSON", help="compare the scripts' values with those recorded here")
    what.add_argument("--against", metavar="CHECKOUT", help="run this checkout's scripts too and compare")
    parser.add_argument("--scripts", nargs="+", default=list(RUNS), choices=list(RUNS))
    args = parser.parse_args(argv)
    if args.record:
        recorded = {script: {"flags": RUNS[script], "scalars": run(script)} for script in args.scripts}
        os.makedirs(os.path.dirname(os.path.abspath(args.record)), exist_ok=True)
        with open(args.record, "w") as f:
            json.dump(recorded, f, indent=0)
        print(f"{len(recorded)} scripts' values -> {args.record}")
        return
    if args.check:
        with open(args.check) as f:
            recorded = json.load(f)
        expected = {script: recorded[script]["scalars"] for script in args.scripts}
    else:
        expected = {script: run(script, os.path.abspath(args.against)) for script in args.scripts}
    failed = False
    for script in args.scripts:
        found = differences(expected[script], run(script))
        failed |= bool(found)
        print(f"{script}: " + ("the same numbers" if not found else "differs: " + "; ".join(found)))
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
