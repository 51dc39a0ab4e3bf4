"""report.html: one static page (no server, nothing downloaded) to judge a run by eye: per photo
its thumbnail, the overlay and qa pictures, the verdict with its reasons and evidence, the depth
as a colored preview with its scale, the pose's and camera's 1-sigmas; a table of all photos
that sorts by any column; for a rig, each shot's rectified pair with horizontal lines. Its
pictures lie in report/ beside it."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from rgbd_gt.export.source import stated_uncertainty

THUMB = 480  # pixels, the longer side of the page's pictures
SPARSE = 0.2  # a depth map with depth on fewer of its pixels is a sweep's points

SORT_SCRIPT = """
document.querySelectorAll('th[data-col]').forEach(function (th) {
  th.addEventListener('click', function () {
    var table = th.closest('table'), body = table.tBodies[0], col = +th.dataset.col;
    var up = th.dataset.dir !== 'up'; th.dataset.dir = up ? 'up' : 'down';
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function (a, b) {
      var x = a.cells[col].dataset.sort, y = b.cells[col].dataset.sort;
      var nx = parseFloat(x), ny = parseFloat(y);
      var c = (!isNaN(nx) && !isNaN(ny)) ? nx - ny : (x < y ? -1 : x > y ? 1 : 0);
      return up ? c : -c;
    });
    rows.forEach(function (r) { body.appendChild(r); });
  });
});
"""

STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; } td, th { border: 1px solid #ccc; padding: 3px 8px; text-align: left; }
th[data-col] { cursor: pointer; background: #eee; } .ok { color: #070; } .suspect { color: #a60; } .failed { color: #b00; }
.photo { border-top: 2px solid #888; margin-top: 1.5em; padding-top: .5em; } img { max-width: 32%; margin: 2px; vertical-align: top; }
.scale { display: inline-block; width: 240px; height: 12px; vertical-align: middle;
         background: linear-gradient(to right, #30123b, #4686fb, #1be5b5, #a4fc3c, #fbb938, #e4460a, #7a0403); }
pre { background: #f6f6f6; padding: 6px; font-size: 85%; max-height: 16em; overflow: auto; }
"""

VERDICT_ORDER = {"ok": 0, "suspect": 1, "failed": 2}


def _thumb(image: np.ndarray, path: Path) -> str:
    """Write image (H, W[, 3]) uint8 RGB shrunk to THUMB as a PNG in path; its name for the page."""
    import cv2

    from rgbd_gt.io.image import write_image

    h, w = image.shape[:2]
    f = min(1.0, THUMB / max(h, w))
    small = cv2.resize(image, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA) if f < 1 else image
    write_image(path, small)
    return f"{path.parent.name}/{path.name}"


