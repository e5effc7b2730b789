#!/usr/bin/env bash
# Sets up placedb on a fresh Debian 12 machine: installs the Debian packages it needs, builds it
# in Release and prepares the defaults (the ORB and SIFT vocabularies, trained on Debian's own
# sample images). Idempotent: re-running skips what is already done.
#
#   tools/setup.sh            install + build + defaults
#   tools/setup.sh --run      ... then run placedb on its embedded defaults
#   tools/setup.sh --deps     install packages only
set -euo pipefail
cd "$(dirname "$0")/.."

PACKAGES=(
  build-essential cmake ninja-build pkg-config git ca-certificates
  libopencv-dev libeigen3-dev libtbb-dev
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler
  librocksdb-dev prometheus-cpp-dev
  libcpp-httplib-dev  # the metrics endpoint (HTTP and HTTPS)
  libssl-dev openssl  # TLS (server/transport_security); the tests make certificates with openssl
  libturbojpeg0-dev  # strict JPEG decoding (core/decode)
  libjemalloc-dev    # PLACEDB_ALLOCATOR=jemalloc (measured against glibc, tuned: the default)
  libgtest-dev libgmock-dev libbenchmark-dev
  libspdlog-dev libfmt-dev libcli11-dev libyaml-cpp-dev nlohmann-json3-dev
  libssl-dev openssl  # tokens (SHA-256, random), TLS on /metrics; tests make certificates
  python3 python3-grpcio python3-protobuf python3-numpy  # the Python SDK (client/python)
  python3-pytest python3-opencv  # its tests and examples
  python3-venv python3-wheel  # pip install ./client/python into a venv, offline
  python3-rosbag python3-sensor-msgs  # ROS 1 bags (placedb.read_bag; its tests write bags)
  chromium python3-websocket  # the web console's browser test (tests/console/browser_test.py)
  clang-format ccache
  clang-14 libclang-rt-14-dev  # CI's -Wthread-safety and libFuzzer stages (tools/test.sh)
  nats-server libnats-dev etcd-server etcd-client  # cluster mode (issue 18): engines, NATS C client
  # Debian's sample images: the default vocabulary is trained on these (never on eval data).
  opencv-doc darknet
)

run=0
deps_only=0
for arg in "$@"; do
  case "$arg" in
    --run) run=1 ;;
    --deps) deps_only=1 ;;
    -h|--help) sed -n '2,9p' "$0"; exit 0 ;;
    *) echo "setup.sh: unknown option $arg (see --help)" >&2; exit 2 ;;
  esac
done

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
cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE=Release
cmake --build "$BUILD_DIR" -j "$jobs"

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
