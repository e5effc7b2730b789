#!/usr/bin/env bash
# Builds the default vocabulary (k=10, L=6, ORB) if it is missing or does not load.
#
#   tools/build_default_vocabulary.sh <placedb-vocab binary> <output path>
#
# Trains ONLY on Debian's sample images: the OpenCV samples (package opencv-doc), darknet's
# sample images (package darknet) and frames of OpenCV's vtest.avi. Never on ../shared/data:
# that is the evaluation data, and a vocabulary trained on it would flatter every result.
# Still images get 16 randomly warped views each (crop, rotation, scale, exposure) so that there
# are ~1.6M descriptors, enough for a ~550k-word tree; the run takes well under a minute on two
# cores. The seed is fixed, so the result is reproducible on the same OpenCV build.
set -euo pipefail

readonly OPENCV_DATA=/usr/share/doc/opencv-doc/examples/data
readonly DARKNET_DATA=/usr/share/darknet/data
readonly VIDEO="${OPENCV_DATA}/vtest.avi"

die() {
  echo "build_default_vocabulary: $*" >&2
  exit 1
}

if [[ $# -ne 2 ]]; then
  echo "usage: $0 <placedb-vocab binary> <output path>" >&2
  exit 2
fi
readonly TOOL="$1"
readonly OUTPUT="$2"

[[ -x "${TOOL}" ]] || die "placedb-vocab not found or not executable: ${TOOL} (build it first)"

if [[ -e "${OUTPUT}" ]]; then
  if "${TOOL}" info "${OUTPUT}" >/dev/null 2>&1; then
    echo "build_default_vocabulary: ${OUTPUT} exists and loads; nothing to do"
    exit 0
  fi
  echo "build_default_vocabulary: ${OUTPUT} exists but does not load; rebuilding it" >&2
fi

[[ -d "${OPENCV_DATA}" ]] || die "missing ${OPENCV_DATA}: install the Debian package opencv-doc"
[[ -f "${VIDEO}" ]] || die "missing ${VIDEO}: install the Debian package opencv-doc"
[[ -d "${DARKNET_DATA}" ]] || die "missing ${DARKNET_DATA}: install the Debian package darknet"

mkdir -p "$(dirname "${OUTPUT}")"
# Train into a temporary file next to the output and move it into place only when complete, so
# an interrupted run never leaves a half-written vocabulary behind.
TEMP="$(mktemp "${OUTPUT}.tmp.XXXXXX")"
trap 'rm -f "${TEMP}"' EXIT

echo "build_default_vocabulary: training ${OUTPUT} from Debian sample images (k=10, L=6)"
start=${SECONDS}
"${TOOL}" train --out "${TEMP}" \
  --images "${OPENCV_DATA}" --images "${DARKNET_DATA}" \
  --video "${VIDEO}" --video-every 2 \
  --k 10 --L 6 --features 1000 --seed 1 --augment 16 \
  || die "training failed"
"${TOOL}" info "${TEMP}" >/dev/null || die "the trained vocabulary does not load"
mv -f "${TEMP}" "${OUTPUT}"
trap - EXIT
echo "build_default_vocabulary: wrote ${OUTPUT} in $((SECONDS - start)) s"