def depth_preview(z: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(H, W, 3) uint8 RGB of depth z (H, W) metres colored by turbo from its 1st to 99th
    percentile (black: no depth), and that range (metres)."""
    import cv2

    on = z > 0
    lo, hi = (np.percentile(z[on], [1, 99]) if on.any() else (0.0, 1.0))
    hi = max(hi, lo + 1e-6)
    gray = np.clip((z - lo) / (hi - lo) * 254, 0, 254).astype(np.uint8)
    if on.mean() < SPARSE:  # sparse (a sweep's points): each point grown to survive the thumbnail, the nearest on top
        k = max(3, 2 * (max(z.shape) // THUMB) + 1)
        near = cv2.dilate(np.where(on, 255 - gray, 0).astype(np.uint8), np.ones((k, k), np.uint8))
        on, gray = near > 0, (255 - near).astype(np.uint8)
    rgb = cv2.applyColorMap(gray, cv2.COLORMAP_TURBO)[:, :, ::-1].copy()
    rgb[~on] = 0
    return rgb, float(lo), float(hi)


def rectified_lines(left: np.ndarray, right: np.ndarray, every: int = 12) -> np.ndarray:
    """left | right side by side with `every` horizontal lines across both: a rectified pair's
    features lie on one row in both."""
    pair = np.concatenate([left, right], axis=1).copy()
    for v in np.linspace(0, pair.shape[0] - 1, every + 2)[1:-1].astype(int):
        pair[v] = (0, 255, 0)
    return pair


def _num(v, fmt: str = ".4g") -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float)):  # a hand-edited pose file's value: shown as it is
        return "-" if v is None else html.escape(str(v))
    return format(v, fmt) if np.isfinite(v) else "-"


def write_report(path: Path, sources: list, folder: Path | None = None, exported=None) -> None:
    """report.html at `path` with its pictures in report/ beside it, of the run's sources
    (`export.source.read_run`); folder: an export's output (its depth maps and rectified pairs
    are shown where the run has none); exported: that export's `export.dataset.Exported`."""
    from rgbd_gt.io.atomic import atomic_output

    assets = path.parent / "report"
    assets.mkdir(parents=True, exist_ok=True)
    several = len(sources) > 1
    photos = [(f"{src.name}_{s.name}" if several else s.name, s, src.name if several else None)
              for src in sources for s in src.photos]
    missing = [(f"{src.name}_{n}" if several else n, why) for src in sources for n, why in src.missing.items()]
    figures = exported.photos if exported is not None else {}
    sections = "".join(_photo_section(name, s, scan, assets, folder, figures.get(name) or {}) for name, s, scan in photos)
    pairs = "".join(_pair_section(key, pair, folder, assets) for key, pair in exported.pairs.items()) \
        if exported is not None and folder is not None else ""
    counts = ", ".join(f"{sum(s.verdict == v for _, s, _ in photos)} {v}" for v in VERDICT_ORDER)
    counts += f", {len(missing)} without a pose" if missing else ""
    n = len(photos) + len(missing)
    page = (f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>rgbd-gt report</title><style>{STYLE}</style></head><body>'
            f'<h1>rgbd-gt report</h1><p>{n} photo{"s" * (n != 1)}: {counts}. Click a column to sort.</p>'
            + _table(photos, missing) + (f"<h2>Stereo pairs</h2>{pairs}" if pairs else "") + "<h2>Photos</h2>" + sections
            + f"<script>{SORT_SCRIPT}</script></body></html>")
    with atomic_output(path) as tmp:
        tmp.write_text(page)


def _photo_section(name: str, s, scan: str | None, assets: Path, folder: Path | None, figures: dict) -> str:
    """A photo's part of the page: its pictures (the photo; the run's overlay, points and qa
    pictures; the depth preview from the run's or the export's millimetre PNG, which a preview
    needs no more than and reads 5x quicker than the EXR), verdict, 1-sigmas, export figures,
    reasons and evidence."""
    from rgbd_gt.export.formats import nerfstudio_folder
    from rgbd_gt.io.depth_file import read_png16
    from rgbd_gt.io.image import read_image

    here = s.pose_file.parent
    pictures = [("photo", _thumb(read_image(s.image), assets / f"{name}_photo.png"))]
    for label, file in (("overlay", "overlay_blend.png"), ("overlay: the sweep's points", "overlay_points.png"),
                        ("qa: edges", "qa.png")):
        if (here / file).is_file():
            pictures.append((label, _thumb(read_image(here / file), assets / f"{name}_{file}")))
    shown = [here / "depth.png"] + ([folder / "plain" / name / "depth.png", nerfstudio_folder(folder, scan) / "depth" / f"{name}.png"]
                                    if folder else [])
    depth_file = next((f for f in shown if f.is_file()), None)
    scale = ""
    if depth_file is not None:
        z = read_png16(depth_file) / 1000.0
        rgb, lo, hi = depth_preview(z)
        pictures.append(("depth", _thumb(rgb, assets / f"{name}_depth.png")))
        scale = (f'<p>depth: <span data-key="depth_min_m">{lo:.3f}</span> m <span class="scale"></span> '
                 f'<span data-key="depth_max_m">{hi:.3f}</span> m (1st to 99th percentile; black: no depth'
                 + ("; the sparse map's points drawn larger" if (z > 0).mean() < SPARSE else "") + ")</p>")
    u = stated_uncertainty(s.evidence)
    cam = ", ".join(f"{k} {v:.3g}" for k, v in s.camera_sigma.items()) or "as its file (not refined)"
    exported = ""
    if "valid" in figures:
        q = figures["depth_sigma_mm"]
        exported = (f"<p>exported: {figures['valid'] / figures['pixels']:.1%} of pixels valid, "
                    f"{figures['near_edge'] / figures['pixels']:.2%} near a depth edge; depth 1-sigma "
                    + (f"median {q['p50']:.3f} mm, 90% {q['p90']:.3f} mm</p>" if q else "unknown (no pixel valid)</p>"))
    imgs = "".join(f'<img src="{html.escape(src)}" alt="{html.escape(label)}" title="{html.escape(label)}">'
                   for label, src in pictures)
    reasons = "".join(f"<li>{html.escape(r)}</li>" for r in s.reasons) or "<li>none</li>"
    return (f'<div class="photo" id="{html.escape(name)}"><h3>{html.escape(name)} '
            f'<span class="{s.verdict}" data-key="verdict">{s.verdict}</span></h3>{imgs}{scale}'
            f'<p>pose 1-sigma (worst direction): <span data-key="rotation_deg">{_num(u.get("rotation_deg"))}</span> deg, '
            f'<span data-key="translation_mm">{_num(u.get("translation_mm"))}</span> mm, '
            f'<span data-key="image_px">{_num(u.get("image_px"))}</span> px; camera ({html.escape(s.camera_name)}) 1-sigma: '
            f'{html.escape(cam)}</p>{exported}<p>reasons:</p><ul>{reasons}</ul>'
            f'<details><summary>evidence</summary><pre>{html.escape(json.dumps(s.evidence, indent=1, default=str))}</pre></details></div>')


