#!/usr/bin/env bash
# Reproduces the figures of docs/evaluation.md: prepares the three datasets and runs BoBW vs
# BoBW+DO on each with oracle masks (exact coverage 25 %), oracle boxes (keypoint-in-box, the
# paper's heuristic) and the real detector (YOLOX-Nano, keypoint-in-box, confidence 0.1-0.4).
#
#   eval/reproduce.sh [BUILD_DIR=build] [OUT_DIR=var/eval] [FEATURES=300,500,1000,1500,2000]
#
# About an hour on 2 cores (the service-default runs extract ORB and refine boxes per frame and
# setting: most of the time). Datasets go to
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

# The harder revisits (issue 13): backgrounds keep their own objects, people of vtest.avi.
[ -f "$out/datasets/revisits-hard/dataset.json" ] ||
  "$eval_bin" prepare revisits-hard --places 60 --visits 3 --coverage 0.1:0.4 --seed 7 \
    --out "$out/datasets/revisits-hard"
[ -f "$out/datasets/rtabmap/dataset.json" ] || "$eval_bin" prepare rtabmap --out "$out/datasets/rtabmap"

cache_dir="$out/datasets/cache"
# The paper's BoBW+DO (whole boxes, the whole frame's feature budget, no short-term tier, the best
# candidate verified), as in the tables of the paper's section V.
paper=(--refine-boxes none --static-budget off --short-term off --rerank 0)
for dataset in camvid camvid-stops revisits revisits-4visits; do
  common=(run --dataset "$out/datasets/$dataset" --features "$features" --geom none,0,1,2,6
          --threads "$threads" "${paper[@]}")
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-oracle-masks" \
    --boxes none --masks oracle --filter exact_coverage --sensitivity 0.25 \
    --title "$dataset: oracle masks, exact coverage 25 %" > /dev/null
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-oracle-boxes" \
    --boxes oracle --filter keypoint_in_box \
    --title "$dataset: oracle boxes, keypoint in box (1/4)" > /dev/null
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-detector" \
    --boxes detector --confidence 0.1,0.2,0.3,0.4 --filter keypoint_in_box \
    --cache-dir "$cache_dir" \
    --title "$dataset: YOLOX-Nano boxes, keypoint in box (1/4)" > /dev/null
done
# The service's defaults with the real detector (GrabCut boxes, static feature budget,
# short-term tier, re-ranking of the 10 best) against the paper's filter and oracle masks.
for dataset in camvid camvid-stops rtabmap revisits-hard; do
  common=(run --dataset "$out/datasets/$dataset" --features 300,500,1000,2000
          --geom none,0,2,6 --threads "$threads")
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-detector-paper" "${paper[@]}" \
    --boxes detector --confidence 0.2 --cache-dir "$cache_dir" \
    --title "$dataset: YOLOX-Nano, the paper's filter" > /dev/null
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-detector-default" \
    --boxes detector --confidence 0.2 --cache-dir "$cache_dir" \
    --title "$dataset: YOLOX-Nano, the service's defaults" > /dev/null
  [ "$dataset" = rtabmap ] && continue
  "$eval_bin" "${common[@]}" --out "$out/results/$dataset-oracle-paper" "${paper[@]}" \
    --masks oracle --filter exact_coverage --sensitivity 0.25 \
    --title "$dataset: oracle masks, the paper's filter" > /dev/null
done
echo "results in $out/results/*/table3.md"
