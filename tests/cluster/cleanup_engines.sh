#!/usr/bin/env bash
# Kills the nats-server and etcd processes a crashed cluster test left behind (ctest runs this as
# the cleanup of the `cluster_engines` fixture; tests/cluster/engines.h). Every engine the harness
# starts has a pid file in the pid directory ($1); a pid is killed (its process group, SIGKILL)
# only while its command line is still the engine the file names, so a reused pid is left alone;
# the harness's temp dir named in the file is removed.
set -u
dir=${1:?usage: cleanup_engines.sh <pid directory>}
[ -d "$dir" ] || exit 0
left=0
for file in "$dir"/*; do
  [ -f "$file" ] || continue
  pid=$(basename "$file")
  binary=$(head -n1 "$file")
  engines_dir=$(sed -n 2p "$file")
  if [ -r "/proc/$pid/cmdline" ] && tr '\0' '\n' <"/proc/$pid/cmdline" | head -n1 | grep -qxF "$binary"; then
    echo "cleanup_engines: killing leftover $binary (pid $pid)"
    kill -KILL -- "-$pid" 2>/dev/null || kill -KILL "$pid" 2>/dev/null
    left=$((left + 1))
  fi
  rm -f "$file"
  # The harness's temp dir, which a crashed test could not remove.
  case "$engines_dir" in
    */placedb-engines-*) [ -d "$engines_dir" ] && rm -rf -- "$engines_dir" ;;
  esac
done
echo "cleanup_engines: $left leftover engine(s) killed"
