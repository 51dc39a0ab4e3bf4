#!/usr/bin/env bash
# The demo: a built-in synthetic scene, then ingest of its scan (and of the real pump-room
# scan from the shared data, when present).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${RGBD_GT_DATA:-../shared/data}
OUT=demo_out
mkdir -p "$OUT"
.venv/bin/rgbd-gt synth "$OUT/scene" --seed 0
.venv/bin/rgbd-gt ingest "$OUT/scene/scan.e57" -o "$OUT/scene_scan.ply"
if [ -f "$DATA/e57/pumpA.e57" ]; then
    .venv/bin/rgbd-gt ingest "$DATA/e57/pumpA.e57" -o "$OUT/pumpA.ply" --extract-images "$OUT/images"
fi
echo "demo: synthetic scene in $OUT/scene (photo.png, scan.e57, gt_pose.yaml, ...), ingested scans in $OUT/"
