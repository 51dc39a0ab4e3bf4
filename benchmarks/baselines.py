"""Feature baselines: match ORB or SIFT features between the photo and an image rendered from
the colored cloud at the initial pose, lift the rendered keypoints to 3D, and solve RANSAC PnP."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from rgbd_gt.camera import Camera
from rgbd_gt.pose import rigid, transform_points
from rgbd_gt.render.splat import render_points


def feature_pose(points: np.ndarray, colors: np.ndarray, photo: np.ndarray, camera: Camera,
                 T_init: np.ndarray, kind: str = "sift") -> np.ndarray:
    """T_cam_from_scan estimated by feature matching + RANSAC PnP; T_init when it fails."""
    cam_pts = torch.as_tensor(transform_points(T_init, points), dtype=torch.float32)
    img, _, index = render_points(cam_pts, torch.as_tensor(colors), torch.as_tensor(camera.K, dtype=torch.float32),
                                  camera.size, radius=0)
    rendered = img.numpy().astype(np.uint8)
    index = index.numpy()
    g1 = cv2.cvtColor(rendered, cv2.COLOR_RGB2GRAY)
    g2 = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    if kind == "orb":
        det = cv2.ORB_create(4000)
        norm = cv2.NORM_HAMMING
    else:
        det = cv2.SIFT_create(4000)
        norm = cv2.NORM_L2
    k1, d1 = det.detectAndCompute(g1, (index >= 0).astype(np.uint8) * 255)
    k2, d2 = det.detectAndCompute(g2, None)
    if d1 is None or d2 is None or len(k1) < 6 or len(k2) < 6:
        return T_init
    matches = cv2.BFMatcher(norm).knnMatch(d1, d2, k=2)
    good = [m for m, n in (p for p in matches if len(p) == 2) if m.distance < 0.8 * n.distance]
    obj, img_pts = [], []
    for m in good:
        u, v = np.round(k1[m.queryIdx].pt).astype(int)
        i = index[min(v, camera.height - 1), min(u, camera.width - 1)]
        if i >= 0:
            obj.append(points[i])
            img_pts.append(k2[m.trainIdx].pt)
    if len(obj) < 6:
        return T_init
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        np.array(obj, np.float64), np.array(img_pts, np.float64), camera.K, None,
        reprojectionError=2.0, iterationsCount=2000, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < 6:
        return T_init
    idx = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(np.array(obj)[idx], np.array(img_pts)[idx], camera.K, None, rvec, tvec)
    return rigid(cv2.Rodrigues(rvec)[0], tvec)
