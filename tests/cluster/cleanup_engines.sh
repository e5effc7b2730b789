#!/usr/bin/env bash
# Kills the nats-server and etcd processes a crashed cluster test left behind (ctest runs this as
# the cleanup of the `cluster_engines` fixture; tests/cluster/engines.h). Every engine the harness
# starts has a pid file in the pid directory ($1); a pid is killed (its process group, SIGKILL)
# only while its command line is still the engine the file names, so a reused pid is left alone;
# the harness's temp dir named in the file is removed. Then the test hosts (tests/cluster/hosts.h)
# of runs whose owner process is gone: every process in their network namespaces is killed, the
# namespaces and the bridge removed (registry: $PLACEDB_HOSTS_REGISTRY or /run/placedb-hosts).
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

registry=${PLACEDB_HOSTS_REGISTRY:-/run/placedb-hosts}
[ -d "$registry" ] || exit 0
for file in "$registry"/10.*; do
  [ -f "$file" ] || continue
  owner=$(sed -n 1p "$file")
  # A live owner is another test run (ctest -j, parallel runs): its hosts are its own. Owner 0:
  # tools/cluster_local.py's hosts, which outlive the launcher; its `down` removes them.
  [ "$owner" = 0 ] && continue
  if [ -n "$owner" ] && kill -0 "$owner" 2>/dev/null; then continue; fi
  bridge=$(sed -n 2p "$file")
  for ns in $(sed -n '3,$p' "$file"); do
    if [ -e "/run/netns/$ns" ]; then
      echo "cleanup_engines: removing leftover host $ns"
      for pid in $(ip netns pids "$ns" 2>/dev/null); do kill -KILL "$pid" 2>/dev/null; done
      ip netns del "$ns" 2>/dev/null
    fi
  done
  if [ -n "$bridge" ]; then
    # The outer veth ends ("<bridge without its final b>v<i>"): a deleted namespace is destroyed
    # asynchronously, and its veth pair with it; do not leave them to chance.
    for link in /sys/class/net/"${bridge%b}"v*; do
      [ -e "$link" ] && ip link del "$(basename "$link")" 2>/dev/null
    done
    ip link show "$bridge" >/dev/null 2>&1 && ip link del "$bridge"
  fi
  rm -f "$file"
done
exit 0
