#!/usr/bin/env bash
# Sweep algorithms x tasks x seeds, here (--workers runs at a time, one torch thread each) or as one
# Slurm job array (--slurm), a process per run or per N consecutive seeds (--seeds-per-process N).
# Re-running the same sweep skips finished runs and resumes the others from their checkpoints. Run
# `bash benchmark.sh --help` for the flags.
set -uo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
PAPER_DMC=(
  dm_control/ball_in_cup-catch-v0 dm_control/cartpole-balance-v0 dm_control/cartpole-balance_sparse-v0
  dm_control/cartpole-swingup-v0 dm_control/cheetah-run-v0 dm_control/finger-spin-v0 dm_control/fish-swim-v0
  dm_control/fish-upright-v0 dm_control/hopper-stand-v0 dm_control/pendulum-swingup-v0 dm_control/point_mass-easy-v0
  dm_control/reacher-easy-v0 dm_control/reacher-hard-v0 dm_control/swimmer-swimmer6-v0 dm_control/swimmer-swimmer15-v0
  dm_control/walker-run-v0 dm_control/walker-stand-v0 dm_control/walker-walk-v0
)
PAPER_MUJOCO=(Ant-v4 Hopper-v4 Humanoid-v4 Walker2d-v4)

usage() {
  cat <<EOF
Usage: bash benchmark.sh [flags] [-- flags passed to every script]

  --algos A [A ...]         scripts by short name, {A}_continuous_action.py: oparl td3 sac redq ppo rnd ebd,
                            or any other such file (default: oparl td3 sac)
  --env-ids E [E ...]       environment ids (default: the paper's 18 DeepMind Control tasks)
  --suite dmc|mujoco        the paper's 18 DMC tasks or its 4 MuJoCo tasks (Ant, Hopper, Humanoid, Walker2d -v4)
  --seeds S [S ...]         seeds (default: 1 2 3 4 5 6 7 8 9 10)
  --seeds-per-process N     train up to N consecutive seeds of a task and algorithm in one process, the script's
                            --num-seeds (oparl td3 sac redq; default: 1, a process per run)
  --total-timesteps N       steps per run (default: each script's default, 1000000)
  --workers N               runs at a time here, one torch thread each (default: number of cores, $(nproc))
  --checkpoint-frequency N  checkpoint every N steps, so an interrupted run resumes (default: 10000)
  --skip-listed FILE        runs named in FILE (one name a line, e.g. results/finished_runs.txt) count as
                            finished: how a sweep continues on a machine that lacks their runs/ folders
  --gpu                     the sweep on this machine's one CUDA GPU, at the shape measured fastest: up to 16 seeds
                            a process (unless --seeds-per-process is given; 1 for a script without --num-seeds), the
                            processes sharing the GPU under MPS (started here if it is not running; it stays on),
                            each with --cudagraphs where its script takes it (not part of the run names: a run
                            is the same run on a CPU); refused in one line, before anything starts, when the
                            processes that run at once would not fit the GPU's free memory (tools/gpu_fit.py)
  --dry-run                 print the commands (or the Slurm job script) and run nothing
  --slurm                   submit the sweep as one Slurm job array, one run (one process) per array task
  --slurm-partition P       sbatch --partition
  --slurm-time T            sbatch --time (e.g. 2-00:00:00)
  --slurm-cpus-per-task N   sbatch --cpus-per-task (default: 1)
  --slurm-extra LINE        an extra '#SBATCH LINE' (repeatable), e.g. --slurm-extra '--mem=8G'
  -h, --help                this help

Runs are named {env}__{algo}__{seed}__{steps}[__{extra flags}] ('/' in the env id written '-'):
TensorBoard logs go to runs/{name}/, each run's output to logs/{name}.log. A finished run is marked
runs/{name}/DONE and skipped next time; an unfinished one resumes from runs/{name}/checkpoint.pt, or
starts again if it had none. A run that another sweep is running (it holds logs/{name}.lock) is
left alone, so two sweeps over overlapping lists can share one folder. One failing run doesn't stop
the others; the summary lists failures and the exit status is non-zero if any run failed.

With --seeds-per-process N, each task and algorithm's unfinished seeds are split into groups of at most
N consecutive seeds (a gap starts a new group), a process each. The runs keep their names and folders;
a group's output goes to its first run's log, and every run's log gets the line 'seeds per process: <n>
(output in logs/<first run>.log)'. Skipping, resuming (from the first run's checkpoint) and locks are
per group; the counts are per run. Resume a sweep with the N it started with.

Example: bash benchmark.sh --algos td3 oparl --env-ids dm_control/cartpole-balance-v0 --seeds 1 2 \\
           --workers 2 --total-timesteps 2000 -- --learning-starts 1000
EOF
}

die() { echo "error: $*" >&2; exit 2; }

# The name of a run: every input that changes its result.
run_name() {  # algo env seed total extra...
  local algo=$1 env=$2 seed=$3 total=$4; shift 4
  local name="${env//\//-}__${algo}__${seed}__${total}"
  if (($#)); then
    local extra="$*"
    extra="${extra//--/}"
    extra="${extra// /_}"
    extra="${extra//[^A-Za-z0-9_.=-]/-}"
    if ((${#extra} > 120)); then extra="$(printf '%s' "$*" | sha1sum | cut -c1-12)"; fi
    name="${name}__${extra}"
  fi
  printf '%s' "$name"
}

# Whether a run counts as finished: marked DONE, or named in --skip-listed's file.
finished() { [[ -f runs/$1/DONE ]] || { [[ -n ${SKIP_LISTED:-} ]] && grep -qxF "$1" "$SKIP_LISTED"; }; }

# The run names of a process's seeds: SEED alone, or FIRST-LAST for the seeds a --seeds-per-process group trains.
group_names() {  # array algo env seed|first-last total extra...
  local -n group_out=$1
  local algo=$2 env=$3 seed=$4 total=$5 s; shift 5
  if [[ $seed != *-* ]]; then group_out=("$(run_name "$algo" "$env" "$seed" "$total" "$@")"); return; fi
  group_out=()
  for ((s = ${seed%-*}; s <= ${seed#*-}; s++)); do group_out+=("$(run_name "$algo" "$env" "$s" "$total" "$@")"); done
}

# Whether a script takes --cudagraphs (what --gpu adds where it can).
takes_cudagraphs() { grep -q '^ *cudagraphs: bool' "$REPO/${1}_continuous_action.py"; }

# The training command of one process (what run_one runs and --dry-run prints): its script, seed, steps, run name,
# checkpoints and the flags passed on, resuming from its first run's checkpoint if it has one.
train_command() {  # array algo env seed|first-last total checkpoint_frequency [--] extra...
  local -n command_out=$1
  local algo=$2 env=$3 seed=$4 total=$5 ckpt=$6 names=(); shift 6
  [[ ${1:-} == "--" ]] && shift
  group_names names "$algo" "$env" "$seed" "$total" "$@"
  local steps=() seed_flags=() resume=() template=${names[0]}
  [[ $total != default ]] && steps=(--total-timesteps "$total")
  # several seeds: --num-seeds, and the run name with {seed} where each seed's number goes
  if ((${#names[@]} > 1)); then
    seed_flags=(--num-seeds "${#names[@]}")
    template="$(run_name "$algo" "$env" "{seed}" "$total" "$@")"
  fi
  [[ -f runs/${names[0]}/checkpoint.pt ]] && resume=(--resume "runs/${names[0]}")
  local gpu_flags=()  # --gpu: recorded updates, where the script takes them; a run's name is the same on a CPU
  [[ -n ${GPU_SWEEP:-} ]] && takes_cudagraphs "$algo" && gpu_flags=(--cudagraphs)
  command_out=("${PYTHON:-python}" "$REPO/${algo}_continuous_action.py" --env-id "$env" --seed "${seed%-*}" "${seed_flags[@]}"
    "${steps[@]}" --run-name "$template" --checkpoint-frequency "$ckpt" "$@" "${gpu_flags[@]}" "${resume[@]}")
}

# One run, or one process training the consecutive seeds FIRST-LAST (--seeds-per-process), skipped if finished,
# resumed if it has a checkpoint (a group: its first run's, which names the others). Prints one word: done,
# skipped, busy, failed.
run_one() {  # algo env seed|first-last total checkpoint_frequency [-- extra...]
  local algo=$1 env=$2 seed=$3 total=$4 ckpt=$5; shift 5
  [[ ${1:-} == "--" ]] && shift
  local names=() name unfinished=()
  group_names names "$algo" "$env" "$seed" "$total" "$@"
  for name in "${names[@]}"; do finished "$name" || unfinished+=("$name"); done
  if ((${#unfinished[@]} == 0)); then echo skipped; return 0; fi
  mkdir -p logs
  # one process per run: a second sweep over the same folder (or a re-submitted Slurm task) leaves a
  # run alone while another holds its lock; the training process inherits the lock and keeps it
  # (util-linux's flock; without it runs are not locked). A group takes every one of its runs' locks.
  if command -v flock >/dev/null; then
    local lock
    for name in "${names[@]}"; do
      exec {lock}>>"logs/$name.lock"
      if ! flock -n "$lock"; then echo busy; return 0; fi
    done
  fi
  local dir="runs/${names[0]}" log="logs/${names[0]}.log"
  if ((${#unfinished[@]} < ${#names[@]})); then  # another sweep finished some of them after this one grouped them
    echo "error: runs of this process finished elsewhere meanwhile; run the sweep again to group the others anew" >>"$log"
    echo failed
    return 0
  fi
  if [[ ! -f $dir/checkpoint.pt ]]; then
    for name in "${names[@]}"; do rm -rf "runs/$name"; done  # a run that died before its first checkpoint starts again
  fi
  # which float32 matmul kernels this part of the run uses (tools/mkl_avx512.sh preloads its library), for
  # results/mkl_kernels.csv; a resumed run appends a second line
  local kernels=mkl-default
  [[ ${LD_PRELOAD:-} == *libmkl_intel_cpu_true* ]] && kernels=mkl-avx512
  if [[ -n ${GPU_SWEEP:-} ]]; then  # --gpu: the GPU's, recorded as CUDA graphs where the script takes --cudagraphs
    kernels=cuda
    takes_cudagraphs "$algo" && kernels=cuda-cudagraphs
  fi
  for name in "${names[@]}"; do
    echo "float32 kernels: $kernels" >>"logs/$name.log"
    if ((${#names[@]} > 1)); then echo "seeds per process: ${#names[@]} (output in $log)" >>"logs/$name.log"; fi
  done
  local command=()
  train_command command "$algo" "$env" "$seed" "$total" "$ckpt" "$@"
  if OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 "${command[@]}" >>"$log" 2>&1; then
    for name in "${names[@]}"; do touch "runs/$name/DONE"; done
    echo done
  else
    echo failed
  fi
}

if [[ ${1:-} == "--run-one" ]]; then  # one run of a sweep: what each worker or Slurm array task executes
  shift
  run_one "$@"
  exit 0
fi

algos=(oparl td3 sac)
env_ids=("${PAPER_DMC[@]}")
seeds=(1 2 3 4 5 6 7 8 9 10)
seeds_per_process=1 seeds_per_process_given=0
gpu=0
total=default
workers=$(nproc)
checkpoint_frequency=10000
dry_run=0
slurm=0
slurm_partition="" slurm_time="" slurm_cpus=1
slurm_extra=()
extra=()

values() {  # the values after a multi-value flag, up to the next flag
  local -n out=$1; shift
  out=()
  while (($#)) && [[ $1 != -* ]]; do out+=("$1"); shift; done
  ((${#out[@]})) || die "$flag needs at least one value"
}
count_values() { local n=0; while (($#)) && [[ $1 != -* ]]; do n=$((n + 1)); shift; done; echo "$n"; }
need_int() { [[ $2 =~ ^[0-9]+$ ]] && (($2 > 0)) || die "$1 must be a positive integer, got '$2'"; }

while (($#)); do
  flag=$1
  case $flag in
    -h | --help) usage; exit 0 ;;
    --algos) shift; values algos "$@"; shift $(count_values "$@") ;;
    --env-ids) shift; values env_ids "$@"; shift $(count_values "$@") ;;
    --seeds) shift; values seeds "$@"; shift $(count_values "$@") ;;
    --seeds-per-process) need_int "$flag" "${2:-}"; seeds_per_process=$2; seeds_per_process_given=1; shift 2 ;;
    --suite)
      case ${2:-} in
        dmc) env_ids=("${PAPER_DMC[@]}") ;;
        mujoco) env_ids=("${PAPER_MUJOCO[@]}") ;;
        *) die "--suite takes dmc or mujoco, got '${2:-}'" ;;
      esac
      shift 2 ;;
    --total-timesteps) need_int "$flag" "${2:-}"; total=$2; shift 2 ;;
    --workers) need_int "$flag" "${2:-}"; workers=$2; shift 2 ;;
    --checkpoint-frequency) need_int "$flag" "${2:-}"; checkpoint_frequency=$2; shift 2 ;;
    --skip-listed)
      [[ -f ${2:-} ]] || die "--skip-listed: no such file '${2:-}'"
      SKIP_LISTED="$(cd "$(dirname "$2")" && pwd)/$(basename "$2")"; export SKIP_LISTED; shift 2 ;;
    --dry-run) dry_run=1; shift ;;
    --gpu) gpu=1; shift ;;
    --slurm) slurm=1; shift ;;
    --slurm-partition) slurm_partition=${2:?--slurm-partition needs a value}; shift 2 ;;
    --slurm-time) slurm_time=${2:?--slurm-time needs a value}; shift 2 ;;
    --slurm-cpus-per-task) need_int "$flag" "${2:-}"; slurm_cpus=$2; shift 2 ;;
    --slurm-extra) slurm_extra+=("${2:?--slurm-extra needs a value}"); shift 2 ;;
    --) shift; extra=("$@"); break ;;
    *) die "unknown flag '$flag' (see --help)" ;;
  esac
done

for algo in "${algos[@]}"; do
  [[ -f $REPO/${algo}_continuous_action.py ]] || die "unknown algorithm '$algo': no $REPO/${algo}_continuous_action.py"
done
for seed in "${seeds[@]}"; do [[ $seed =~ ^[0-9]+$ ]] || die "seeds must be non-negative integers, got '$seed'"; done
((gpu && slurm)) && die "--gpu runs the sweep on this machine's GPU, not as a Slurm array (--slurm: ask for GPUs with --slurm-extra, and pass '-- --cudagraphs' to the scripts that take it)"
if ((gpu)); then
  export GPU_SWEEP=1  # train_command adds --cudagraphs where a script takes it
  if ((!seeds_per_process_given)); then
    seeds_per_process=16
    for algo in "${algos[@]}"; do  # every script of the sweep must train many seeds a process, else one a process
      grep -q '^ *num_seeds: int' "$REPO/${algo}_continuous_action.py" &&
        ! grep -q '(args.num_seeds == 1, "' "$REPO/${algo}_continuous_action.py" || seeds_per_process=1
    done
  fi
fi
if ((seeds_per_process > 1)); then
  for algo in "${algos[@]}"; do
    grep -q '^ *num_seeds: int' "$REPO/${algo}_continuous_action.py" ||
      die "--seeds-per-process $seeds_per_process: ${algo}_continuous_action.py has no --num-seeds (one seed per process)"
    # a script that has the flag but refuses more than one seed says so in check_args
    ! grep -q '(args.num_seeds == 1, "' "$REPO/${algo}_continuous_action.py" ||
      die "--seeds-per-process $seeds_per_process: ${algo}_continuous_action.py trains one seed per process (its --num-seeds check)"
  done
fi

PYTHON="$(command -v "${PYTHON:-python}")" || die "no python on PATH (activate the virtual environment first)"
export PYTHON

# one line per run (per process: with --seeds-per-process, a group of runs): the arguments of run_one
runs=()
sizes=()           # each line's number of runs
skipped_before=()  # with --seeds-per-process, the runs found finished while grouping
if ((seeds_per_process == 1)); then
  for env in "${env_ids[@]}"; do
    for seed in "${seeds[@]}"; do
      for algo in "${algos[@]}"; do
        runs+=("$(printf '%q ' "$algo" "$env" "$seed" "$total" "$checkpoint_frequency" -- "${extra[@]}")")
        sizes+=(1)
      done
    done
  done
else
  # each task and algorithm's unfinished seeds, in the given order, in groups of at most N consecutive ones
  # (written FIRST-LAST; a gap or a seed written with leading zeros starts a new group); the algorithms take
  # turns, as the seeds do with one per process
  for env in "${env_ids[@]}"; do
    declare -A group=()
    most=0
    for algo in "${algos[@]}"; do
      k=-1 first="" last=""
      for seed in "${seeds[@]}"; do
        name="$(run_name "$algo" "$env" "$seed" "$total" "${extra[@]}")"
        if finished "$name"; then skipped_before+=("$name"); continue; fi
        if ! [[ -n $first && $first == "$((10#$first))" && $seed == "$((10#$last + 1))" ]] ||
          ((seed - first >= seeds_per_process)); then
          k=$((k + 1)) first=$seed
        fi
        last=$seed
        group[$algo,$k]=$first
        [[ $last != "$first" ]] && group[$algo,$k]=$first-$last
      done
      ((k + 1 > most)) && most=$((k + 1))
    done
    for ((k = 0; k < most; k++)); do
      for algo in "${algos[@]}"; do
        [[ -n ${group[$algo,$k]:-} ]] || continue
        seed=${group[$algo,$k]}
        runs+=("$(printf '%q ' "$algo" "$env" "$seed" "$total" "$checkpoint_frequency" -- "${extra[@]}")")
        if [[ $seed == *-* ]]; then sizes+=($((${seed#*-} - ${seed%-*} + 1))); else sizes+=(1); fi
      done
    done
    unset group
  done
fi
n=${#runs[@]}
n_runs=0
for size in "${sizes[@]}"; do n_runs=$((n_runs + size)); done

if ((slurm && n == 0)); then
  echo "nothing to submit: the sweep's ${#skipped_before[@]} runs are all finished"
  exit 0
fi
if ((slurm)); then
  sweep_dir="slurm/$(date +%Y%m%d-%H%M%S)-$$"
  script="#!/usr/bin/env bash
#SBATCH --job-name=oparl-sweep
#SBATCH --array=0-$((n - 1))
#SBATCH --cpus-per-task=$slurm_cpus
#SBATCH --output=$PWD/logs/slurm-%A_%a.out"
  [[ -n $slurm_partition ]] && script+=$'\n'"#SBATCH --partition=$slurm_partition"
  [[ -n $slurm_time ]] && script+=$'\n'"#SBATCH --time=$slurm_time"
  for line in "${slurm_extra[@]}"; do script+=$'\n'"#SBATCH $line"; done
  script+="
cd $(printf '%q' "$PWD")
export PYTHON=$(printf '%q' "$PYTHON") SKIP_LISTED=$(printf '%q' "${SKIP_LISTED:-}")
args=\$(sed -n \"\$((SLURM_ARRAY_TASK_ID + 1))p\" $(printf '%q' "$PWD/$sweep_dir/runs.txt"))
eval \"bash $(printf '%q' "$REPO/benchmark.sh") --run-one \$args\""
  if ((dry_run)); then
    echo "$script"
    printf '%s\n' "${runs[@]}" | sed 's/^/# run: /'
    exit 0
  fi
  mkdir -p "$sweep_dir" logs
  printf '%s\n' "${runs[@]}" >"$sweep_dir/runs.txt"
  echo "$script" >"$sweep_dir/job.sh"
  sbatch "$sweep_dir/job.sh" || die "sbatch failed"
  if ((seeds_per_process == 1)); then
    echo "submitted $n runs as one array job ($sweep_dir/job.sh); each run's output: logs/<run name>.log"
  else
    echo "submitted $n_runs runs in $n processes as one array job ($sweep_dir/job.sh), ${#skipped_before[@]} finished" \
      "before; each process's output: logs/<its first run's name>.log"
  fi
  exit 0
fi

# each process's training command, as run_one would run it now; a finished run as a comment
plan() {
  local args names left name line command
  for name in "${skipped_before[@]}"; do echo "# finished: $name"; done
  for args in "${runs[@]}"; do
    eval "set -- $args"
    group_names names "$1" "$2" "$3" "$4" "${@:7}"
    left=()
    for name in "${names[@]}"; do finished "$name" && echo "# finished: $name" || left+=("$name"); done
    ((${#left[@]})) || continue
    train_command command "$@"
    line=$(printf '%q ' "${command[@]}")
    echo "${line% }"
  done
}

if ((gpu)) && ! command -v nvidia-smi >/dev/null; then  # no GPU to check against: a preview only
  if ((!dry_run)); then
    echo "error: --gpu trains on this machine's CUDA GPU, and there is no nvidia-smi here (--dry-run previews the sweep)" >&2
    exit 2
  fi
  echo "dry run: no nvidia-smi here, so the GPU memory check (tools/gpu_fit.py) is left to the real run" >&2
elif ((gpu)); then  # the processes that run at once must fit the GPU's free memory
  plan | "$PYTHON" "$REPO/tools/gpu_fit.py" --workers "$workers" >&2 || exit 2
fi
if ((dry_run)); then
  plan
  exit 0
fi
if ((gpu)) && command -v nvidia-cuda-mps-control >/dev/null && ! echo get_server_list | nvidia-cuda-mps-control >/dev/null 2>&1; then
  nvidia-cuda-mps-control -d && echo "MPS started (it stays on: 'echo quit | nvidia-cuda-mps-control' stops it)"
fi

mkdir -p logs
status_dir="$(mktemp -d)"
trap 'rm -rf "$status_dir"' EXIT
started=0
last_progress="runs: 0 finished, 0 running, $n_runs left"  # not printed: the first line is after a launch
progress() {  # prints when the counts (of runs, not processes) changed
  local finished=0 line status i
  for status in "$status_dir"/*.status; do
    [[ -f $status ]] || continue
    i=${status##*/}
    finished=$((finished + sizes[${i%.status}]))
  done
  line="runs: $finished finished, $((started - finished)) running, $((n_runs - started)) left"
  [[ $line == "$last_progress" ]] || echo "[$(date +%H:%M:%S)] $line"
  last_progress=$line
}
for i in "${!runs[@]}"; do
  while (($(jobs -rp | wc -l) >= workers)); do wait -n; progress; done
  progress  # a run that ended before the check above is counted before the next one starts
  # a stopped sweep took $status_dir with it (its EXIT trap); its running runs still finish and write their DONE
  (result=$(eval "run_one ${runs[$i]}"); { echo "$result" >"$status_dir/$i.status"; } 2>/dev/null) &
  started=$((started + sizes[i]))
  progress
done
while (($(jobs -rp | wc -l) > 0)); do wait -n; progress; done
progress  # the last line, also when the last run ended before the check above

done_runs=() skipped_runs=("${skipped_before[@]}") busy_runs=() failed_runs=()
declare -A log_of=()  # a run's process's log: its group's first run's
for i in "${!runs[@]}"; do
  eval "set -- ${runs[$i]}"
  group_names names "$1" "$2" "$3" "$4" "${@:7}"
  status=$(cat "$status_dir/$i.status")
  for name in "${names[@]}"; do
    log_of[$name]="logs/${names[0]}.log"
    case $status in
      done) done_runs+=("$name") ;;
      skipped) skipped_runs+=("$name") ;;
      busy) busy_runs+=("$name") ;;
      *) failed_runs+=("$name") ;;
    esac
  done
done
echo "summary: ${#done_runs[@]} done, ${#skipped_runs[@]} skipped (finished before), ${#failed_runs[@]} failed"
for name in "${busy_runs[@]}"; do echo "  left alone, running in another sweep: $name (log: logs/$name.log)"; done
for name in "${failed_runs[@]}"; do echo "  failed: $name (log: ${log_of[$name]})"; done
((${#failed_runs[@]} == 0))
