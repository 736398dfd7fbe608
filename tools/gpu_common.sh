# Sourced by tools/gpu_seed_scaling.sh and tools/gpu_speed.sh (not run alone): their budget, their steps and
# the machine's description. Reads OUT (default gpu_out), BUDGET (seconds, default 540) and the first argument
# (FIRST_STEP, default 1); writes $OUT/machine.txt and appends to $OUT/log.txt.
OUT=${OUT:-gpu_out}
BUDGET=${BUDGET:-540}
FIRST=${1:-1}
mkdir -p "$OUT"
LOG=$OUT/log.txt
export PYTHONUNBUFFERED=1
n=0
step() { # step SECONDS_IT_NEEDS "command": runs the command if it fits the budget, within what is left
    n=$((n + 1))
    local need=$1 command=$2
    if ((n < FIRST)); then return; fi
    if ((SECONDS + need > BUDGET)); then
        echo "step $n skipped (needs ~${need} s, $((BUDGET - SECONDS)) s left): $command" | tee -a "$LOG"
        return
    fi
    echo "== step $n at ${SECONDS} s: $command" | tee -a "$LOG"
    timeout $((BUDGET - SECONDS)) bash -c "$command" >>"$LOG" 2>&1 || echo "step $n failed ($?): $command" | tee -a "$LOG"
}
{
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
    python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
    grep -m1 "model name" /proc/cpuinfo
    nproc
    pin=$(sed -n 's/^numpy==//p' requirements.txt)
    python -c "import numpy, sys; v = numpy.__version__; print('numpy', v, '' if v == sys.argv[1] else '(requirements.txt pins ' + sys.argv[1] + ')')" "$pin"
} >"$OUT/machine.txt" 2>&1
