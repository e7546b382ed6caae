#!/usr/bin/env bash
# Train the shipped detector and keypoint models for the built-in robot on this machine's CPU
# (both networks at once, one torch thread each, sharing one render cache), then the semantic
# segmentation network (one thread, one render worker, its own render sets, three legs), and
# copy the ONNX files, model cards and export references into edge_agent/models/. Run again to
# resume after an interruption. The shipped detector and keypoint network now come from a GPU
# (scripts/train_models_gpu.py, since 2026-11-27): this script copies only the segmentation
# network unless DETECTOR=1 / KEYPOINTS=1 ask for the CPU-trained detector / keypoint model.
#   scripts/train_shipped_models.sh [OUT] [MINUTES] [SEGMENTATION_MINUTES]
set -euo pipefail
OUT=${1:-runs/models}
MINUTES=${2:-55}
SEG_MINUTES=${3:-40}
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
# whole frames with label images; the site views spread over 4 texture seeds, then a fine-tune
# with the site views spread over 8 (more floor and wall textures)
SEG=(--threads 1 --workers 1 --train-views 3000 --site-views 2000 --val-views 200)
smartedge train segmentation --out "$OUT/seg" --minutes "$SEG_MINUTES" --site-seeds 4 \
    "${SEG[@]}" > "$OUT/segmentation.log" 2>&1
smartedge train segmentation --out "$OUT/seg_ft" --init-from "$OUT/seg/segmentation.ckpt" \
    --lr 8e-4 --steps 1100 --site-seeds 8 "${SEG[@]}" > "$OUT/segmentation_ft.log" 2>&1
# then what the robot's own head camera sees (furniture from ~1 m up, not from the ceiling):
# 2,000 head-camera views over texture seeds 0 and 2-9, keeping the site and randomized views
smartedge train segmentation --out "$OUT/seg_robot" --init-from "$OUT/seg_ft/segmentation.ckpt" \
    --lr 8e-4 --steps 1863 --site-seeds 8 --robot-views 2000 "${SEG[@]}" \
    > "$OUT/segmentation_robot.log" 2>&1
mkdir -p edge_agent/models
kinds=()
[ "${DETECTOR:-0}" = 1 ] && kinds+=(detector)
[ "${KEYPOINTS:-0}" = 1 ] && kinds+=(keypoints)
for kind in "${kinds[@]+"${kinds[@]}"}"; do
    cp "$OUT/$kind.onnx" "$OUT/$kind.json" "$OUT/$kind.md" "$OUT/$kind.reference.npz" \
        edge_agent/models/
done
cp "$OUT"/seg_robot/segmentation.{onnx,json,md,reference.npz} edge_agent/models/
echo "shipped models updated in edge_agent/models/"
