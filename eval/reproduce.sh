#!/usr/bin/env bash
# Reproduces the figures of docs/evaluation.md: prepares the three datasets and runs BoBW vs
# BoBW+DO on each with oracle masks (exact coverage 25 %), oracle boxes (keypoint-in-box, the
# paper's heuristic) and the real detector (YOLOX-Nano, keypoint-in-box, confidence 0.1-0.4).
#
#   eval/reproduce.sh [BUILD_DIR=build] [OUT_DIR=var/eval] [FEATURES=300,500,1000,1500,2000]
#
# About 10 minutes on 2 cores (4.5 once the datasets and detections exist). Datasets go to
# OUT_DIR/datasets, results to OUT_DIR/results/*.
set -euo pipefail
cd "$(dirname "$0")/.."
build=${1:-build}
out=${2:-var/eval}
features=${3:-300,500,1000,1500,2000}
eval_bin="$build/eval/placedb-eval"
threads=${PLACEDB_EVAL_THREADS:-2}

[ -x "$eval_bin" ] || { echo "no $eval_bin: build first (cmake --build $build)" >&2; exit 1; }
mkdir -p "$out/datasets" "$out/results"

[ -f "$out/datasets/camvid/dataset.json" ] || "$eval_bin" prepare camvid --out "$out/datasets/camvid"
[ -f "$out/datasets/camvid-stops/dataset.json" ] ||
  "$eval_bin" prepare camvid-stops --out "$out/datasets/camvid-stops"
[ -f "$out/datasets/revisits/dataset.json" ] ||
  "$eval_bin" prepare revisits --places 60 --visits 2 --coverage 0.1:0.4 --seed 1 \
    --out "$out/datasets/revisits"
# The same 60 places (same seed) with 3 query visits each: 180 queries, for tighter figures.
[ -f "$out/datasets/revisits-4visits/dataset.json" ] ||
  "$eval_bin" prepare revisits --places 60 --visits 4 --coverage 0.1:0.4 --seed 1 \
    --out "$out/datasets/revisits-4visits"

cache="$out/datasets/detections_yolox_nano_letterbox.json"
for dataset in camvid camvid-stops revisits revisits-4visits; do
  common=(run --dataset "$out/datasets/$dataset" --features "$features" --geom none,0,1,2,6
          --threads "$threads")
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-oracle-masks" \
    --boxes none --masks oracle --filter exact_coverage --sensitivity 0.25 \
    --title "$dataset: oracle masks, exact coverage 25 %" > /dev/null
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-oracle-boxes" \
    --boxes oracle --filter keypoint_in_box \
    --title "$dataset: oracle boxes, keypoint in box (1/4)" > /dev/null
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-detector" \
    --boxes detector --confidence 0.1,0.2,0.3,0.4 --filter keypoint_in_box \
    --detections-cache "$cache" \
    --title "$dataset: YOLOX-Nano boxes, keypoint in box (1/4)" > /dev/null
done
echo "results in $out/results/*/table3.md"
