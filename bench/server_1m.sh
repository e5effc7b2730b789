#!/usr/bin/env bash
# Verified queries and ingest through the server against a map of a million places (issue 31,
# goals 3 and 4). `placedb-bench-storage --only server-map` builds the map (CamVid's even frames
# stored whole, filler up to N places from views of Debian's sample images with 32 features
# each; the map verifies its 10 best candidates exhaustively and re-ranks them: see that
# benchmark's section 3c). One placedb-server on loopback (plaintext, no tokens) serves it; then:
#   1. cold: the page cache dropped (when this user may: root) and the server just started, one
#      placedb-load pass of the odd CamVid frames as 1000-ORB JPEG queries, one in flight;
#   2. warm: the same pass again;
#   3. ingest with matches (search + verification + store) of the same frames, 2 agents;
#   4. the server restarted with the frequent-word skip (search.max_word_share 0.03), a warm-up
#      pass, then a measured warm pass: the same-run baseline of the exact search.
# Prints `name value unit` lines: query latency p50/p99 (client round trip) and the server's
# per-stage p50/p99 for each pass, ingest frames/s, the server's reopen time and memory (VmRSS),
# the map's bytes on disk. The machine's load is printed first: on a shared machine the figures
# compare only within one run.
#
#   bench/server_1m.sh [--places 1000000] [--dir DIR] [--vocabulary FILE] [--build DIR]
#                      [--shared DIR]
#
# --dir keeps the map there (built when missing, reused otherwise: building 1M places takes
# ~10 minutes); without it the map is built in a temporary directory and removed. Defaults:
# vocabulary var/vocabulary/default.pdbv, build dir build/ (PLACEDB_BUILD_DIR), shared data
# ../shared (PLACEDB_SHARED_DIR). Needs jq.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
places=1000000
map_dir=""
vocabulary="$repo/var/vocabulary/default.pdbv"
build="${PLACEDB_BUILD_DIR:-$repo/build}"
shared="${PLACEDB_SHARED_DIR:-$repo/../shared}"
while (($#)); do
  case "$1" in
    --places) places="$2"; shift 2 ;;
    --dir) map_dir="$2"; shift 2 ;;
    --vocabulary) vocabulary="$2"; shift 2 ;;
    --build) build="$2"; shift 2 ;;
    --shared) shared="$2"; shift 2 ;;
    -h|--help) sed -n '2,22p' "$0"; exit 0 ;;
    *) echo "server_1m.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
command -v jq >/dev/null || { echo "server_1m.sh: needs jq" >&2; exit 2; }
server="$build/server/placedb-server"
cli="$build/client/placedb"
load="$build/client/placedb-load"
bench="$build/bench/placedb-bench-storage"
for binary in "$server" "$cli" "$load" "$bench"; do
  [[ -x "$binary" ]] || { echo "server_1m.sh: $binary is not built" >&2; exit 2; }
done

# shellcheck source=bench/servers_cleanup.sh
source "$(dirname "${BASH_SOURCE[0]}")/servers_cleanup.sh"
[[ -n "$map_dir" ]] || map_dir="$work/data"

echo "# $(uptime)"
echo "# $(nproc) cores; $places places in $map_dir"
if [[ -d "$map_dir/maps" ]]; then
  echo "# reusing the map in $map_dir (its size is checked once served)"
else
  "$bench" --vocabulary "$vocabulary" --shared "$shared" --dir "$map_dir" --only server-map \
    --reopen "$places" --keep 1
fi

# The queries: CamVid's odd frames (the map holds the even ones).
find "$shared/data/camvid/images" -name '*.png' -o -name '*.jpg' | sort | awk 'NR % 2 == 0' \
  >"$work/queries.txt"
echo "# $(wc -l <"$work/queries.txt") query frames (CamVid, odd positions)"

if sync && echo 3 >/proc/sys/vm/drop_caches 2>/dev/null; then
  echo "# page cache dropped"
else
  echo "# page cache NOT dropped (not permitted): the cold pass may find the map's files cached"
