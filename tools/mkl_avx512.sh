#!/usr/bin/env bash
# Run a command with MKL's AVX-512 matrix kernels on an AMD CPU.
#
#   bash tools/mkl_avx512.sh python oparl_continuous_action.py --env-id Hopper-v4
#   bash tools/mkl_avx512.sh bash benchmark.sh --algos oparl td3 sac ...   # every run of the sweep
#
# PyTorch's CPU wheels do float32 matmuls with Intel MKL, which takes its AVX-512 code path only on
# CPUs it identifies as Intel; on AMD CPUs with AVX-512 (Zen 4, Zen 5) it falls back to AVX2 and
# runs the matmuls at about half the speed the CPU can do. MKL asks one function whether the CPU is
# Intel; this wrapper builds a three-line shared library that answers yes and preloads it, so MKL
# picks its kernels by the CPU's instruction sets instead. The results are float32 matmuls with
# another summation order: they differ from the AVX2 kernels' in the last bits, as results do from
# one machine to another. The bfloat16 matmuls (--bf16) go through oneDNN and do not change.
#
# On any other CPU, or without a C compiler, the command runs unchanged (with a note on stderr).
# The library is built once into build/ (or $MKL_AVX512_BUILD_DIR).
set -euo pipefail

if (($# == 0)); then
  echo "usage: bash tools/mkl_avx512.sh COMMAND [ARGS...]" >&2
  exit 2
fi

cpu_vendor=$(grep -m1 '^vendor_id' /proc/cpuinfo 2>/dev/null | awk '{print $3}' || true)
cpu_flags=$(grep -m1 '^flags' /proc/cpuinfo 2>/dev/null || true)
if [[ $cpu_vendor != AuthenticAMD || $cpu_flags != *avx512f* ]]; then
  echo "mkl_avx512: not an AMD CPU with AVX-512 (${cpu_vendor:-unknown vendor}); running the command unchanged" >&2
  exec "$@"
fi

build_dir=${MKL_AVX512_BUILD_DIR:-"$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/build"}
library="$build_dir/libmkl_intel_cpu_true.so"
if [[ ! -f $library ]]; then
  compiler=$(command -v cc || command -v gcc || command -v clang || true)
  if [[ -z $compiler ]]; then
    echo "mkl_avx512: no C compiler (cc, gcc or clang) to build the library; running the command unchanged" >&2
    exec "$@"
  fi
  mkdir -p "$build_dir"
  source_file=$(mktemp --suffix=.c)
  # MKL's own answer to "is this an Intel CPU?", replaced: it then selects kernels by CPUID features
  printf 'int mkl_serv_intel_cpu_true(void) { return 1; }\n' >"$source_file"
  "$compiler" -shared -fPIC -O2 -o "$library.tmp.$$" "$source_file"
  rm -f "$source_file"
  mv "$library.tmp.$$" "$library"
fi

# one line on stderr, so that a run's log records which kernels it used
echo "mkl_avx512: MKL's AVX-512 kernels (preloading $library)" >&2
export LD_PRELOAD="$library${LD_PRELOAD:+:$LD_PRELOAD}"
exec "$@"
