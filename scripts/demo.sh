#!/usr/bin/env bash
# The demo: for now, ingest the real pump-room scan from the shared data (when present).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${RGBD_GT_DATA:-../shared/data}
OUT=demo_out
mkdir -p "$OUT"
if [ -f "$DATA/e57/pumpA.e57" ]; then
    .venv/bin/rgbd-gt ingest "$DATA/e57/pumpA.e57" -o "$OUT/pumpA.ply" --extract-images "$OUT/images"
    echo "demo: the scan is in $OUT/pumpA.ply, its embedded photo in $OUT/images/"
else
    echo "demo: $DATA/e57/pumpA.e57 not found; nothing to ingest (see README)"
fi
