#!/usr/bin/env bash
# Prints the Debian packages that own the shared libraries the given binaries link directly
# (ELF NEEDED entries, resolved by the dynamic loader, then dpkg -S), one per line, sorted.
# The Dockerfile's build stage runs it so that the runtime stage installs exactly the lib*
# packages matching the -dev ones it was built against; apt then pulls in their dependencies.
#
#   deploy/docker/runtime-packages.sh BINARY...
set -euo pipefail

if (($# == 0)); then
  echo "usage: $0 BINARY..." >&2
  exit 2
fi

owner() {  # the package owning a file; usrmerge: /lib/x is registered as /lib/x or /usr/lib/x
  local real
  real="$(readlink -f "$1")"
  dpkg -S "$real" 2>/dev/null || dpkg -S "${real#/usr}" 2>/dev/null || {
    echo "runtime-packages: no Debian package owns $real" >&2
    return 1
  }
}

for binary in "$@"; do
  resolved="$(ldd "$binary")"
  while read -r lib; do
    path="$(awk -v l="$lib" '$1 == l && $2 == "=>" { print $3 }' <<<"$resolved")"
    if [[ -z "$path" || "$path" == "not" ]]; then
      echo "runtime-packages: $binary needs $lib, which the loader cannot find" >&2
      exit 1
    fi
    owner "$path"
  done < <(readelf -d "$binary" | sed -n 's/.*(NEEDED).*Shared library: \[\(.*\)\]/\1/p')
done | cut -d: -f1 | sort -u
