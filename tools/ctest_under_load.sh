#!/usr/bin/env bash
# Runs the whole ctest suite N times in a row while `placedb load` drives a placedb-server beside
# it (issue 34: CI runs beside other work, so the suite must hold on a loaded machine). Prints one
# line per run (passed/failed counts, seconds, the machine's load) and `name value unit` lines at
# the end; exits non-zero when any run failed. The load: 2 agents ingesting CamVid JPEGs with
# matches, a quarter of the frames as queries, into a temporary map of a server on its own data
# directory and loopback ports; restarted whenever a pass over the frames ends.
#
#   tools/ctest_under_load.sh [--runs N] [--build-dir DIR] [--ctest-args "..."]
#
# Needs a built tree (tools/test.sh's build-test by default) and ../shared/data (the CamVid frames).
set -euo pipefail
cd "$(dirname "$0")/.."

runs=5
build_dir=build-test
ctest_args=""
while (($#)); do
  case "$1" in
    --runs) runs=$2; shift 2 ;;
    --build-dir) build_dir=$2; shift 2 ;;
    --ctest-args) ctest_args=$2; shift 2 ;;
    -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
    *) echo "ctest_under_load.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done

frames=../shared/data/camvid/images
[ -d "$frames" ] || { echo "ctest_under_load.sh: $frames is missing" >&2; exit 2; }
for binary in "$build_dir/server/placedb-server" "$build_dir/client/placedb"; do
  [ -x "$binary" ] || { echo "ctest_under_load.sh: $binary is missing: build first" >&2; exit 2; }
done

work=$(mktemp -d /tmp/placedb-ctest-load.XXXXXX)
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
server_pid=""
load_pid=""
cleanup() {
  [ -n "$load_pid" ] && kill "$load_pid" 2>/dev/null || true
  [ -n "$server_pid" ] && kill "$server_pid" 2>/dev/null || true
  wait 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT

"$build_dir/server/placedb-server" --listen "127.0.0.1:$port" --data-dir "$work/data" \
  --metrics-listen off --console-listen off --detector-model off \
  --vocabulary "default=$PWD/var/vocabulary/default.pdbv" >"$work/server.log" 2>&1 &
server_pid=$!
# Ready when it answers health (a deadline, not a fixed sleep).
for _ in $(seq 1 300); do
  if "$build_dir/client/placedb" --address "127.0.0.1:$port" health >/dev/null 2>&1; then break; fi
  kill -0 "$server_pid" 2>/dev/null || { cat "$work/server.log" >&2; exit 1; }
  sleep 0.2
done
"$build_dir/client/placedb" --address "127.0.0.1:$port" health >/dev/null

(
  while true; do
    "$build_dir/client/placedb" --address "127.0.0.1:$port" load "$frames" --agents 2 \
      --matches --query-ratio 0.25 --max-source-frames 200 --frames 100000000 --duration 60 \
      >>"$work/load.log" 2>&1 || sleep 1
  done
) &
load_pid=$!

failed_runs=0
total_seconds=0
for run in $(seq 1 "$runs"); do
  start=$SECONDS
  # shellcheck disable=SC2086
  if ctest --test-dir "$build_dir" -j "$(nproc)" --timeout 1500 --output-on-failure $ctest_args \
      >"$work/ctest-$run.log" 2>&1; then
    outcome=passed
  else
    outcome=FAILED
    failed_runs=$((failed_runs + 1))
    cp "$work/ctest-$run.log" "/tmp/placedb-ctest-under-load-$run.log"
  fi
  seconds=$((SECONDS - start))
  total_seconds=$((total_seconds + seconds))
  summary=$(grep -E '^[0-9]+% tests passed' "$work/ctest-$run.log" || echo "no summary")
  echo "run $run: $outcome in ${seconds} s: $summary (load $(cut -d' ' -f1-3 /proc/loadavg))"
  grep -E '^\s+[0-9]+ - .*\((Failed|Timeout|SEGFAULT|Subprocess aborted|Child aborted)' \
    "$work/ctest-$run.log" || true
done
kill "$load_pid" 2>/dev/null || true
echo "ctest_under_load_runs $runs runs"
echo "ctest_under_load_failed_runs $failed_runs runs"
echo "ctest_under_load_mean_seconds $((total_seconds / runs)) s"
# Each load session's "result   N frames in Ss: R frames/s" line.
grep -E '^  result' "$work/load.log" | awk '{ frames += $2; n++ } END {
  printf "ctest_under_load_load_sessions %d sessions\nctest_under_load_load_frames %d frames\n", n, frames }'
echo "ctest_under_load_load_sessions_with_errors $(grep -E '^  errors ' "$work/load.log" | grep -vc ' none$' || true) sessions"
((failed_runs == 0))
