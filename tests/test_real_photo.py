"""docs/real-data.md's walkthrough on the real files: pumpA's scan and its photo, with the picks
and camera files kept beside that page (docs/real-data/). The photo faces the scanner, so it sees
the back of what the scanner saw: the commands must say so rather than write or trust it."""

import numpy as np
import yaml

from conftest import ROOT, assert_one_line_error, run_cli
from rgbd_gt.io.pose_file import read_pose

PAGE = ROOT / "docs" / "real-data"


def test_pumpA_from_picks_to_a_verdict(e57_dir, tmp_path):
    assert run_cli("ingest", e57_dir / "pumpA.e57", "-o", tmp_path / "scan.ply", "--extract-images", tmp_path / "images").returncode == 0
    scan, photo = tmp_path / "scan.ply", tmp_path / "images" / "pumpA_0_pumpVisual.jpg"
    common = ["--scan", scan, "--image", photo, "--correspondences", PAGE / "picks.csv"]

    # a threshold tighter than the picks fit names the option to loosen
    assert_one_line_error(run_cli("init-pose", *common, "--camera", PAGE / "cam3346.yaml", "--ransac-px", "1", "-o", tmp_path / "x.yaml"),
                          "RANSAC PnP found no pose", "--ransac-px")
    # six pairs on two vertical lines and a point behind them fix the focal length only roughly, and
    # it says so (a loose threshold only to keep RANSAC short; the estimate is the same at 4 px)
    proc = run_cli("init-pose", *common, "--camera", PAGE / "guess.yaml", "--estimate-focal", "--ransac-px", "40",
                   "--camera-out", tmp_path / "f.yaml", "-o", tmp_path / "init_f.yaml")
    assert proc.returncode == 0, proc.stderr
    focal = yaml.safe_load((tmp_path / "f.yaml").read_text())["fx"]
    sigma = yaml.safe_load((tmp_path / "init_f.yaml").read_text())["uncertainty"]["focal_px"]
    assert 2500 < focal < 4500 and sigma > 200, (focal, sigma)

    init = tmp_path / "init.yaml"
    proc = run_cli("init-pose", *common, "--camera", PAGE / "cam3346.yaml", "-o", init)
    assert proc.returncode == 0, proc.stderr
    meta = yaml.safe_load(init.read_text())
    assert meta["points_used"] >= 5 and meta["reprojection_rms_px"] < 5, meta
    assert 0.1 < meta["uncertainty"]["rotation_deg"] < 3, meta  # six hand picks: a start, and stated as one
    # a check the picks take no part in: the photo's vertical lines stand along the scan's vertical pipes
    assert meta["verticals_usable"] and meta["verticals_roll_low_deg"] < 0 < meta["verticals_roll_high_deg"], meta
    assert "verticals" in proc.stdout and "roll" in proc.stdout, proc.stdout
    T = read_pose(init)[0]
    centre = -T[:3, :3].T @ T[:3, 3]
    assert np.linalg.norm(centre) > 6 and T[2, 1] > 0.8, (centre, T)  # across the room, facing the scanner (-y of it)

    proc = run_cli("export-depth", "--scan", scan, "--camera", PAGE / "cam3346.yaml", "--pose", init, "-o", tmp_path / "depth.exr")
    assert proc.returncode == 0, proc.stderr
    assert "seen from behind" in proc.stderr, proc.stderr
    behind = float(proc.stderr.split("warning: ")[1].split("%")[0])
    assert behind > 70, proc.stderr

    # refine on a photo that sees the scan from behind cannot be trusted, and is not
    refined = tmp_path / "refined.yaml"
    proc = run_cli("refine", "--scan", scan, "--image", photo, "--camera", PAGE / "cam3346.yaml", "--init", init, "-o", refined)
    assert proc.returncode == 0, proc.stderr
    done = yaml.safe_load(refined.read_text())
    assert done["verdict"] == "failed", proc.stdout
    # refine reports the verticals check beside its verdict: the picked pose upright, its result tilted
    assert done["init_verticals_roll_low_deg"] < 0 < done["init_verticals_roll_high_deg"], done
    assert done["verticals_roll_high_deg"] < -1.0 or done["verticals_roll_low_deg"] > 1.0, done
    # the pipes and supports say the same by geometry alone: the picked pose holds the photo upright,
    # refine's tilts it by more than a degree
    proc = run_cli("qa-edges", "--scan", scan, "--image", photo, "--camera", PAGE / "cam3346.yaml", "--pose", refined,
                   "--before", init, "-o", tmp_path / "qa.png", "--json", tmp_path / "qa.json")
    assert proc.returncode == 0, proc.stderr
    qa = yaml.safe_load((tmp_path / "qa.json").read_text())
    assert qa["before_verticals_usable"] and abs(qa["before_verticals_roll_deg"]) < 0.5, qa
    assert qa["verticals_roll_high_deg"] < -1.0 or qa["verticals_roll_low_deg"] > 1.0, qa
