#!/usr/bin/env bash
# The service-level kill soak (docs/storage.md, "Kill soak and disk-full run"): builds the server
# and placedb-kill-soak (Release build in build/, as tools/setup.sh makes it), then SIGKILLs the
# real server 100 times (--kills N) under multi-agent ingest and checks every acknowledged place
# through the API. Prints `kills`, `acknowledged_places`, `lost_places`, `places_checked`, ...;
# exits non-zero on any loss. --disk-full runs the disk-full rounds on a tmpfs instead (root).
# Other options: placedb-kill-soak --help. Niced: it is meant to run beside other work.
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${PLACEDB_BUILD_DIR:-build}
VOCABULARY=${PLACEDB_VOCABULARY:-var/vocabulary/default.pdbv}
cmake --build "$BUILD_DIR" -j2 --target placedb-server placedb-kill-soak
exec nice -n 10 "$BUILD_DIR/tools/placedb-kill-soak" --server "$BUILD_DIR/server/placedb-server" \
  --vocabulary "$VOCABULARY" "$@"
