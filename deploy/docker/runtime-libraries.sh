#!/usr/bin/env bash
# Copies the shared libraries the given binaries load (their whole ldd closure) under DEST, for
# the runtime stage of the Dockerfile, leaving out those of the Debian packages the runtime stage
# already has installed (RUNTIME_STATUS: that stage's /var/lib/dpkg/status).
#
#   deploy/docker/runtime-libraries.sh RUNTIME_STATUS DEST BINARY...
#
# Why files and not packages: Debian's lib packages bring their own hard dependencies, and those
# of OpenCV reach far beyond what placedb loads (libopencv-core406 -> libglx0 -> Mesa -> LLVM,
# 115 MB). The loader needs only the files ldd resolves. For each one:
#   - the file itself at its real path (DEST/usr/lib/...), and its name as the loader asks for it
#     (the soname) as a symlink in the multiarch directory, so that the runtime's default search
#     path finds it (alternatives such as libblas.so.3 -> openblas-pthread/ included);
#   - the owning package's copyright file (DEST/usr/share/doc/<package>/copyright: the licences
#     travel with the files);
#   - a line "package version path" in DEST/usr/share/doc/placedb/runtime-libraries.txt, the
#     manifest of what was copied from which Debian package (dpkg in the image does not list them).
# Fails when a library is not found or belongs to no package (the image would not run).
set -euo pipefail

if (($# < 3)); then
  echo "usage: $0 RUNTIME_STATUS DEST BINARY..." >&2
  exit 2
fi
status_file=$1
dest=$2
shift 2

# Packages installed in the runtime stage: name -> version.
declare -A runtime_version=()
while IFS=$'\t' read -r name version; do
  runtime_version[$name]=$version
done < <(awk -v RS= -F'\n' '
  {
    pkg = ""; ver = ""; installed = 0
    for (i = 1; i <= NF; i++) {
      if ($i ~ /^Package: /) pkg = substr($i, 10)
      else if ($i ~ /^Version: /) ver = substr($i, 10)
      else if ($i ~ /^Status: .* installed$/) installed = 1
    }
    if (pkg != "" && installed) print pkg "\t" ver
  }' "$status_file")
((${#runtime_version[@]} > 0)) || { echo "runtime-libraries: no packages in $status_file" >&2; exit 1; }

# The multiarch library directory (where libc.so.6 lives): the loader's default search path.
libdir="$(dirname "$(readlink -f "$(ldd /bin/sh | awk '$1 == "libc.so.6" { print $3 }')")")"
[[ "$libdir" == /usr/lib/* ]] || { echo "runtime-libraries: unexpected libc directory $libdir" >&2; exit 1; }

owner() {  # the package owning a file; usrmerge: /lib/x is registered as /lib/x or /usr/lib/x
  dpkg -S "$1" 2>/dev/null || dpkg -S "${1#/usr}" 2>/dev/null || {
    echo "runtime-libraries: no Debian package owns $1" >&2
    return 1
  }
}

manifest="$dest/usr/share/doc/placedb/runtime-libraries.txt"
mkdir -p "$(dirname "$manifest")"
: >"$manifest"
declare -A seen=()
copied=0
bytes=0
skipped=()
for binary in "$@"; do
  resolved="$(ldd "$binary")" || { echo "runtime-libraries: ldd $binary failed" >&2; exit 1; }
  if grep -q 'not found' <<<"$resolved"; then
    echo "runtime-libraries: $binary needs libraries the loader cannot find:" >&2
    grep 'not found' <<<"$resolved" >&2
    exit 1
  fi
  # "libfoo.so.1 => /lib/x86_64-linux-gnu/libfoo.so.1 (0x...)" and the interpreter's
  # "/lib64/ld-linux-x86-64.so.2 (0x...)" (libc6's, always in the runtime).
  while read -r soname path; do
    [[ -n "${seen[$path]:-}" ]] && continue
    seen[$path]=1
    real="$(readlink -f "$path")"
    package="$(owner "$real" | head -n 1 | cut -d: -f1)"
    if [[ -n "${runtime_version[$package]:-}" ]]; then
      skipped+=("$package")
      continue
    fi
    [[ "$real" == /usr/* ]] || { echo "runtime-libraries: $real is outside /usr" >&2; exit 1; }
    version="$(dpkg-query -W -f='${Version}' "$package")"
    mkdir -p "$dest$(dirname "$real")"
    cp -a "$real" "$dest$real"
    if [[ "$libdir/$soname" != "$real" ]]; then
      ln -sfn "$real" "$dest$libdir/$soname"
    fi
    if [[ -f "/usr/share/doc/$package/copyright" ]]; then
      mkdir -p "$dest/usr/share/doc/$package"
      cp "/usr/share/doc/$package/copyright" "$dest/usr/share/doc/$package/copyright"
    fi
    printf '%s %s %s\n' "$package" "$version" "$real" >>"$manifest"
    copied=$((copied + 1))
    bytes=$((bytes + $(stat -c %s "$real")))
  done < <(awk '$2 == "=>" && $3 ~ /^\// { print $1, $3 }' <<<"$resolved")
done
sort -o "$manifest" "$manifest"
echo "runtime-libraries: copied $copied libraries ($((bytes / 1000000)) MB) of" \
  "$(cut -d' ' -f1 "$manifest" | sort -u | wc -l) packages; already in the runtime stage:" \
  "$(printf '%s\n' "${skipped[@]}" | sort -u | tr '\n' ' ')"
