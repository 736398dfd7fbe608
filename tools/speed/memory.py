"""Memory and checkpoint costs, the figures quoted in docs/reliability.md.

python tools/speed/memory.py rss td3 --env-id Hopper-v4 --total-timesteps 50000 --checkpoint-frequency 10000
    runs the script (one torch thread) and samples its resident memory every 2 s
python tools/speed/memory.py checkpoint [--script oparl] [--rows 100000]
    size, write and load time of a checkpoint whose replay buffer is full, on Hopper-v4 and
    dm_control/walker-walk-v0 shapes: the script's networks, Adam states and an rl_utils.ReplayBuffer, written by
    rl_utils.checkpoints.write_checkpoints as a run writes its checkpoint
"""

import argparse
import importlib
import os
import statistics
import subprocess
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, REPO)


def rss(script: str, flags: list):
    with tempfile.TemporaryDirectory() as workdir:
        env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
        cmd = [sys.executable, os.path.join(REPO, f"{script}_continuous_action.py"), *flags, "--run-name", "memory"]
        proc = subprocess.Popen(cmd, cwd=workdir, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        start, samples = time.time(), []
        while proc.poll() is None:
            try:
                with open(f"/proc/{proc.pid}/status") as f:
                    kb = next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))
                samples.append((time.time() - start, kb / 1024))
            except (OSError, StopIteration):
                pass
            time.sleep(2)
        if proc.returncode != 0:
            sys.exit(f"error: the run failed: {proc.stderr.read().strip().splitlines()[-1]}")
    settled = [mb for t, mb in samples if t >= 30] or [mb for _, mb in samples]
    print(
        f"{script} {' '.join(flags)}: {time.time() - start:.0f} s; resident memory after the first 30 s: {min(settled):.0f}-{max(settled):.0f} MB over {len(settled)} samples; peak {max(mb for _, mb in samples):.0f} MB"
    )


def checkpoint(script: str, rows: int):
    import gymnasium as gym
    import numpy as np
    import torch

    from rl_utils import ReplayBuffer
    from rl_utils.checkpoints import CHECKPOINT, write_checkpoints

    torch.set_num_threads(1)
    module = importlib.import_module(f"{script}_continuous_action")
    for env_id, obs_dim, action_dim in [("Hopper-v4", 11, 3), ("dm_control/walker-walk-v0", 24, 6)]:
        space = gym.spaces.Box(-1.0, 1.0, (action_dim,), np.float32)
        nets = {name: module.Actor(obs_dim, space) for name in ("actor", "second_actor", "target_actor")}
        nets.update(qf=module.QEnsemble(obs_dim, action_dim, 5), qf_target=module.QEnsemble(obs_dim, action_dim, 5))
        optimizers = {name: torch.optim.Adam(nets[name].parameters()) for name in ("qf", "actor", "second_actor")}
        for name, optimizer in optimizers.items():  # fill Adam's moment estimates
            for p in nets[name].parameters():
                p.grad = torch.zeros_like(p)
            optimizer.step()
        rb = ReplayBuffer(rows, obs_dim, action_dim, 1, torch.device("cpu"))  # one seed's
        rb.storage.normal_()
        rb.size = rows
        state = {
            "nets": {k: v.state_dict() for k, v in nets.items()},
            "optimizers": {k: v.state_dict() for k, v in optimizers.items()},
        }
        with tempfile.TemporaryDirectory() as workdir:
            path, writes = os.path.join(workdir, CHECKPOINT), []
            for _ in range(5):
                start = time.perf_counter()
                write_checkpoints([workdir], [{**state, "buffer": rb.state_dict()}])  # the buffer's rows copied, as a run's
                writes.append(time.perf_counter() - start)
            start = time.perf_counter()
            torch.load(path, weights_only=True)
            load = time.perf_counter() - start
            size = os.path.getsize(path) / 2**20
        print(
            f"{script}, {env_id} shapes, {rows} transitions: {size:.1f} MiB (buffer {rb.storage.numel() * 4 / 2**20:.1f} MiB), write {1e3 * statistics.median(writes):.0f} ms (median of 5), load {1e3 * load:.0f} ms"
        )


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["rss"] and len(argv) > 1:
        return rss(argv[1], argv[2:])
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=["rss", "checkpoint"])
    parser.add_argument("--script", default="oparl", help="an off-policy script (its networks, buffer and writer)")
    parser.add_argument("--rows", type=int, default=100_000)
    args = parser.parse_args(argv)
    if args.mode == "rss":
        parser.error("rss needs a script and its flags: tools/speed/memory.py rss td3 --env-id Hopper-v4 ...")
    checkpoint(args.script, args.rows)


if __name__ == "__main__":
    main()
