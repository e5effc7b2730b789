#!/usr/bin/env bash
# Runs the whole placedb test suite, exactly as CI does (.ci/run calls this):
#   1. packages (idempotent, as tools/setup.sh --deps),
#   2. a -Werror Release build and every test through ctest (unit, recognition on real images,
#      the web console in headless chromium: console_browser_test, label browser),
#   3. the unit tests again under AddressSanitizer + UndefinedBehaviorSanitizer,
#   4. the concurrency tests under ThreadSanitizer,
#   5. a clang build with -Wthread-safety -Werror: the lock annotations (core/base/
#      thread_annotations.h) checked by the compiler,
#   6. short libFuzzer runs of every tests/fuzz target (tools/fuzz.sh, docs/fuzzing.md): any
#      crash, sanitizer report, leak or timeout fails the run.
# Benchmarks are not tests: run them with tools/bench.sh.
set -euo pipefail
cd "$(dirname "$0")/.."

tools/setup.sh --deps --tests  # the product's packages and the test suite's
jobs=$(nproc)
vocabulary="$PWD/var/vocabulary/default.pdbv"

step() { printf '\n==== %s ====\n' "$*"; }

step "Release build (-Werror)"
cmake -S . -B build-test -G Ninja -DCMAKE_BUILD_TYPE=Release -DPLACEDB_WERROR=ON \
  -DPLACEDB_DEFAULT_VOCABULARY="$vocabulary"
cmake --build build-test -j "$jobs"
PLACEDB_BUILD_DIR=build-test tools/install_models.sh var/models

step "All tests (ctest)"
ctest --test-dir build-test --output-on-failure -j "$jobs" --timeout 1500

step "Unit tests under AddressSanitizer + UBSan"
cmake -S . -B build-asan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DPLACEDB_WERROR=ON \
  -DPLACEDB_SANITIZE=ON -DPLACEDB_BUILD_BENCH=OFF -DPLACEDB_DEFAULT_VOCABULARY="$vocabulary"
# Only what the unit tests need (tests/CMakeLists.txt): the service and tools are covered by
# the Release stage.
cmake --build build-asan -j "$jobs" --target placedb_unit_tests
ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
  ctest --test-dir build-asan --output-on-failure -j "$jobs" -L unit --timeout 1500

step "Concurrency tests under ThreadSanitizer"
cmake -S . -B build-tsan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DPLACEDB_WERROR=ON \
  -DPLACEDB_TSAN=ON -DPLACEDB_BUILD_BENCH=OFF -DPLACEDB_DEFAULT_VOCABULARY="$vocabulary"
cmake --build build-tsan -j "$jobs" --target placedb_concurrency_tests
TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1:suppressions=$PWD/tools/tsan.supp" \
  ctest --test-dir build-tsan --output-on-failure -R 'Concurren' --timeout 1500

step "Lock annotations under clang -Wthread-safety"
# Compiling is the check: the libraries and executables, no tests, no optimiser, no debug info.
cmake -S . -B build-clang -G Ninja -DCMAKE_BUILD_TYPE=Debug -DCMAKE_CXX_FLAGS_DEBUG=-O0 \
  -DCMAKE_CXX_COMPILER=clang++-14 -DPLACEDB_WERROR=ON \
  -DPLACEDB_THREAD_SAFETY=ON -DPLACEDB_BUILD_BENCH=OFF -DPLACEDB_DEFAULT_VOCABULARY="$vocabulary"
cmake --build build-clang -j "$jobs" --target placedb-server placedb placedb-load placedb-eval \
  placedb-vocab placedb-sift-vocab placedb-recognize

step "Fuzzing (short runs)"
# 30 s per target (PLACEDB_FUZZ_SECONDS), two targets at a time: ~2.5 minutes plus the build; the
# seed corpora make even short runs reach the parsers' depths. The long runs (tools/fuzz.sh
# --long) are not part of CI.
fuzz_start=$SECONDS
tools/fuzz.sh --seconds "${PLACEDB_FUZZ_SECONDS:-30}"
echo "fuzzing stage: $((SECONDS - fuzz_start)) s"

step "All test stages passed"
