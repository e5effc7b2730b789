#!/usr/bin/env bash
# Runs placedb on its embedded defaults: the gRPC service on 127.0.0.1:50051 (metrics on
# 127.0.0.1:9464, the web console on http://127.0.0.1:9465/; loopback only until tokens or
# mutual TLS are configured: docs/security.md), data in var/data, the default vocabulary, and
# server-side detection with YOLOX-Nano when tools/install_models.sh found the model (otherwise
# detection is off and the server says so).
# Extra arguments go to placedb-server (see --help); stop it with Ctrl-C or SIGTERM.
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${PLACEDB_BUILD_DIR:-build}
args=()
if [ -f var/models/yolox_nano.onnx ]; then
  args+=(--detector-model var/models/yolox_nano.onnx)
fi
exec "$BUILD_DIR/server/placedb-server" "${args[@]}" "$@"
