#!/usr/bin/env bash
# Measures placedb-server's memory and CPU under a small, bounded load on loopback: the figures
# behind the k8s resource requests (deploy/README.md, "Resources").
#
#   deploy/testing/measure-resources.sh SERVER_BINARY VOCABULARY IMAGE_DIR [FRAMES] [STREAMS]
#       [QUERIES] [-- SERVER_FLAGS...]
#
# e.g. with server-side detection (new maps then default to box_source SERVER):
#   deploy/testing/measure-resources.sh build/server/placedb-server var/vocabulary/default.pdbv \
#       ../shared/data/camvid/images 300 2 100 -- --detector-model var/models/yolox_nano.onnx
#
# Starts the server with 2 workers on free 127.0.0.1 ports and an empty temporary data
# directory, then runs deploy/testing/grpc_probe.py load (STREAMS Ingest streams splitting FRAMES
# frames of IMAGE_DIR, then QUERIES queries) and reports RSS (idle, after the load, peak) and
# CPU (cores used on average during the load), then stops the server with SIGTERM.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
positional=()
while (($#)) && [[ "$1" != "--" ]]; do
  positional+=("$1")
  shift
done
(($#)) && shift  # the "--"
server_flags=("$@")
if ((${#positional[@]} < 3)); then
  sed -n '2,16p' "$0"
  exit 2
fi
server="$(readlink -f "${positional[0]}")"
vocabulary="$(readlink -f "${positional[1]}")"
images="$(readlink -f "${positional[2]}")"
frames="${positional[3]:-300}"
streams="${positional[4]:-2}"
queries="${positional[5]:-100}"

work="$(mktemp -d)"
pid=""
cleanup() {
  if [[ -n "$pid" ]] && kill -0 "$pid" 2>/dev/null; then
    kill -TERM "$pid"
    wait "$pid" || true
  fi
  rm -rf "$work"
}
trap cleanup EXIT

port() { /usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
grpc="$(port)"
metrics="$(port)"
"$server" --listen "127.0.0.1:$grpc" --metrics-listen "127.0.0.1:$metrics" \
  --console-listen off \
  --data-dir "$work/data" --vocabulary "default=$vocabulary" --threads 2 --log-level warn \
  "${server_flags[@]}" >"$work/server.log" 2>&1 &
pid=$!

rss_mib() { awk '/^VmRSS:/ { printf "%.0f", $2 / 1024 }' "/proc/$pid/status"; }
hwm_mib() { awk '/^VmHWM:/ { printf "%.0f", $2 / 1024 }' "/proc/$pid/status"; }
cpu_ticks() { awk '{ print $14 + $15 }' "/proc/$pid/stat"; }
hz="$(getconf CLK_TCK)"

/usr/bin/python3 "$here/grpc_probe.py" health "127.0.0.1:$grpc" --wait 120 >/dev/null
sleep 1
idle_rss="$(rss_mib)"
ticks0="$(cpu_ticks)"
start="$(date +%s.%N)"
/usr/bin/python3 "$here/grpc_probe.py" load "127.0.0.1:$grpc" --proto-root "$repo" \
  --map measure --images "$images" --frames "$frames" --streams "$streams" --queries "$queries"
end="$(date +%s.%N)"
ticks1="$(cpu_ticks)"
loaded_rss="$(rss_mib)"
peak_rss="$(hwm_mib)"
disk="$(du -sm "$work/data" | cut -f1)"
cores="$(awk -v t=$((ticks1 - ticks0)) -v hz="$hz" -v s="$start" -v e="$end" \
  'BEGIN { printf "%.2f", t / hz / (e - s) }')"
cpu_s="$(awk -v t=$((ticks1 - ticks0)) -v hz="$hz" 'BEGIN { printf "%.1f", t / hz }')"
echo "measure: RSS idle ${idle_rss} MiB, after load ${loaded_rss} MiB, peak ${peak_rss} MiB;" \
  "CPU ${cpu_s} s over the load = ${cores} cores on average (2 workers);" \
  "data dir ${disk} MiB; $(nproc) cores here"
