#!/usr/bin/env bash
# The cost of transport security and token checks (issue 14, "Benchmark"): one run starts two
# placedb-servers on loopback with the same data-dir layout and the same settings, A = plaintext
# without tokens and B = TLS (certificate made here with openssl) + a tokens file holding one admin
# token (only its SHA-256, computed with sha256sum), and runs the load tester with precomputed
# features (--mode features: the server only searches and stores, so transport and auth costs
# show most) against each, alternating A/B/A/B for a few rounds. Prints `name value unit` lines:
# frames/s, ingest p50/p99 latency and the server's CPU time per frame per mode (median over the
# rounds) and the relative loss of B against A (goal: <= 5 % of throughput). Use an odd number of rounds; expect a few % of noise
# between rounds on a shared machine.
#
#   bench/security_overhead.sh [--rounds 3] [--duration 15] [--agents 2] [--threads 2]
#       [--frames DIR] [--vocabulary FILE] [--build DIR]
#
# Defaults: frames from ../shared/data/rtabmap-loop (PLACEDB_SHARED_DIR), vocabulary
# var/vocabulary/default.pdbv, build dir build/ (PLACEDB_BUILD_DIR). Needs openssl, sha256sum, jq.
# The machine's load is printed first: the figures only compare within one run.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
rounds=3
duration=15
agents=2
threads=2
frames="${PLACEDB_SHARED_DIR:-$repo/../shared}/data/rtabmap-loop"
vocabulary="$repo/var/vocabulary/default.pdbv"
build="${PLACEDB_BUILD_DIR:-$repo/build}"
while (($#)); do
  case "$1" in
    --rounds) rounds="$2"; shift 2 ;;
    --duration) duration="$2"; shift 2 ;;
    --agents) agents="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --frames) frames="$2"; shift 2 ;;
    --vocabulary) vocabulary="$2"; shift 2 ;;
    --build) build="$2"; shift 2 ;;
    -h|--help) sed -n '2,17p' "$0"; exit 0 ;;
    *) echo "security_overhead.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
for tool in openssl sha256sum jq; do
  command -v "$tool" >/dev/null || { echo "security_overhead.sh: needs $tool" >&2; exit 2; }
done
server="$build/server/placedb-server"
load="$build/client/placedb-load"
cli="$build/client/placedb"
for binary in "$server" "$load" "$cli"; do
  [[ -x "$binary" ]] || { echo "security_overhead.sh: $binary is not built" >&2; exit 2; }
done

# shellcheck source=bench/servers_cleanup.sh
source "$(dirname "${BASH_SOURCE[0]}")/servers_cleanup.sh"

# A CA and a certificate for localhost / 127.0.0.1; an admin token and its hash.
key_options=(-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes)
openssl req -x509 "${key_options[@]}" -days 2 -keyout "$work/ca.key" -out "$work/ca.pem" \
  -subj "/CN=bench CA" 2>/dev/null
openssl req -new "${key_options[@]}" -keyout "$work/server.key" -out "$work/server.csr" \
  -subj "/CN=localhost" 2>/dev/null
printf 'subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth\n' >"$work/server.ext"
openssl x509 -req -in "$work/server.csr" -CA "$work/ca.pem" -CAkey "$work/ca.key" \
  -CAcreateserial -days 2 -extfile "$work/server.ext" -out "$work/server.pem" 2>/dev/null
token="pdb_$(openssl rand 32 | base64 | tr '+/' '-_' | tr -d '=\n')"
token_sha256="$(printf '%s' "$token" | sha256sum | cut -d' ' -f1)"
cat >"$work/tokens.yaml" <<EOF
# placedb tokens file (bench/security_overhead.sh): one admin principal.
principals:
  - name: bench
    token_sha256: $token_sha256
    admin: true
EOF