def _pair_section(key: str, pair: dict, folder: Path, assets: Path) -> str:
    """A rig shot's rectified pair (middlebury's, else kitti's files) with horizontal lines."""
    from rgbd_gt.io.image import read_image

    left, right = folder / "middlebury" / key / "im0.png", folder / "middlebury" / key / "im1.png"
    if not left.is_file():
        stem = f"{pair['kitti_index']:06d}_10.png"
        left, right = folder / "kitti" / "image_2" / stem, folder / "kitti" / "image_3" / stem
    if not left.is_file():
        return ""
    src = _thumb(rectified_lines(read_image(left), read_image(right)), assets / f"pair_{key}.png")
    return (f'<div class="photo"><h3>shot {html.escape(key)}: {html.escape(pair["left"])} | {html.escape(pair["right"])}</h3>'
            f'<img style="max-width:96%" src="{src}" alt="rectified pair {html.escape(key)}">'
            f'<p>baseline {pair["baseline_m"] * 1e3:.2f} mm; a feature must lie on one row in both halves</p></div>')


def _table(photos: list, missing: list) -> str:
    """The table of every photo, sortable by a click on a column (SORT_SCRIPT sorts on data-sort)."""
    head = ["photo", "verdict", "rotation 1-sigma (deg)", "translation 1-sigma (mm)", "image 1-sigma (px)", "reasons"]
    rows = []
    for n, s, _ in photos:
        u = stated_uncertainty(s.evidence)
        rows.append(f'<tr><td data-sort="{html.escape(n)}"><a href="#{html.escape(n)}">{html.escape(n)}</a></td>'
                    f'<td data-sort="{VERDICT_ORDER.get(s.verdict, 3)}" class="{s.verdict}">{s.verdict}</td>'
                    + "".join(f'<td data-sort="{u.get(k, "nan")}">{_num(u.get(k))}</td>'
                              for k in ("rotation_deg", "translation_mm", "image_px"))
                    + f'<td data-sort="{len(s.reasons)}">{html.escape("; ".join(s.reasons))}</td></tr>')
    rows += [f'<tr><td data-sort="{html.escape(n)}">{html.escape(n)}</td><td data-sort="3" class="failed">no pose</td>'
             + '<td data-sort="nan">-</td>' * 3 + f'<td data-sort="1">{html.escape(why)}</td></tr>' for n, why in missing]
    return ('<table id="photos"><thead><tr>' + "".join(f'<th data-col="{i}">{h}</th>' for i, h in enumerate(head))
            + f"</tr></thead><tbody>{''.join(rows)}</tbody></table>")
