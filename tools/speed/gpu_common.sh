# Sourced by tools/speed/gpu_seed_scaling.sh and tools/speed/gpu_speed.sh (not run alone): their budget, their steps,
# MPS and the machine's description. Reads OUT (default gpu_out), BUDGET (seconds, default 540), the first argument
# (FIRST_STEP, default 1), MPS_STATE and MPS_SETTLE (see mps; tests/test_gpu_scripts.py sets them); writes
# $OUT/machine.txt and appends to $OUT/log.txt.
OUT=${OUT:-gpu_out}
BUDGET=${BUDGET:-540}
FIRST=${1:-1}
mkdir -p "$OUT"
LOG=$OUT/log.txt
export PYTHONUNBUFFERED=1
n=0
STOPPED=0
fits() { ((SECONDS + $1 <= BUDGET)); } # fits SECONDS_IT_NEEDS: whether that much is left of the budget
run_step() { # run_step LABEL SECONDS_IT_NEEDS "command": runs the command within what is left of the budget
    echo "== $1 at ${SECONDS} s: $3" | tee -a "$LOG"
    timeout $((BUDGET - SECONDS)) bash -c "$3" >>"$LOG" 2>&1 || echo "$1 failed ($?): $3" | tee -a "$LOG"
}
step() { # step SECONDS_IT_NEEDS "command": runs the command if it fits the budget; the first step that does not fit
    # stops the list (the later ones are not run out of order), and the log names it
    n=$((n + 1))
    if ((n < FIRST || STOPPED)); then return; fi
    if ! fits "$1"; then
        STOPPED=1
        echo "stopped before step $n (needs ~$1 s, $((BUDGET - SECONDS)) s left): run again with FIRST_STEP $n" | tee -a "$LOG"
        return
    fi
    run_step "step $n" "$@"
}
again() { # again SECONDS_IT_NEEDS "command": a step of every call, whatever FIRST_STEP (the single-seed baseline
    # that a call's rows are read beside); not numbered, and skipped, not stopping the list, when it does not fit
    if ((STOPPED)); then return; fi
    if ! fits "$1"; then
        echo "skipped (needs ~$1 s, $((BUDGET - SECONDS)) s left): $2" | tee -a "$LOG"
        return
    fi
    run_step "every call" "$@"
}
MPS_STATE=${MPS_STATE:-/tmp/mps_state} MPS_SETTLE=${MPS_SETTLE:-2}
export MPS_STATE MPS_SETTLE
mps() { # mps on|off: starts or stops the MPS daemon when that changes its state (kept in $MPS_STATE, which a fresh
    # machine lacks: off), then waits MPS_SETTLE seconds; every script ends with it off
    [ "$1" = "$(cat "$MPS_STATE" 2>/dev/null || echo off)" ] && return 0
    if [ "$1" = on ]; then
        nvidia-cuda-mps-control -d
    else
        echo quit | nvidia-cuda-mps-control
    fi
    echo "$1" >"$MPS_STATE"
    sleep "$MPS_SETTLE"
}
export -f mps
trap 'mps off' EXIT
# the GPU's name for tools/speed/throughput.py's CSV, asked once here instead of in every timed step
GPU_NAME=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -n 1)
export GPU_NAME
{
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
    python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
    grep -m1 "model name" /proc/cpuinfo
    nproc
    pin=$(sed -n 's/^numpy==//p' requirements.txt)
    python -c "import numpy, sys; v = numpy.__version__; print('numpy', v, '' if v == sys.argv[1] else '(requirements.txt pins ' + sys.argv[1] + ')')" "$pin"
} >"$OUT/machine.txt" 2>&1
