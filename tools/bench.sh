#!/usr/bin/env bash
# Runs the core benchmark (Release build in build/, as tools/setup.sh makes it) and prints its
# `name value unit` lines. Pass --places to change the size sweep (default 1k,10k,100k).
# bench/compare.py runs every benchmark against a base build and writes one table.
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${PLACEDB_BUILD_DIR:-build}
cmake --build "$BUILD_DIR" --target placedb-bench-core
"$BUILD_DIR/bench/placedb-bench-core" --vocabulary var/vocabulary/default.pdbv "$@"
