# Sourced by the bench scripts that start servers: a temporary work directory ($work) and the
# started processes' ids ($pids, append with `pids+=($!)`), both cleaned up when the script exits
# (servers get SIGTERM and are waited for, so their data directories close cleanly).
work="$(mktemp -d)"
pids=()
cleanup() {
  for pid in "${pids[@]}"; do
    if kill -0 "$pid" 2>/dev/null; then
      kill -TERM "$pid"
      wait "$pid" || true
    fi
  done
  rm -rf "$work"
}
trap cleanup EXIT
