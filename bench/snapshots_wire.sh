#!/usr/bin/env bash
# Snapshots through the server and the CLI (issue 15, "Benchmark"): what the wire adds to the core
# figures of `placedb-bench-storage --only snapshots`. That benchmark builds a map of N places
# (default 10k) in a data directory and is told to keep it; server A serves that directory, server
# B an empty one, both on loopback, plaintext, no tokens. Then, timed from the CLI's start to its
# exit: `placedb snapshots create` on A, `download` from A to a file, `upload` of the file to B,
# `restore` on B. Prints the core figures, then `name value unit` lines for the four commands and
# the archive's bytes. The machine's load is printed first: a shared machine's figures compare
# only within one run.
#
#   bench/snapshots_wire.sh [--places 10000] [--vocabulary FILE] [--build DIR] [--shared DIR]
#
# Defaults: vocabulary var/vocabulary/default.pdbv, build dir build/ (PLACEDB_BUILD_DIR), shared
# data ../shared (PLACEDB_SHARED_DIR). Needs jq.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
places=10000
vocabulary="$repo/var/vocabulary/default.pdbv"
build="${PLACEDB_BUILD_DIR:-$repo/build}"
shared="${PLACEDB_SHARED_DIR:-$repo/../shared}"
while (($#)); do
  case "$1" in
    --places) places="$2"; shift 2 ;;
    --vocabulary) vocabulary="$2"; shift 2 ;;
    --build) build="$2"; shift 2 ;;
    --shared) shared="$2"; shift 2 ;;
    -h|--help) sed -n '2,14p' "$0"; exit 0 ;;
    *) echo "snapshots_wire.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
command -v jq >/dev/null || { echo "snapshots_wire.sh: needs jq" >&2; exit 2; }
server="$build/server/placedb-server"
cli="$build/client/placedb"
bench="$build/bench/placedb-bench-storage"
for binary in "$server" "$cli" "$bench"; do
  [[ -x "$binary" ]] || { echo "snapshots_wire.sh: $binary is not built" >&2; exit 2; }
done

# shellcheck source=bench/servers_cleanup.sh
source "$(dirname "${BASH_SOURCE[0]}")/servers_cleanup.sh"

echo "# $(uptime)"
echo "# $(nproc) cores; $places places"
"$bench" --vocabulary "$vocabulary" --shared "$shared" --dir "$work/core" --only snapshots \
  --snapshot-places "$places" --keep 1

free_port() {
  python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}
# start NAME PORT DATA_DIR: a server on loopback; waits until it answers.
start() {
  local name="$1" port="$2" data="$3"
  "$server" --listen "127.0.0.1:$port" --metrics-listen off --console-listen off --data-dir "$data" \
    --vocabulary "default=$vocabulary" --log-level warn >"$work/$name.log" 2>&1 &
  pids+=($!)
  for _ in $(seq 240); do
    if "$cli" --timeout 2 --address "127.0.0.1:$port" health >/dev/null 2>&1; then return 0; fi
    sleep 0.5
  done
  echo "snapshots_wire.sh: server $name did not start:" >&2
  cat "$work/$name.log" >&2
  exit 1
}
port_a="$(free_port)"
port_b="$(free_port)"
start a "$port_a" "$work/core/snapshot-source"
start b "$port_b" "$work/b"
a=(--address "127.0.0.1:$port_a")
b=(--address "127.0.0.1:$port_b")

# timed NAME COMMAND...: runs it with stdout to $work/NAME.json, prints NAME's seconds.
timed() {
  local name="$1"
  shift
  local start end
  start="$(date +%s.%N)"
  "$@" >"$work/$name.json"
  end="$(date +%s.%N)"
  echo "$name $(echo "$end - $start" | bc -l | awk '{ printf "%.4g", $1 }') s"
}
timed cli_snapshot_create "$cli" "${a[@]}" --json snapshots create m
id="$(jq -r .id "$work/cli_snapshot_create.json")"
timed cli_snapshot_download "$cli" "${a[@]}" --json snapshots download "$id" "$work/m.pdbsnap"
echo "cli_snapshot_archive_bytes $(stat -c %s "$work/m.pdbsnap") bytes"
timed cli_snapshot_upload "$cli" "${b[@]}" --json snapshots upload "$work/m.pdbsnap"
uploaded="$(jq -r .id "$work/cli_snapshot_upload.json")"
timed cli_snapshot_restore "$cli" "${b[@]}" --json snapshots restore "$uploaded" m
places_b="$("$cli" "${b[@]}" --json maps show m | jq -r ".stats.places // empty")"
echo "# restored map on B: ${places_b:-?} places"
