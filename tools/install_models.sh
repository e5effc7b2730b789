#!/usr/bin/env bash
# Installs the dynamic-object detector models into DEST (default var/models). Idempotent.
#
#   tools/install_models.sh [DEST]      DEST defaults to var/models in the project
#
#  1. From ../shared/models (PLACEDB_SHARED_DIR/models) when present: yolox_nano.onnx and
#     yolo-fastest-1.1-xl.cfg/.weights, each verified against SHA256SUMS there first.
#  2. Otherwise YOLOX-Nano from its official GitHub release (0.1.1rc0, asset yolox_nano.onnx) with
#     curl or wget, then checked to load and yield [1,3549,85] with the built detector_test
#     (PLACEDB_BUILD_DIR, default build/); without a build the check is skipped, and says so.
#     Yolo-Fastest has no release asset to fetch: without ../shared the darknet backend is off.
#  3. With neither, it says that server-side detection will be off and exits 0: placedb then
#     runs on the agents' boxes only (a degraded mode, not an error).
# Exit status 1 only for a usage error or a DEST that cannot be written. PLACEDB_SHARED_DIR and
# PLACEDB_BUILD_DIR, when relative, are relative to the project root.
set -euo pipefail
caller_dir="$PWD"
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"

case "${1:-}" in
  -h|--help) sed -n '2,15p' "$root/tools/install_models.sh"; exit 0 ;;
esac
if (($# > 1)); then
  echo "usage: tools/install_models.sh [DEST]" >&2
  exit 1
fi
dest="${1:-var/models}"  # a relative DEST argument is relative to the caller's directory
if [ -n "${1:-}" ] && [ "${dest#/}" = "$dest" ]; then dest="$caller_dir/$dest"; fi
shared_models="${PLACEDB_SHARED_DIR:-$root/../shared}/models"
build_dir="${PLACEDB_BUILD_DIR:-build}"
# PLACEDB_YOLOX_URL: a mirror of the same asset (any URL curl/wget accept, file:// too).
yolox_url="${PLACEDB_YOLOX_URL:-https://github.com/Megvii-BaseDetection/YOLOX/releases/download/0.1.1rc0/yolox_nano.onnx}"
files=(yolox_nano.onnx yolo-fastest-1.1-xl.cfg yolo-fastest-1.1-xl.weights)

say() { echo "install_models: $*"; }

mkdir -p "$dest" || { say "cannot create $dest" >&2; exit 1; }

# The expected checksum of a file from SHA256SUMS, or nothing.
expected_sum() {
  awk -v f="$1" '$2 == f || $2 == "*" f { print $1 }' "$shared_models/SHA256SUMS" 2>/dev/null
}
sum_of() { sha256sum "$1" | awk '{ print $1 }'; }

# 1. The shared copies, verified.
if [ -d "$shared_models" ]; then
  for f in "${files[@]}"; do
    src="$shared_models/$f"
    [ -f "$src" ] || { say "$src missing"; continue; }
    want="$(expected_sum "$f")"
    if [ -z "$want" ]; then
      say "$f has no entry in $shared_models/SHA256SUMS: not installed"
      continue
    fi
    if [ -f "$dest/$f" ] && [ "$(sum_of "$dest/$f")" = "$want" ]; then
      say "$dest/$f up to date"
      continue
    fi
    if [ "$(sum_of "$src")" != "$want" ]; then
      say "$src does not match SHA256SUMS: not installed" >&2
      continue
    fi
    cp "$src" "$dest/$f.tmp" && chmod 644 "$dest/$f.tmp" && mv -f "$dest/$f.tmp" "$dest/$f"
    say "installed $dest/$f (sha256 ok)"
  done
else
  say "no shared models at $shared_models"
fi

# 2. YOLOX from the official release when it is still missing.
if [ ! -f "$dest/yolox_nano.onnx" ]; then
  tmp="$(mktemp -d)"
  trap 'rm -rf "$tmp"' EXIT
  say "downloading $yolox_url"
  fetched=0
  if command -v curl >/dev/null; then
    curl -fL --connect-timeout 15 --max-time 300 --retry 2 -sS -o "$tmp/yolox_nano.onnx" \
      "$yolox_url" && fetched=1
  elif command -v wget >/dev/null; then
    wget -q --timeout=15 --tries=2 -O "$tmp/yolox_nano.onnx" "$yolox_url" && fetched=1
  else
    say "neither curl nor wget is installed"
  fi
  if ((fetched)) && [ -s "$tmp/yolox_nano.onnx" ]; then
    checker="$build_dir/tests/detector_test"
    verified=1
    if [ -x "$checker" ]; then
      # The test loads the model from PLACEDB_MODELS_DIR and requires [1,3549,85] outputs.
      if PLACEDB_MODELS_DIR="$tmp" "$checker" \
        --gtest_filter='DetectorModelFiles.YoloxLoadsWithTheExpectedOutput' >"$tmp/check.log" 2>&1
      then
        say "downloaded model loads and yields [1,3549,85]"
      else
        verified=0
        say "the downloaded yolox_nano.onnx failed the load/shape check:" >&2
        tail -n 20 "$tmp/check.log" >&2
      fi
    else
      say "no $checker (build the detector_test target): load/shape check skipped"
    fi
    if ((verified)); then
      mv -f "$tmp/yolox_nano.onnx" "$dest/yolox_nano.onnx"
      chmod 644 "$dest/yolox_nano.onnx"
      say "installed $dest/yolox_nano.onnx (sha256 $(sum_of "$dest/yolox_nano.onnx"))"
    fi
  else
    say "download failed"
  fi
fi

# 3. What the service will be able to do.
if [ -f "$dest/yolox_nano.onnx" ]; then
  say "YOLOX-Nano ready: $dest/yolox_nano.onnx"
else
  say "no YOLOX model: server-side detection will be off (agents' boxes only)"
fi
if [ -f "$dest/yolo-fastest-1.1-xl.cfg" ] && [ -f "$dest/yolo-fastest-1.1-xl.weights" ]; then
  say "Yolo-Fastest 1.1 XL ready: $dest/yolo-fastest-1.1-xl.{cfg,weights}"
else
  say "no Yolo-Fastest model: the darknet backend is unavailable"
fi
exit 0
