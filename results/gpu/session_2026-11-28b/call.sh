#!/usr/bin/env bash
# The device calls of the second 2026-11-28 session, from the repository's root on the lent GPU machine (the device tool sets OUT):
#     BUDGET=560 bash results/gpu/session_2026-11-28b/call.sh    # a call's budget in seconds; a later call skips what an earlier did
# 1. starts, in the background (setsid: it outlives the call), 15 runs of 100k steps with benchmark.sh --gpu, seeds 1-3:
#    TD3 --critic-style release on cheetah-run and Ant-v4 (the critic comparison's missing TD3 arm, results/critic_style),
#    and OPARL with its defaults on walker-run, cheetah-run and Ant-v4 (the control for the grouped GPU shape, in which
#    OPARL --critic-style td3 ran); 2. the CUDA tests on the current code (first call only);
#    3. waits for the runs, copying their TensorBoard files to $OUT, never checkpoints.
set -u
BUDGET=${BUDGET:-560}
bash .whl/install.sh || exit 1
export PYTHONPATH=/tmp/site MUJOCO_GL=disable PYTHONUNBUFFERED=1 PYTHON=python3
REPO=$PWD W=/tmp/w N=15
mkdir -p "$W" "$OUT"
collect() {
    (cd "$W" && find runs -name 'events.out.tfevents*' -o -name DONE | tar czf "$OUT/runs.tgz" -T - logs sweep_td3.txt sweep_oparl.txt 2>/dev/null)
    { date +%T; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader; } >>"$OUT/nvidia_smi.txt" 2>&1
}
{
    nvidia-smi --query-gpu=name,driver_version,memory.total,memory.free --format=csv
    python3 -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'numpy', numpy.__version__)"
    grep -m1 "model name" /proc/cpuinfo; nproc; date -u +%FT%T
} >"$OUT/machine.txt" 2>&1
if [ ! -e "$W/started" ]; then
    touch "$W/started"
    echo get_server_list | nvidia-cuda-mps-control >/dev/null 2>&1 || nvidia-cuda-mps-control -d
    (cd "$W" && setsid nohup bash -c "bash $REPO/benchmark.sh --gpu --algos td3 --env-ids dm_control/cheetah-run-v0 Ant-v4 \
        --seeds 1 2 3 --total-timesteps 100000 -- --critic-style release >sweep_td3.txt 2>&1" >/dev/null 2>&1 &)
    (cd "$W" && setsid nohup bash -c "bash $REPO/benchmark.sh --gpu --algos oparl --env-ids dm_control/walker-run-v0 \
        dm_control/cheetah-run-v0 Ant-v4 --seeds 1 2 3 --total-timesteps 100000 >sweep_oparl.txt 2>&1" >/dev/null 2>&1 &)
    sleep 5
    timeout $((BUDGET - SECONDS - 200)) python3 -m pytest -p no:cacheprovider -n 6 tests/test_cudagraphs.py tests/test_reliability.py \
        -k "cudagraphs or cuda" -q --durations=10 2>&1 | tee "$OUT/gpu_tests.txt" | tail -n 25
fi
while (($(ls "$W"/runs/*/DONE 2>/dev/null | wc -l) < N && SECONDS < BUDGET - 30)); do collect; sleep 20; done
collect
echo "runs done: $(ls "$W"/runs/*/DONE 2>/dev/null | wc -l) of $N at ${SECONDS} s"
tail -n 3 "$W"/sweep_td3.txt "$W"/sweep_oparl.txt
