"""The local web server of `rgbd-gt pick`: the standard library's, on 127.0.0.1 only.

The page (pick_page/, static, no dependencies) asks for the photo, the scan image, the scan
point under a click, the live pose of the pairs so far and its overlay, and saves the pairs.
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import cv2
import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError
from rgbd_gt.init.pick import ClickView, solve, write_pairs
from rgbd_gt.io.json_text import json_text
from rgbd_gt.scan import Scan

PAGE_FILES = {"/": ("index.html", "text/html"), "/pick.js": ("pick.js", "text/javascript"),
              "/pick.css": ("pick.css", "text/css")}
OVERLAY_SIDE = 1600  # the live overlay's longer side (pixels)


@dataclass
class PickSession:
    """What the page works on; `pairs` are the rows loaded from an existing output."""

    scan: Scan
    photo: np.ndarray  # (H, W, 3) uint8 RGB
    view: ClickView
    output: Path
    camera: Camera | None = None
    estimate_focal: bool = False
    ransac_px: float = 4.0
    pairs: list[dict] = field(default_factory=list)
    saved: int = 0  # rows in the last save
    overlay_png: bytes = b""
    lock: threading.Lock = field(default_factory=threading.Lock)

    def info(self) -> dict:
        h, w = self.photo.shape[:2]
        vh, vw = self.view.image.shape[:2]
        return {"photo": [w, h], "view": [vw, vh], "view_kind": self.view.kind, "camera": self.camera is not None,
                "estimate_focal": self.estimate_focal, "output": str(self.output), "pairs": self.pairs}

    def solve(self, pairs: list[dict]) -> dict:
        """The live pose and its overlay at most OVERLAY_SIDE: the blend, or for a sweep the
        visible points as dots over the photo (as `overlay` draws them)."""
        from rgbd_gt.camera import rescale
        from rgbd_gt.qa.overlay import blend, points_image, render_colors
        from rgbd_gt.render.blocks import view_of
        from rgbd_gt.render.points import is_sweep
        from rgbd_gt.render.renders import Renders
        from rgbd_gt.scan import scan_colors

        if self.camera is None:
            raise InputError("the live pose needs --camera")
        out = solve(pairs, self.camera, self.estimate_focal, self.ransac_px)
        cam = out.pop("camera")
        s = min(1.0, OVERLAY_SIDE / max(cam.size))
        small = rescale(cam, max(1, round(cam.width * s)), max(1, round(cam.height * s)))
        photo = cv2.resize(self.photo, small.size, interpolation=cv2.INTER_AREA)
        T = np.array(out["T_cam_from_scan"])
        seen = view_of(self.scan, small, [T])  # a render costs what the photo sees
        renders = Renders(seen, scan_colors(seen))
        if is_sweep(seen):
            picture = points_image(renders, photo, small, T)[0]
        else:
            picture = blend(photo, *render_colors(renders, small, T))
        ok, png = cv2.imencode(".png", cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
        with self.lock:
            self.overlay_png = png.tobytes()
        return out


def request_pairs(data) -> list[dict]:
    """The pairs of a request's JSON body ({"pairs": [{u, v, x, y, z, label}, ...]}), each
    coordinate a finite number or null (a pair half made); InputError otherwise. The page sends
    only such; anything else is a request made by hand, answered with an error, not a traceback."""
    pairs = data.get("pairs", []) if isinstance(data, dict) else None
    if not isinstance(pairs, list) or not all(isinstance(p, dict) for p in pairs):
        raise InputError("the request needs pairs: a list of {u, v, x, y, z}")
    for k, p in enumerate(pairs, 1):
        for c in "uvxyz":
            v = p.get(c)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
                raise InputError(f"pair {k}: {c} must be a finite number, got {v!r}")
    return pairs


def _handler(session: PickSession, stop: threading.Event):
    page = resources.files("rgbd_gt.init") / "pick_page"
    photo_jpg = cv2.imencode(".jpg", cv2.cvtColor(session.photo, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()
    view_png = cv2.imencode(".png", cv2.cvtColor(session.view.image, cv2.COLOR_RGB2BGR))[1].tobytes()

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:  # the terminal shows the command's own lines only
            pass

        def _send(self, body: bytes, kind: str, code: int = 200) -> None:
            self.send_response(code)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, data, code: int = 200) -> None:
            # the page's JSON.parse refuses json.dumps' bare NaN: a figure that is not finite is null
            self._send(json_text(data, indent=None).encode(), "application/json", code)

        def do_GET(self) -> None:
            url = urlparse(self.path)
            if url.path in PAGE_FILES:
                name, kind = PAGE_FILES[url.path]
                self._send((page / name).read_bytes(), kind + "; charset=utf-8")
            elif url.path == "/photo.jpg":
                self._send(photo_jpg, "image/jpeg")
            elif url.path == "/view.png":
                self._send(view_png, "image/png")
            elif url.path == "/overlay.png":
                self._send(session.overlay_png, "image/png")
            elif url.path == "/api/info":
                self._json(session.info())
            elif url.path == "/api/point":
                q = parse_qs(url.query)
                try:
                    x, y = float(q["x"][0]), float(q["y"][0])
                except (KeyError, ValueError):
                    x = y = math.nan
                if not (math.isfinite(x) and math.isfinite(y)):
                    return self._json({"error": "x and y are needed, as finite numbers"}, 400)
                p = session.view.point_at(x, y)
                self._json({"xyz": None if p is None else p.tolist()})
            else:
                self._json({"error": "not found"}, 404)

        def do_POST(self) -> None:
            try:  # a bad length, bytes that are not UTF-8 or text that is not JSON
                data = json.loads(self.rfile.read(int(self.headers.get("Content-Length", 0))) or b"{}")
            except ValueError:
                return self._json({"error": "not JSON"}, 400)
            url = urlparse(self.path)
            try:
                if url.path == "/api/solve":
                    self._json({"ok": True, **session.solve(request_pairs(data))})
                elif url.path == "/api/save":
                    pairs = [p for p in request_pairs(data) if all(p.get(c) is not None for c in "uvxyz")]
                    write_pairs(session.output, pairs)
                    session.saved = len(pairs)
                    self._json({"ok": True, "rows": len(pairs), "path": str(session.output)})
                elif url.path == "/api/quit":
                    self._json({"ok": True})
                    stop.set()
                else:
                    self._json({"error": "not found"}, 404)
            except InputError as exc:
                self._json({"ok": False, "error": str(exc)})

    return Handler


def serve(session: PickSession, port: int = 0, ready=None) -> None:
    """Serve the page on 127.0.0.1:port (0: any free port) until the page says it is done or the
    user interrupts. ready(url) is called once the server listens."""
    stop = threading.Event()
    server = ThreadingHTTPServer(("127.0.0.1", port), _handler(session, stop))
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        if ready is not None:
            ready(f"http://127.0.0.1:{server.server_address[1]}/")
        while not stop.wait(0.2):
            pass
    finally:
        server.shutdown()
        server.server_close()