free_port() {
  python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# start NAME PORT FLAGS...: a server with its own data dir; waits until it is SERVING.
start() {
  local name="$1" port="$2"
  shift 2
  mkdir -p "$work/$name"
  "$server" --listen "127.0.0.1:$port" --metrics-listen off --console-listen off --data-dir "$work/$name/data" \
    --vocabulary "default=$vocabulary" --threads "$threads" --log-level warn "$@" \
    >"$work/$name/server.log" 2>&1 &
  pids+=($!)
}
wait_serving() {
  local name="$1"
  shift
  for _ in $(seq 120); do
    if "$cli" --timeout 2 "$@" health >/dev/null 2>&1; then return 0; fi
    sleep 0.5
  done
  echo "security_overhead.sh: server $name did not start:" >&2
  cat "$work/$name/server.log" >&2
  exit 1
}

port_a="$(free_port)"
port_b="$(free_port)"
start plaintext "$port_a"
start tls_tokens "$port_b" --tls-cert "$work/server.pem" --tls-key "$work/server.key" \
  --tokens-file "$work/tokens.yaml"
flags_a=(--address "127.0.0.1:$port_a")
flags_b=(--address "localhost:$port_b" --tls --ca-cert "$work/ca.pem")
wait_serving plaintext "${flags_a[@]}"
PLACEDB_TOKEN="$token" wait_serving tls_tokens "${flags_b[@]}"
# B really checks tokens: a call without one is refused (else B would measure nothing).
if denied="$(env -u PLACEDB_TOKEN "$cli" --timeout 10 "${flags_b[@]}" maps list 2>&1)" ||
  [[ "$denied" != *UNAUTHENTICATED* ]]; then
  echo "security_overhead.sh: the tls_tokens server answered a call without a token: $denied" >&2
  exit 1
fi

echo "# $(uptime)"
echo "# $(nproc) cores; $rounds rounds x ${duration} s per mode, $agents agents, --mode features," \
  "server --threads $threads; frames $frames"
# The server's CPU time (user + system, clock ticks): its cost per frame does not depend on what
# else the machine runs, unlike frames/s.
cpu_ticks() { awk '{ print $14 + $15 }' "/proc/$1/stat"; }
declare -A pid_of=([plaintext]="${pids[0]}" [tls_tokens]="${pids[1]}")
hz="$(getconf CLK_TCK)"
for round in $(seq "$rounds"); do
  # A B, then B A: a drift in the machine's load does not favour one mode.
  order=(plaintext tls_tokens)
  if ((round % 2 == 0)); then order=(tls_tokens plaintext); fi
  for mode in "${order[@]}"; do
    if [[ "$mode" == plaintext ]]; then flags=("${flags_a[@]}"); else flags=("${flags_b[@]}"); fi
    ticks0="$(cpu_ticks "${pid_of[$mode]}")"
    PLACEDB_TOKEN="$token" "$load" "${flags[@]}" --mode features --agents "$agents" \
      --duration "$duration" --glob '*.jpg' --json-out "$work/$mode-$round.json" "$frames" \
      >"$work/$mode-$round.txt" 2>&1 || {
      echo "security_overhead.sh: the load test against $mode failed:" >&2
      cat "$work/$mode-$round.txt" >&2
      exit 1
    }
    ticks1="$(cpu_ticks "${pid_of[$mode]}")"
    # The report gains the server's CPU milliseconds per answered frame.
    jq --argjson ticks "$((ticks1 - ticks0))" --argjson hz "$hz" \
      '. + {server_cpu_ms_per_frame: ($ticks / $hz * 1000 / .frames)}' \
      "$work/$mode-$round.json" >"$work/$mode-$round.tmp" && mv "$work/$mode-$round.tmp" "$work/$mode-$round.json"
    errors="$(jq '.rpc.ingest.errors' "$work/$mode-$round.json")"
    if [[ "$errors" != 0 ]]; then
      echo "security_overhead.sh: $errors ingest errors against $mode" >&2
      jq '.errors' "$work/$mode-$round.json" >&2
      exit 1
    fi
    echo "# round $round $mode: $(jq -r '"\(.throughput_fps | . * 10 | round / 10) frames/s, p50 \(.rpc.ingest.latency_ms.p50) ms, p99 \(.rpc.ingest.latency_ms.p99) ms, server CPU \(.server_cpu_ms_per_frame | . * 1000 | round / 1000) ms/frame"' "$work/$mode-$round.json")"
  done
done

# median MODE JQ-EXPRESSION: the median over the rounds (the mean of the middle two for an even
# count).
median() {
  local mode="$1" expression="$2"
  jq -s "[.[] | $expression] | sort | if length % 2 == 1 then .[length / 2 | floor]
         else (.[length / 2 - 1] + .[length / 2]) / 2 end | . * 100 | round / 100" \
    "$work/$mode"-*.json
}
for mode in plaintext tls_tokens; do
  echo "${mode}_frames_per_s $(median "$mode" .throughput_fps) frames/s"
  echo "${mode}_ingest_p50 $(median "$mode" .rpc.ingest.latency_ms.p50) ms"
  echo "${mode}_ingest_p99 $(median "$mode" .rpc.ingest.latency_ms.p99) ms"
  echo "${mode}_server_cpu_per_frame $(median "$mode" '.server_cpu_ms_per_frame * 1000') us"
done
a="$(median plaintext .throughput_fps)"
b="$(median tls_tokens .throughput_fps)"
awk -v a="$a" -v b="$b" 'BEGIN { printf "throughput_loss %.1f %%\n", (a - b) / a * 100 }'
# Paired: each round's two runs are adjacent in time; the median of the rounds' own losses is
# less moved by a load that changes between rounds.
for round in $(seq "$rounds"); do
  jq -n --slurpfile a "$work/plaintext-$round.json" --slurpfile b "$work/tls_tokens-$round.json" \
    '($a[0].throughput_fps - $b[0].throughput_fps) / $a[0].throughput_fps * 100'
done | sort -g | awk '{ v[NR] = $1 } END {
  m = NR % 2 ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2
  printf "throughput_loss_paired %.1f %%\n", m }'
a50="$(median plaintext .rpc.ingest.latency_ms.p50)"
b50="$(median tls_tokens .rpc.ingest.latency_ms.p50)"
awk -v a="$a50" -v b="$b50" 'BEGIN { printf "ingest_p50_increase %.1f %%\n", (b - a) / a * 100 }'
c_a="$(median plaintext '.server_cpu_ms_per_frame * 1000')"
c_b="$(median tls_tokens '.server_cpu_ms_per_frame * 1000')"
awk -v a="$c_a" -v b="$c_b" 'BEGIN { printf "server_cpu_per_frame_increase %.1f %%\n", (b - a) / a * 100 }'
echo "# $(uptime)"
