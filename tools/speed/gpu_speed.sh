#!/usr/bin/env bash
# One-seed GPU speed beside CleanRL (docs/speed.md, "GPU: --cudagraphs"), in order of priority within a budget:
# 1. CleanRL's TD3 and SAC and our td3, sac, oparl and redq --cudagraphs on Hopper-v4, 3 repeats interleaved, each
#    run timed by tools/speed/throughput.py --window (one process start per run; CleanRL's cumulative charts/SPS is read
#    by its events' times): $OUT/speed.csv;
# 2-5. td3, oparl, sac and redq --cudagraphs in the host's view (tools/speed/phase_times.py --no-sync), with acting's copy
#    of the observations as it is and as it was before commit e4d8b37 (--blocking-copy, which waits for the
#    replaying update), four runs in the order now, before, before, now: compare their whole step (the wait moves
#    between phases): $OUT/phases.csv;
# 6. ours on cartpole-swingup (CleanRL's scripts do not run DeepMind Control tasks);
# 7-9. where a step's time goes in td3, oparl and redq --cudagraphs, each phase timed with the GPU synchronised at
#    its start and end, so that a graph's replay is charged its kernels.
# $OUT is, on the device machine, the folder that comes back (default here: gpu_out); $OUT/log.txt says what ran.
# Measured on an H200 (2026-11-26): step 1 took 359 s (budgeted 400), steps 2-5 46, 53, 54 and 74 s; 6-9 need about 340 s;
# each call starts from the step the log says the last one stopped before:
#     BUDGET=570 bash tools/speed/gpu_speed.sh [FIRST_STEP]
# CLEANRL (default .cleanrl): a folder holding CleanRL's cleanrl/{td3,sac}_continuous_action.py and cleanrl_utils/
# at the commit docs/speed.md names, e.g. `mkdir .cleanrl && git -C ../cleanrl archive fe8d8a0
# cleanrl/td3_continuous_action.py cleanrl/sac_continuous_action.py cleanrl_utils | tar -x -C .cleanrl && echo fe8d8a0
# > .cleanrl/COMMIT` (list it in .git/info/exclude and carry it); without it only our scripts are timed.
set -u
source "$(dirname "$0")/gpu_common.sh"   # OUT, BUDGET, FIRST_STEP, LOG, step, $OUT/machine.txt
ASKED=${CLEANRL:-.cleanrl}
CLEANRL=$(cd "$ASKED" 2>/dev/null && pwd)
echo "cleanrl: ${CLEANRL:-none} at commit $(cat "$CLEANRL/COMMIT" 2>/dev/null || echo unknown)" >>"$OUT/machine.txt"
export CSV=$OUT/speed.csv PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$CLEANRL
export CLEANRL C=$CLEANRL/cleanrl
speed() { # speed ENV_ID REPEATS [cleanrl]: every entry once per repeat, interleaved; one 1000-step window per run
    local entries=("td3 --cudagraphs" "oparl --cudagraphs" "sac --cudagraphs" "redq --cudagraphs")
    if [ "${3:-}" = cleanrl ] && [ -n "$CLEANRL" ]; then
        entries=("$C/td3_continuous_action.py" "${entries[@]}" "$C/sac_continuous_action.py")
    fi
    python tools/speed/throughput.py "${entries[@]}" --env-id "$1" --cuda --window --learning-starts 500 --steps 1500 \
        --repeats "$2" --csv "$CSV" --label mps=off
}
phases() { # phases SCRIPT ENV_ID [STEPS [FLAGS]]: ms per training step by phase, after 500 random and 300 warm-up steps
    python tools/speed/phase_times.py "$1" --env-id "$2" --cudagraphs --learning-starts 500 --total-timesteps "${3:-3000}" \
        --eval-frequency 1000000000 --eval-episodes 1 --warmup-updates 300 --csv "$OUT/phases.csv" "${@:4}"
}
ab() { # ab SCRIPT [STEPS]: the host's view, acting's copy as it is (A) and as before (B), in the order A B B A
    local run
    for run in "" --blocking-copy --blocking-copy ""; do
        phases "$1" Hopper-v4 "${2:-1500}" --no-sync $run || return
    done
}
export -f speed phases ab

[ -n "$CLEANRL" ] || echo "no CleanRL folder ($ASKED): our scripts only" | tee -a "$LOG"
mps off   # one process at a time: no MPS (a daemon an earlier call of gpu_seed_scaling.sh left on is stopped)
step 400 "speed Hopper-v4 3 cleanrl"
step 60 "ab td3"
step 60 "ab oparl"
step 60 "ab sac"
step 100 "ab redq 1100"
step 240 "speed dm_control/cartpole-swingup-v0 3"
step 30 "phases td3 Hopper-v4"
step 30 "phases oparl Hopper-v4"
step 40 "phases redq Hopper-v4 1500"
echo "done at ${SECONDS} s" | tee -a "$LOG"
