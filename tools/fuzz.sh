#!/usr/bin/env bash
# Builds the libFuzzer targets (tests/fuzz, clang 14, ASan + UBSan), writes their seed corpora
# from real data (../shared, never committed) and runs them. docs/fuzzing.md.
#
#   tools/fuzz.sh [--seconds N] [TARGET...]   short runs: N seconds per target (default 60), two
#                                             targets at a time; what CI's "Fuzzing" stage runs
#   tools/fuzz.sh --long [TARGET...]          long runs: each target until 1e7 executions or one
#                                             hour (nice -n 19), logs in --log-dir
# Options:
#   --build-dir DIR   default build-fuzz
#   --jobs J          targets run at once (default: the number of cores, at most 2)
#   --log-dir DIR     where --long writes its logs (default build-fuzz/fuzz-long)
#   --runs N          --long: executions per target (default 10000000)
#   --max-seconds N   --long: seconds per target (default 3600)
#   --no-build        use the targets already built
#
# Corpora: build-fuzz/fuzz-seeds/<target> (regenerated every time) and build-fuzz/fuzz-corpus/
# <target> (what the fuzzers found, kept between runs). A crash, leak, timeout or out-of-memory
# fails the script; the input is kept in build-fuzz/fuzz-artifacts/<target>/ and the script
# prints the command that reproduces it.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD

targets_all=(fuzz_codec fuzz_map_settings fuzz_server_config fuzz_vocabulary_binary
  fuzz_vocabulary_dbow2_text fuzz_float_vocabulary fuzz_observation fuzz_image fuzz_eval_dataset)
build=build-fuzz
seconds=60
long=0
build_step=1
runs=10000000
max_seconds=3600
jobs=$(nproc)
((jobs > 2)) && jobs=2
log_dir=""
targets=()
while (($#)); do
  case "$1" in
    --seconds) seconds=$2; shift 2 ;;
    --long) long=1; shift ;;
    --build-dir) build=$2; shift 2 ;;
    --jobs) jobs=$2; shift 2 ;;
    --log-dir) log_dir=$2; shift 2 ;;
    --runs) runs=$2; shift 2 ;;
    --max-seconds) max_seconds=$2; shift 2 ;;
    --no-build) build_step=0; shift ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    fuzz_*) targets+=("$1"); shift ;;
    *) echo "tools/fuzz.sh: unknown argument $1 (--help)" >&2; exit 2 ;;
  esac
done
((${#targets[@]})) || targets=("${targets_all[@]}")
build=$(realpath -m "$build")

if ((build_step)); then
  # -O1 with line tables: quick to build, fast enough to fuzz, stack traces with lines.
  cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
    -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -gline-tables-only" -DCMAKE_CXX_COMPILER=clang++-14 \
    -DPLACEDB_FUZZ=ON -DPLACEDB_WERROR=ON -DPLACEDB_BUILD_TESTS=OFF -DPLACEDB_BUILD_BENCH=OFF \
    >/dev/null
  cmake --build "$build" -j "$(nproc)" --target placedb_fuzz_targets
fi

seeds=$build/fuzz-seeds
rm -rf "$seeds"
"$build/tests/fuzz/placedb-fuzz-seeds" "$seeds" "$root/server/placedb.yaml"

# Sanitizers stop at the first report; OpenCV stays on one thread (libFuzzer runs one input at a
# time, and thread pools only add noise to the coverage).
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:abort_on_error=0:allocator_may_return_null=0}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-halt_on_error=1:print_stacktrace=1}
export OPENCV_FOR_THREADS_NUM=1

dictionary() {
  case "$1" in
    fuzz_image|fuzz_observation) echo "$root/tests/fuzz/image.dict" ;;
    *) [[ -f $seeds/$1.dict ]] && echo "$seeds/$1.dict" ;;
  esac
  return 0
}

