#!/usr/bin/env bash
# Train the shipped detector and keypoint models for the built-in robot on this machine's CPU
# (both networks at once, one torch thread each, sharing one render cache), then copy the ONNX
# files and model cards into edge_agent/models/. Run again to resume after an interruption.
#   scripts/train_shipped_models.sh [OUT] [MINUTES]
set -euo pipefail
OUT=${1:-runs/models}
MINUTES=${2:-55}
VIEWS=(--train-views 4000 --site-views 1200 --val-views 200)
mkdir -p "$OUT"
smartedge train detector --out "$OUT" --minutes "$MINUTES" --threads 1 "${VIEWS[@]}" \
    > "$OUT/detector.log" 2>&1 &
det=$!
# the keypoint run reuses the render cache: start it once the detector run has finished rendering
until grep -q "parameters," "$OUT/detector.log" 2>/dev/null; do
    kill -0 "$det" 2>/dev/null || { cat "$OUT/detector.log"; exit 1; }
    sleep 5
done
smartedge train keypoints --out "$OUT" --minutes "$MINUTES" --threads 1 "${VIEWS[@]}" \
    > "$OUT/keypoints.log" 2>&1 &
kp=$!
wait "$det" "$kp"
mkdir -p edge_agent/models
for kind in detector keypoints; do
    cp "$OUT/$kind.onnx" "$OUT/$kind.json" "$OUT/$kind.md" edge_agent/models/
done
echo "shipped models updated in edge_agent/models/"
