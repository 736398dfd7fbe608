#!/usr/bin/env bash
# Many seeds on one GPU: agent-steps/s of oparl, td3 and sac --cudagraphs with N seeds in one process, and of
# K processes x N seeds with and without MPS, each timed by tools/throughput.py --window (the charts/SPS of
# 1000-step windows after warm-up: start-up, the random phase, graph recording and evaluations excluded).
# Steps run in order of priority and each appends to $OUT/scaling.csv (its label column says whether MPS ran),
# so a lease that ends early still leaves the steps before it. Each shape runs once; the list needs about
# 1,100 s, more than one call: run it again from FIRST_STEP (on a warm machine, or a fresh one: the MPS steps
# start MPS themselves). On the device machine $OUT is the folder that comes back (default here: gpu_out):
#     BUDGET=540 bash tools/gpu_seed_scaling.sh [FIRST_STEP]
# BUDGET: seconds; a step that would not fit is skipped and named in $OUT/log.txt. Needs CUDA, MPS (nvidia-cuda-mps-control) and the NumPy that
# requirements.txt pins: carry its wheel (docs/sweeps.md, "One GPU"); under NumPy 2.5 dm-control writes a
# DeprecationWarning at every environment step (a few us each and megabytes of log).
set -u
source "$(dirname "$0")/gpu_common.sh"   # OUT, BUDGET, FIRST_STEP, LOG, step, $OUT/machine.txt
CSV=$OUT/scaling.csv
time_it() { # time_it ENV_ID ENTRY [STEPS]: one run of the entry (500 random steps, then STEPS), its windows appended to the CSV
    local mps=mps=off
    pgrep -x nvidia-cuda-mps >/dev/null && mps=mps=on
    python tools/throughput.py "$2" --env-id "$1" --cuda --window --learning-starts 500 --steps "${3:-2500}" --repeats 1 \
        --csv "$CSV" --label "$mps"
}
mps() { # mps on|off
    if [ "$1" = on ]; then
        pgrep -x nvidia-cuda-mps >/dev/null || nvidia-cuda-mps-control -d
    else
        echo quit | nvidia-cuda-mps-control
    fi
    sleep 2
}
export -f time_it mps
export CSV
E=${E:-dm_control/cartpole-swingup-v0}
G=${G---cudagraphs}

step 15 "python tools/env_cost.py $E dm_control/walker-walk-v0 > $OUT/env_cost.md"
step 60 "python -m pytest tests/test_cudagraphs.py -q -x -p no:cacheprovider -k 'syncs and 3]'"
step 25 "time_it $E 'oparl $G'"
step 5 "mps on"
step 60 "time_it $E '16x:oparl $G --num-seeds 16' 1500"
step 50 "time_it $E '8x:oparl $G --num-seeds 16'"
step 45 "time_it $E '16x:oparl $G --num-seeds 8'"
step 70 "time_it $E '8x:oparl $G --num-seeds 32' 1500"
step 40 "time_it $E '16x:oparl $G'"
step 5 "mps off"
step 50 "time_it $E '8x:oparl $G --num-seeds 16'"
step 25 "time_it $E 'td3 $G'"
step 25 "time_it $E 'sac $G'"
step 25 "time_it $E 'oparl $G --num-seeds 4'"
step 35 "time_it $E 'oparl $G --num-seeds 16'"
step 70 "time_it $E 'oparl $G --num-seeds 64' 1500"
step 5 "mps on"
step 60 "time_it $E '16x:td3 $G --num-seeds 16' 1500"
step 60 "time_it $E '16x:sac $G --num-seeds 16' 1500"
step 70 "time_it dm_control/walker-walk-v0 '16x:oparl $G --num-seeds 16' 1500"
step 5 "mps off"
step 25 "time_it $E 'td3 $G --num-seeds 4'"
step 25 "time_it $E 'sac $G --num-seeds 4'"
step 35 "time_it $E 'td3 $G --num-seeds 16'"
step 35 "time_it $E 'sac $G --num-seeds 16'"
step 70 "time_it $E 'td3 $G --num-seeds 64' 1500"
step 70 "time_it $E 'sac $G --num-seeds 64' 1500"
echo "done at ${SECONDS} s" | tee -a "$LOG"
