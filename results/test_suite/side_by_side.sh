#!/usr/bin/env bash
# Two short TD3 runs side by side against one alone, under each thread setting: with more threads than cores,
# OpenMP's default (spinning) wait is what makes the side-by-side pair slow. Run from the repository's root with
# its virtual environment active: bash results/test_suite/side_by_side.sh (TRIES=3 tries of each, by default)
set -euo pipefail
repo=$(pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
run() {
  (cd "$work" && python "$repo/td3_continuous_action.py" --env-id Hopper-v4 --total-timesteps 600 --learning-starts 300 \
    --batch-size 64 --eval-frequency 600 --eval-episodes 1 --run-name "$1" >/dev/null 2>&1)
}
seconds() { local start=$(date +%s.%N); "$@"; echo "$(date +%s.%N) - $start" | bc; }
pair() { run "$1a" & run "$1b" & wait; }
echo "try,setting,alone_s,two_side_by_side_s"
for try in $(seq "${TRIES:-3}"); do
  for setting in "OMP_NUM_THREADS=1" "OMP_NUM_THREADS=2" "OMP_NUM_THREADS=2 OMP_WAIT_POLICY=PASSIVE"; do
    export OMP_NUM_THREADS=1; unset OMP_WAIT_POLICY
    export $setting
    name=$(echo "$setting" | tr ' =' '__')_$try
    echo "$try,$setting,$(seconds run "alone_$name"),$(seconds pair "pair_$name")"
  done
done
