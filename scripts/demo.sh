#!/usr/bin/env bash
# The demo: the whole workflow on the built-in synthetic scene (one scan, two photos), then the
# errors of the initial and refined poses against the scene's exact truth.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=demo_out
.venv/bin/rgbd-gt synth "$OUT/scene" --size small --seed 0 --photos 2
# rgbd-gt run resumes from outputs that exist: start afresh so that the demo shows this code's results
rm -rf "$OUT/run"
.venv/bin/rgbd-gt run configs/example.yaml
.venv/bin/python - <<'PY'
from pathlib import Path
from rgbd_gt.io import read_pose
from rgbd_gt.pose import rotation_error_deg, translation_error_m
scene, run = Path("demo_out/scene"), Path("demo_out/run")
for photo, truth in (("photo", "gt_pose.yaml"), ("photo_1", "gt_pose_1.yaml")):
    gt = read_pose(scene / truth)[0]
    for step in ("init", "pose"):
        T = read_pose(run / photo / f"{step}.yaml")[0]
        print(f"{photo:8s} {'init-pose' if step == 'init' else 'refine':9s} error: "
              f"{translation_error_m(T, gt) * 1e3:7.3f} mm {rotation_error_deg(T, gt):.4f} deg")
print("depth maps: demo_out/run/*/depth.exr (and depth.png, mm); edge overlays: demo_out/run/*/qa.png; "
      "the run at a glance: demo_out/run/report.html; as a data set: rgbd-gt export demo_out/run -o dataset -f plain")
PY
