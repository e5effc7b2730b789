#!/usr/bin/env bash
# Runs placedb on its embedded defaults: the default vocabulary and the RTAB-Map loop frames
# from ../shared when present (database = first pass, queries = the revisit), otherwise
# opencv-doc's stereo pairs (database = left views, queries = right views).
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${PLACEDB_BUILD_DIR:-build}
vocabulary=var/vocabulary/default.pdbv
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
loop=../shared/data/rtabmap-loop
if [ -d "$loop" ]; then
  for i in $(seq 1 40); do echo "$loop/$i.jpg"; done > "$work/database.txt"
  for i in $(seq 41 84); do echo "$loop/$i.jpg"; done > "$work/queries.txt"
  echo "placedb: RTAB-Map loop, database = frames 1-40, queries = frames 41-84"
else
  samples=/usr/share/doc/opencv-doc/examples/data
  ls "$samples"/left0*.jpg > "$work/database.txt"
  ls "$samples"/right0*.jpg > "$work/queries.txt"
  echo "placedb: ../shared not found; opencv-doc stereo pairs, database = left, queries = right"
fi
"$BUILD_DIR/tools/placedb-recognize" --vocabulary "$vocabulary" \
  --database "$work/database.txt" --queries "$work/queries.txt" --verify exhaustive "$@"