fi
# start_server [CONFIG]: placedb-server on a free loopback port serving the map (CONFIG: a YAML
# file, else the defaults); waits until it answers and prints its start-up time. The budget must
# exceed what the process holds once the map is open (the 1M map's index alone is ~3.7 GB; the
# default 1 GiB refuses to start, saying so).
start_server() {
  local config=()
  [[ -n "${1:-}" ]] && config=(--config "$1")
  local port
  port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
  local start
  start="$(date +%s.%N)"
  "$server" "${config[@]}" --listen "127.0.0.1:$port" --metrics-listen off --console-listen off \
    --data-dir "$map_dir" --vocabulary "default=$vocabulary" --log-level warn \
    --memory-budget-bytes "$((12 << 30))" >"$work/server.log" 2>&1 &
  server_pid=$!
  pids+=("$server_pid")
  address=(--address "127.0.0.1:$port")
  local ready=""
  for _ in $(seq 1200); do
    if "$cli" --timeout 2 "${address[@]}" health >/dev/null 2>&1; then ready=1; break; fi
    kill -0 "$server_pid" 2>/dev/null || break
    sleep 0.5
  done
  if [[ -z "$ready" ]]; then
    echo "server_1m.sh: the server did not start:" >&2
    cat "$work/server.log" >&2
    exit 1
  fi
  echo "server_start_to_healthy $(echo "$(date +%s.%N) - $start" | bc -l | awk '{ printf "%.4g", $1 }') s"
}
stop_server() {
  kill -TERM "$server_pid"
  wait "$server_pid" || true
}
rss() { awk '/^VmRSS:/ { printf "%.4g", $2 * 1024 }' "/proc/$server_pid/status"; }

start_server
echo "server_rss_after_open $(rss) bytes"
"$cli" "${address[@]}" --json maps show big >"$work/map.json"
served="$(jq -r '.stats.places' "$work/map.json")"
echo "map_places $served places"
# Each run's ingest pass adds its frames: a kept map grows a little from run to run.
if ((served < places)); then
  echo "server_1m.sh: the map in $map_dir holds $served places, fewer than $places (remove it)" >&2
  exit 1
fi
echo "map_bytes_on_disk $(du -sb "$map_dir" | cut -f1) bytes"

# report PASS FILE: the query (or ingest) latency and the server's stages of one pass.
report() {
  local pass="$1" file="$2" rpc="$3"
  jq -r --arg pass "$pass" --arg rpc "$rpc" '
    .rpc[$rpc] as $r
    | "\($pass)_\($rpc)_ok \($r.ok) count",
      "\($pass)_\($rpc)_errors \($r.errors) count",
      "\($pass)_\($rpc)_per_second \($r.per_s) frames/s",
      "\($pass)_\($rpc)_latency_p50 \($r.latency_ms.p50) ms",
      "\($pass)_\($rpc)_latency_p99 \($r.latency_ms.p99) ms",
      ($r.stages_ms | to_entries[] | select(.value.p99 > 0)
       | "\($pass)_\($rpc)_stage_\(.key)_p50 \(.value.p50) ms",
         "\($pass)_\($rpc)_stage_\(.key)_p99 \(.value.p99) ms")' "$file"
}
for pass in cold warm; do
  "$load" "${address[@]}" --map big --query-ratio 1 --agents 1 "$work/queries.txt" \
    --json-out "$work/$pass.json" >"$work/$pass.txt"
  report "$pass" "$work/$pass.json" query
  echo "server_rss_after_${pass}_queries $(rss) bytes"
done
"$load" "${address[@]}" --map big --matches --agents 2 "$work/queries.txt" \
  --json-out "$work/ingest.json" >"$work/ingest.txt"
report matches "$work/ingest.json" ingest
echo "server_rss_after_ingest $(rss) bytes"

# The same-run baseline for the search: the server with the frequent-word skip (an option, the
# default before 29 Nov 2026: docs/index.md), one warm-up pass, then the measured pass.
stop_server
printf 'search:\n  max_word_share: 0.03\n' >"$work/skip.yaml"
start_server "$work/skip.yaml"
"$load" "${address[@]}" --map big --query-ratio 1 --agents 1 "$work/queries.txt" >/dev/null
"$load" "${address[@]}" --map big --query-ratio 1 --agents 1 "$work/queries.txt" \
  --json-out "$work/skip.json" >"$work/skip.txt"
report skip_words_over_3pct_warm "$work/skip.json" query
