#!/usr/bin/env bash
# The device calls of 2026-11-28, from the repository's root on the lent GPU machine (the device tool sets OUT):
#     BUDGET=535 bash results/gpu/session_2026-11-28/call.sh     # a call's budget in seconds (the 2nd call: 320);
#                                                                # what an earlier call did is skipped
# 1. starts, in the background (setsid: it outlives the call), the 14 runs of 100k steps that fit one lease:
#    the QNetwork learning check (td3 seeds 2-3, oparl seeds 1-3, cartpole-swingup; td3 seed 1 finished on a CPU;
#    results/qnetwork) and OPARL with TD3's critics (walker-run, cheetah-run, Ant-v4, seeds 1-3; results/critic_style), both
#    with benchmark.sh --gpu; 2. the CUDA tests on the current code (first call only); 3. waits for the runs,
#    copying their TensorBoard files to $OUT; 4. once they are done, the critics' speed before and after the
#    QNetwork change (.before/: td3 and oparl of 5b9ba77 with their rl_utils, carried) with --cudagraphs.
set -u
BUDGET=${BUDGET:-540}
bash .whl/install.sh || exit 1
export PYTHONPATH=/tmp/site MUJOCO_GL=disable PYTHONUNBUFFERED=1 PYTHON=python3
REPO=$PWD W=/tmp/w
mkdir -p "$W" "$OUT"
collect() { # evaluations and logs back, never checkpoints
    (cd "$W" && find runs -name 'events.out.tfevents*' -o -name DONE | tar czf "$OUT/runs.tgz" -T - logs sweep68.txt sweep67.txt 2>/dev/null)
    { date +%T; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader; } >>"$OUT/nvidia_smi.txt" 2>&1
}
{
    nvidia-smi --query-gpu=name,driver_version,memory.total,memory.free --format=csv
    python3 -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'numpy', numpy.__version__)"
    grep -m1 "model name" /proc/cpuinfo; nproc; git log -1 --format=%h 2>/dev/null
} >"$OUT/machine.txt" 2>&1
if [ ! -e "$W/started" ]; then
    touch "$W/started"
    echo dm_control-cartpole-swingup-v0__td3__1__100000 >"$W/skip.txt"
    echo get_server_list | nvidia-cuda-mps-control >/dev/null 2>&1 || nvidia-cuda-mps-control -d
    (cd "$W" && setsid nohup bash -c "bash $REPO/benchmark.sh --gpu --algos td3 oparl --env-ids dm_control/cartpole-swingup-v0 \
        --seeds 1 2 3 --total-timesteps 100000 --skip-listed skip.txt >sweep68.txt 2>&1" >/dev/null 2>&1 &)
    (cd "$W" && setsid nohup bash -c "bash $REPO/benchmark.sh --gpu --algos oparl --env-ids dm_control/walker-run-v0 \
        dm_control/cheetah-run-v0 Ant-v4 --seeds 1 2 3 --total-timesteps 100000 -- --critic-style td3 >sweep67.txt 2>&1" >/dev/null 2>&1 &)
    sleep 5
    timeout $((BUDGET - SECONDS - 200)) python3 -m pytest -p no:cacheprovider -n 6 tests/test_cudagraphs.py tests/test_reliability.py \
        -k "cudagraphs or cuda" -q --durations=10 2>&1 | tee "$OUT/gpu_tests.txt" | tail -n 25
fi
while (($(ls "$W"/runs/*/DONE 2>/dev/null | wc -l) < 14 && SECONDS < BUDGET - 40)); do collect; sleep 20; done
collect
echo "runs done: $(ls "$W"/runs/*/DONE 2>/dev/null | wc -l) of 14 at ${SECONDS} s"
tail -n 3 "$W"/sweep68.txt "$W"/sweep67.txt
if (($(ls "$W"/runs/*/DONE 2>/dev/null | wc -l) == 14 && SECONDS < BUDGET - 150)) && [ ! -e "$W/speed_done" ]; then
    touch "$W/speed_done"
    timeout $((BUDGET - SECONDS - 10)) python3 tools/speed/throughput.py "td3 --cudagraphs" ".before/td3_continuous_action.py --cudagraphs" \
        "oparl --cudagraphs" ".before/oparl_continuous_action.py --cudagraphs" \
        "oparl --cudagraphs --num-seeds 4" ".before/oparl_continuous_action.py --cudagraphs --num-seeds 4" \
        --cuda --window --env-id Hopper-v4 --learning-starts 1000 --steps 3000 --warmup 1000 --repeats 2 \
        --csv "$OUT/critic_speed.csv" 2>&1 | tee "$OUT/critic_speed.txt" | tail -n 15
fi
collect
