#!/usr/bin/env bash
# Many seeds on one GPU: agent-steps/s of oparl, td3 and sac --cudagraphs with N seeds in one process, and of
# K processes x N seeds with and without MPS, each timed by tools/speed/throughput.py --window (the charts/SPS of
# 1000-step windows after warm-up: start-up, the random phase, graph recording and evaluations excluded).
# Steps run in order of priority and each appends to $OUT/scaling.csv (its label column says whether MPS ran;
# each timing step sets MPS as it needs it), so a lease that ends early still leaves the steps before it. Each
# shape runs once; the whole list needs about 1,500 s of steps, from step 16 about 800 s, two calls (more than one
# session's 15 minutes of device time): the log names the step a call stopped before; run it again from there
# (FIRST_STEP), on a warm machine or a fresh one. On the device machine $OUT is the folder that comes back
# (default here: gpu_out):
#     BUDGET=540 bash tools/speed/gpu_seed_scaling.sh [FIRST_STEP]
# BUDGET: seconds. Needs CUDA, MPS (nvidia-cuda-mps-control) and the NumPy that requirements.txt pins: carry its
# wheel (docs/sweeps.md, "One GPU"); under NumPy 2.5 dm-control writes a DeprecationWarning at every environment
# step (a few us each and megabytes of log).
set -u
source "$(dirname "$0")/gpu_common.sh"   # OUT, BUDGET, FIRST_STEP, LOG, step, $OUT/machine.txt
CSV=$OUT/scaling.csv
time_it() { # time_it on|off ENV_ID ENTRY [STEPS]: MPS on or off, then one run of the entry (500 random steps, then
    # STEPS), its windows appended to the CSV
    mps "$1"
    python tools/speed/throughput.py "$3" --env-id "$2" --cuda --window --learning-starts 500 --steps "${4:-2500}" \
        --repeats 1 --csv "$CSV" --label "mps=$1"
}
export -f time_it
export CSV
E=${E:-dm_control/cartpole-swingup-v0}
G=${G---cudagraphs}

step 15 "python tools/speed/env_cost.py $E dm_control/walker-walk-v0 > $OUT/env_cost.md"
step 60 "python -m pytest tests/test_cudagraphs.py -q -x -p no:cacheprovider -k 'syncs and 3]'"
again 25 "time_it off $E 'oparl $G'"   # the one-seed baseline, in every call
step 60 "time_it on $E '16x:oparl $G --num-seeds 16' 1500"
step 50 "time_it on $E '8x:oparl $G --num-seeds 16'"
step 45 "time_it on $E '16x:oparl $G --num-seeds 8'"
step 70 "time_it on $E '8x:oparl $G --num-seeds 32' 1500"
step 40 "time_it on $E '16x:oparl $G'"
step 70 "time_it off $E '8x:oparl $G --num-seeds 16'"
step 25 "time_it off $E 'td3 $G'"
step 25 "time_it off $E 'sac $G'"
step 25 "time_it off $E 'oparl $G --num-seeds 4'"
step 45 "time_it off $E 'oparl $G --num-seeds 16'"
step 95 "time_it off $E 'oparl $G --num-seeds 64' 1500"
step 60 "time_it on $E '16x:td3 $G --num-seeds 16' 1500"
step 60 "time_it on $E '16x:sac $G --num-seeds 16' 1500"
# steps 3-15 ran on 2026-11-26 (results/gpu/h200_session_2026-11-26b; the step estimates above are from its log); steps
# 16-18 were added after it, so its log's "step 16" is walker-walk, now step 19. The next session starts here, at step 16
# (steps 1-2 alone: FIRST_STEP 1 with BUDGET=80)
step 60 "time_it on $E '16x:oparl $G --num-seeds 16' 1500"   # the highest figure of step 3, a second run
# bfloat16 matmuls: the lever, not the float32 goal (never run under graphs on a GPU: a failure is logged, the list goes on)
step 60 "time_it on $E '16x:oparl $G --num-seeds 16 --bf16' 1500"
step 90 "time_it on $E '16x:oparl $G --num-seeds 32' 1500"
step 70 "time_it on dm_control/walker-walk-v0 '16x:oparl $G --num-seeds 16' 1500"
step 25 "time_it off $E 'td3 $G --num-seeds 4'"
step 25 "time_it off $E 'sac $G --num-seeds 4'"
step 45 "time_it off $E 'td3 $G --num-seeds 16'"
step 45 "time_it off $E 'sac $G --num-seeds 16'"
step 95 "time_it off $E 'td3 $G --num-seeds 64' 1500"
step 95 "time_it off $E 'sac $G --num-seeds 64' 1500"
step 60 "time_it on $E '16x:oparl $G --num-seeds 16' 1500"   # a third run of the best shape, and of TD3's and SAC's
step 60 "time_it on $E '16x:td3 $G --num-seeds 16' 1500"
step 60 "time_it on $E '16x:sac $G --num-seeds 16' 1500"
echo "done at ${SECONDS} s" | tee -a "$LOG"
