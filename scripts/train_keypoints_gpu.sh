#!/usr/bin/env bash
# Train the shipped keypoint network on a GPU machine (made 2026-11-26 on one H200 with 16
# cores: render 26,200 views in ~100 s, train 4 minutes in bf16, ~7,400 steps of batch 128),
# then measure its confidence -> sigma table through the deployed pipeline (with the test-time
# flip the card asks for) and copy it into edge_agent/models/. Needs the train extra and a
# headless OpenGL (EGL) driver for the renders. Run again to resume; the checkpoint also
# resumes on another machine (`--device cpu`).
#   scripts/train_keypoints_gpu.sh [OUT] [MINUTES]
set -euo pipefail
OUT=${1:-runs/keypoints_gpu}
MINUTES=${2:-4}
WORKERS=$(nproc)
smartedge train keypoints --out "$OUT" --train-views 17800 --site-views 8400 --site-seeds 3 \
    --val-views 200 --workers "$WORKERS" --threads 4 --batch 128 --lr 2e-3 \
    --minutes "$MINUTES" --mirror --device auto --no-calibration 2>&1 | tee "$OUT.log"
# the pipeline needs a detector beside the keypoint model: the shipped one
for f in detector.onnx detector.json detector.md detector.reference.npz; do
    [ -f "$OUT/$f" ] || cp "edge_agent/models/$f" "$OUT/"
done
smartedge evaluate keypoints --model "$OUT" --calibrate --count 200
cp "$OUT"/keypoints.{onnx,json,md,reference.npz} edge_agent/models/
echo "shipped keypoint model updated in edge_agent/models/"
