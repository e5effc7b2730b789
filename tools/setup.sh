#!/usr/bin/env bash
# Sets up placedb on a fresh Debian 12 machine: installs the Debian packages the product needs,
# builds the product in Release (placedb-server, the placedb CLI and placedb-load, the Python
# SDK, and the vocabulary tools the defaults need; no tests, no benchmarks) and prepares the
# defaults (the ORB and SIFT vocabularies, trained on Debian's own sample images; the detector
# model). Idempotent: re-running skips what is already done. The test suite's packages (chromium,
# clang, etcd, nats, gtest, ...) and build are tools/test.sh's: it calls `setup.sh --deps --tests`.
#
#   tools/setup.sh                 install + build the product + defaults
#   tools/setup.sh --run           ... then run placedb on its embedded defaults
#   tools/setup.sh --deps          install the product's packages only
#   tools/setup.sh --deps --tests  install the product's and the test suite's packages
set -euo pipefail
cd "$(dirname "$0")/.."

# The product: what placedb-server, the CLI and the Python SDK need to build and run.
PACKAGES=(
  build-essential cmake ninja-build pkg-config git ca-certificates
  curl  # the README's metrics check (a minimal Debian 12 has none)
  libopencv-dev libeigen3-dev libtbb-dev
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler
  librocksdb-dev prometheus-cpp-dev
  libcpp-httplib-dev  # the metrics endpoint and the console (HTTP and HTTPS)
  libssl-dev openssl  # TLS (server/net/transport_security), tokens (SHA-256, random)
  libturbojpeg0-dev  # strict JPEG decoding (core/decode)
  libjemalloc-dev    # PLACEDB_ALLOCATOR=jemalloc (measured against glibc, tuned: the default)
  libbz2-dev liblz4-dev  # ROS 1 bag chunks (client/rosbag_reader): bz2 and lz4 (roslz4 = LZ4 frames)
  libspdlog-dev libfmt-dev libcli11-dev libyaml-cpp-dev nlohmann-json3-dev
  libgtest-dev libgmock-dev libbenchmark-dev  # small; CMake configures tests/ and bench/ (unbuilt)
  libnats-dev  # cluster mode's NATS C client (issue 18); without it the server has no cluster roles
  python3 python3-grpcio python3-protobuf python3-numpy  # the Python SDK (client/python)
  python3-venv python3-wheel  # pip install ./client/python into a venv, offline
  # Debian's sample images: the default vocabulary is trained on these (never on eval data).
  opencv-doc darknet
)
# The test suite (tools/test.sh) on top: setup.sh --deps --tests.
TEST_PACKAGES=(
  python3-pytest python3-opencv  # the SDK's tests and examples
  python3-rosbag python3-sensor-msgs  # ROS 1 bags (placedb.read_bag; its tests write bags)
  python3-roslz4  # lz4 bags in tests/recordings (python3-rosbag writes bz2 without it, not lz4)
  chromium python3-websocket  # the web console's browser test (tests/console/browser_test.py)
  clang-format ccache
  clang-14 libclang-rt-14-dev  # CI's -Wthread-safety and libFuzzer stages (tools/test.sh)
  nats-server etcd-server etcd-client  # cluster mode's engines in tests/cluster
)

run=0
deps_only=0
tests=0
for arg in "$@"; do
  case "$arg" in
    --run) run=1 ;;
    --deps) deps_only=1 ;;
    --tests) tests=1 ;;
    -h|--help) sed -n '2,13p' "$0"; exit 0 ;;
    *) echo "setup.sh: unknown option $arg (see --help)" >&2; exit 2 ;;
  esac
done
if ((tests && !deps_only)); then
  echo "setup.sh: --tests goes with --deps (tools/test.sh builds and runs the tests)" >&2
  exit 2
fi
((tests)) && PACKAGES+=("${TEST_PACKAGES[@]}")

missing=()
for pkg in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  echo "setup: installing ${#missing[@]} Debian packages: ${missing[*]}"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${PACKAGES[@]}"
else
  echo "setup: all Debian packages present"
fi
((deps_only)) && exit 0

BUILD_DIR=${PLACEDB_BUILD_DIR:-build}
jobs=$(nproc)
# The product's targets only: the test suite is tools/test.sh's (build-test/). Tests and
# benchmarks stay configured here, so `cmake --build build --target X` (tools/bench.sh, a test)
# still builds one on demand.
cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE=Release
targets=(placedb-server placedb placedb-load placedb-vocab placedb-sift-vocab)
# The Python SDK when its packages are there (client/python/CMakeLists.txt says when not).
if cmake --build "$BUILD_DIR" --target help | grep -q '^placedb_python:'; then
  targets+=(placedb_python)
fi
cmake --build "$BUILD_DIR" -j "$jobs" --target "${targets[@]}"

tools/build_default_vocabulary.sh "$BUILD_DIR/tools/placedb-vocab" var/vocabulary/default.pdbv
# The SIFT vocabulary for SIFT maps (float words, k=10, L=4, Debian sample images only; ~30 s).
"$BUILD_DIR/tools/placedb-sift-vocab" --out var/vocabulary/sift-debian.pdbfv --if-missing
# The detector model: from ../shared/models when present, else the official download, else
# server-side detection stays off (the service says so; maps that need it are refused).
PLACEDB_BUILD_DIR="$BUILD_DIR" tools/install_models.sh var/models

echo "setup: done. Binaries in $BUILD_DIR/, vocabularies var/vocabulary/default.pdbv (ORB) and" \
  "var/vocabulary/sift-debian.pdbfv (SIFT)"
if ((run)); then
  # The server's embedded default console_listen; `build/client/placedb console` asks the server.
  echo "setup: starting placedb; its web console: http://127.0.0.1:9465/ (docs/console.md)"
  exec tools/run.sh
fi