# run_target TARGET LOG: one libFuzzer run; its exit status is the verdict.
run_target() {
  local target=$1 log=$2
  local corpus=$build/fuzz-corpus/$target artifacts=$build/fuzz-artifacts/$target
  local binary=$build/tests/fuzz/$target
  if ((long)); then
    # A copy of the binary, seeds and corpus of its own: rebuilding or short runs meanwhile do
    # not disturb an hour-long run.
    corpus=$log_dir/corpus/$target
    artifacts=$log_dir/artifacts/$target
    binary=$log_dir/bin/$target
  fi
  mkdir -p "$corpus" "$artifacts"
  local args=(-timeout=10 -rss_limit_mb=2048 -max_len=16384 -print_final_stats=1
    "-artifact_prefix=$artifacts/")
  local dict
  dict=$(dictionary "$target")
  [[ -n $dict ]] && args+=("-dict=$dict")
  if ((long)); then
    args+=("-runs=$runs" "-max_total_time=$max_seconds")
  else
    args+=("-max_total_time=$seconds")
  fi
  # The first directory receives new inputs; the seeds are only read.
  local command=("$binary" "${args[@]}" "$corpus" "$seeds/$target")
  if ((long)); then command=(nice -n 19 "${command[@]}"); fi
  "${command[@]}" </dev/null >"$log" 2>&1
}

# summary TARGET LOG STATUS: one line from libFuzzer's final stats.
summary() {
  local target=$1 log=$2 status=$3
  local execs cov corpus secs
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1) || true
  cov=$( (grep -o 'cov: [0-9]*' "$log" || true) | tail -1 | cut -d' ' -f2)
  corpus=$( (grep -o 'corp: [0-9]*/[0-9a-zA-Z]*' "$log" || true) | tail -1 | cut -d' ' -f2)
  secs=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1) || true
  printf '%-28s %s  executions %-10s exec/s %-7s coverage %-6s corpus %s\n' "$target" \
    "$([[ $status == 0 ]] && echo ok || echo FAILED)" "${execs:-?}" "${secs:-?}" "${cov:-?}" \
    "${corpus:-?}"
}

if ((long)); then
  [[ -n $log_dir ]] || log_dir=$build/fuzz-long
else
  log_dir=$build/fuzz-logs
fi
mkdir -p "$log_dir"
if ((long)); then
  mkdir -p "$log_dir/bin"
  for target in "${targets[@]}"; do cp "$build/tests/fuzz/$target" "$log_dir/bin/"; done
  rm -rf "$log_dir/seeds"
  cp -r "$seeds" "$log_dir/seeds"
  seeds=$log_dir/seeds
fi
echo "fuzzing ${#targets[@]} targets, $jobs at a time, logs in $log_dir"

# A simple job pool: at most $jobs targets at once, each verdict in $log_dir/<target>.status.
running=0
for target in "${targets[@]}"; do
  rm -f "$log_dir/$target.status"
  ( set +e; run_target "$target" "$log_dir/$target.log"; echo $? >"$log_dir/$target.status" ) &
  running=$((running + 1))
  if ((running >= jobs)); then wait -n || true; running=$((running - 1)); fi
done
wait

failed=0
for target in "${targets[@]}"; do
  status=$(cat "$log_dir/$target.status" 2>/dev/null || echo 1)
  summary "$target" "$log_dir/$target.log" "$status"
  if [[ $status != 0 ]]; then
    failed=1
    echo "---- $target: last lines of $log_dir/$target.log"
    tail -n 40 "$log_dir/$target.log"
    if ((long)); then artifacts=$log_dir/artifacts/$target; else artifacts=$build/fuzz-artifacts/$target; fi
    for artifact in "$artifacts"/*; do
      [[ -e $artifact ]] || continue
      echo "reproduce: OPENCV_FOR_THREADS_NUM=1 $build/tests/fuzz/$target $artifact"
    done
  fi
done
exit $failed
