// rgbd-gt pick: click pairs of points in the photo and in the scan image; the server knows the
// scan point under each scan pixel, solves the pose live and saves PAIRS.csv.
"use strict";

// One zoomable, pannable image on a canvas. Image coordinates: (0, 0) is the top-left corner of
// the first pixel, so pixel i spans [i, i + 1) and its centre is i + 0.5.
class ImageView {
  constructor(canvas, onPick) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.img = null;
    this.overlay = null;
    this.overlayAlpha = 0;
    this.scale = 1;
    this.ox = 0;
    this.oy = 0;
    this.markers = [];
    this.onPick = onPick;
    let drag = null;
    canvas.addEventListener("mousedown", (e) => { drag = { x: e.offsetX, y: e.offsetY, ox: this.ox, oy: this.oy, moved: false }; });
    canvas.addEventListener("mousemove", (e) => {
      if (!drag) return;
      const dx = e.offsetX - drag.x, dy = e.offsetY - drag.y;
      if (Math.abs(dx) + Math.abs(dy) > 3) drag.moved = true;
      if (drag.moved) { this.ox = drag.ox + dx; this.oy = drag.oy + dy; this.fitted = false; this.draw(); }
    });
    canvas.addEventListener("mouseup", (e) => {
      if (drag && !drag.moved) { const [x, y] = this.toImage(e.offsetX, e.offsetY); this.onPick(x, y); }
      drag = null;
    });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const f = Math.exp(-e.deltaY * 0.0015);
      const [x, y] = this.toImage(e.offsetX, e.offsetY);
      this.scale *= f;
      this.ox = e.offsetX - x * this.scale;
      this.oy = e.offsetY - y * this.scale;
      this.fitted = false;
      this.draw();
    }, { passive: false });
    new ResizeObserver(() => this.resize()).observe(canvas);
  }
  resize() {
    this.canvas.width = this.canvas.clientWidth;
    this.canvas.height = this.canvas.clientHeight;
    // the layout may still settle after the image arrives: keep it fitted until the user zooms or pans
    if (this.fitted) this.fit(); else this.draw();
  }
  setImage(img) {
    this.img = img;
    this.fit();
  }
  fit() {
    if (!this.img) return;
    const s = Math.min(this.canvas.width / this.img.width, this.canvas.height / this.img.height);
    this.scale = s;
    this.ox = (this.canvas.width - this.img.width * s) / 2;
    this.oy = (this.canvas.height - this.img.height * s) / 2;
    this.fitted = true;
    this.draw();
  }
  toImage(sx, sy) { return [(sx - this.ox) / this.scale, (sy - this.oy) / this.scale]; }
  toScreen(x, y) {
    const r = this.canvas.getBoundingClientRect();
    return [r.left + x * this.scale + this.ox, r.top + y * this.scale + this.oy];
  }
  draw() {
    const c = this.ctx;
    c.setTransform(1, 0, 0, 1, 0, 0);
    c.fillStyle = "#000";
    c.fillRect(0, 0, this.canvas.width, this.canvas.height);
    if (!this.img) return;
    c.imageSmoothingEnabled = this.scale < 2;
    c.setTransform(this.scale, 0, 0, this.scale, this.ox, this.oy);
    c.drawImage(this.img, 0, 0);
    if (this.overlay && this.overlayAlpha > 0) {
      c.globalAlpha = this.overlayAlpha;
      c.drawImage(this.overlay, 0, 0, this.img.width, this.img.height);
      c.globalAlpha = 1;
    }
    c.setTransform(1, 0, 0, 1, 0, 0);
    for (const m of this.markers) {
      const [sx, sy] = [m.x * this.scale + this.ox, m.y * this.scale + this.oy];
      c.strokeStyle = m.color;
      c.lineWidth = m.selected ? 3 : 1.5;
      if (m.to) {  // where the pose puts the scan point
        const [tx, ty] = [m.to[0] * this.scale + this.ox, m.to[1] * this.scale + this.oy];
        c.beginPath(); c.moveTo(sx, sy); c.lineTo(tx, ty); c.stroke();
        c.beginPath(); c.moveTo(tx - 5, ty); c.lineTo(tx + 5, ty); c.moveTo(tx, ty - 5); c.lineTo(tx, ty + 5); c.stroke();
      }
      c.beginPath(); c.arc(sx, sy, 6, 0, 2 * Math.PI); c.stroke();
      c.fillStyle = m.color;
      c.font = "12px system-ui";
      c.fillText(m.label, sx + 8, sy - 8);
    }
  }
}

const api = {
  get: (path) => fetch(path).then((r) => r.json()),
  post: (path, data) => fetch(path, { method: "POST", body: JSON.stringify(data) }).then((r) => r.json()),
};

function loadImage(src) {
  return new Promise((resolve) => { const i = new Image(); i.onload = () => resolve(i); i.src = src; });
}

class Picker {
  constructor() {
    this.pairs = [];  // {u, v, x, y, z, label, sx, sy} (sx, sy: scan image pixel)
    this.pending = {};
    this.selected = -1;
    this.solution = null;
    this.solving = 0;
    this.photo = new ImageView(document.getElementById("photo"), (x, y) => this.pickPhoto(x, y));
    this.scan = new ImageView(document.getElementById("scan"), (x, y) => this.pickScan(x, y));
    document.getElementById("save").onclick = () => this.save(false);
    document.getElementById("done").onclick = () => this.save(true);
    document.getElementById("show-overlay").onchange = () => this.showOverlay();
    document.getElementById("opacity").oninput = () => this.showOverlay();
    document.addEventListener("keydown", (e) => { if (e.key === "Escape") { this.pending = {}; this.select(-1); } });
  }
  async start() {
    this.info = await api.get("/api/info");
    document.getElementById("view-kind").textContent = this.info.view_kind;
    const [photo, view] = await Promise.all([loadImage("/photo.jpg"), loadImage("/view.png")]);
    this.photo.setImage(photo);
    this.scan.setImage(view);
    this.pairs = this.info.pairs.map((p) => ({ ...p }));
    this.status(this.info.camera ? "Pick 6 or more pairs: the pose is solved as you go."
                                 : "No --camera: pairs are saved, but no pose is solved.");
    this.ready = true;
    this.changed();
  }
  status(text) { document.getElementById("status").textContent = text; }
  pickPhoto(x, y) {
    const u = x - 0.5, v = y - 0.5;  // OpenCV pixel coordinates: the first pixel's centre is (0, 0)
    if (this.selected >= 0) { Object.assign(this.pairs[this.selected], { u, v }); this.select(-1); return this.changed(); }
    this.pending.photo = { u, v };
    this.complete();
  }
  async pickScan(x, y) {
    const r = await api.get(`/api/point?x=${x}&y=${y}`);
    if (!r.xyz) { this.status("No scan point there: click on the scan."); return; }
    const p = { x: r.xyz[0], y: r.xyz[1], z: r.xyz[2], sx: x, sy: y };
    if (this.selected >= 0) { Object.assign(this.pairs[this.selected], p); this.select(-1); return this.changed(); }
    this.pending.scan = p;
    this.complete();
  }
  complete() {
    if (this.pending.photo && this.pending.scan) {
      this.pairs.push({ ...this.pending.photo, ...this.pending.scan, label: String(this.pairs.length + 1) });
      this.pending = {};
      this.changed();
    } else {
      this.status(this.pending.photo ? "Now the same point in the scan." : "Now the same point in the photo.");
      this.redraw();
    }
  }
  select(k) { this.selected = this.selected === k ? -1 : k; this.render(); }
  remove(k) { this.pairs.splice(k, 1); this.select(-1); this.changed(); }
  async changed() {
    this.solution = null;
    this.render();
    if (!this.info.camera || this.pairs.length < 6) {
      if (this.info.camera) this.status(`${this.pairs.length} pairs: ${6 - this.pairs.length} more to solve the pose.`);
      return;
    }
    const ticket = ++this.solving;
    this.status(`${this.pairs.length} pairs: solving...`);
    const r = await api.post("/api/solve", { pairs: this.pairs });
    if (ticket !== this.solving) return;  // a newer change is being solved
    if (!r.ok) { this.status(r.error); return; }
    this.solution = r;
    this.overlayImage = await loadImage(`/overlay.png?t=${ticket}`);
    document.getElementById("show-overlay").disabled = false;
    this.status(`${this.pairs.length} pairs, ${r.inliers} used: RMS ${r.rms_px.toFixed(2)} px`);
    const u = r.uncertainty;
    document.getElementById("pose").textContent = `pose solved (focal ${r.focal_px.toFixed(1)} px` +
      (u ? `; 1 sigma ${u.rotation_deg.toFixed(3)} deg, ${u.translation_mm.toFixed(1)} mm` : "") + ")";
    this.showOverlay();
    this.render();
  }
  showOverlay() {
    const on = document.getElementById("show-overlay").checked && this.solution;
    this.photo.overlay = on ? this.overlayImage : null;
    this.photo.overlayAlpha = document.getElementById("opacity").value / 100;
    this.photo.draw();
  }
  redraw() {
    const s = this.solution;
    const color = (k) => (s ? (s.pairs[k].inlier ? "#4f4" : "#f44") : "#4cf");
    this.photo.markers = this.pairs.map((p, k) => ({ x: p.u + 0.5, y: p.v + 0.5, label: p.label, color: color(k),
      selected: k === this.selected, to: s ? [s.pairs[k].u + 0.5, s.pairs[k].v + 0.5] : null }));
    this.scan.markers = this.pairs.filter((p) => p.sx !== undefined).map((p) => ({ x: p.sx, y: p.sy, label: p.label,
      color: "#4cf", selected: this.pairs.indexOf(p) === this.selected }));
    if (this.pending.photo) this.photo.markers.push({ x: this.pending.photo.u + 0.5, y: this.pending.photo.v + 0.5, label: "?", color: "#ff0" });
    if (this.pending.scan) this.scan.markers.push({ x: this.pending.scan.sx, y: this.pending.scan.sy, label: "?", color: "#ff0" });
    this.photo.draw();
    this.scan.draw();
  }
  render() {
    const body = document.querySelector("#pairs tbody");
    body.innerHTML = "";
    const s = this.solution;
    this.pairs.forEach((p, k) => {
      const tr = document.createElement("tr");
      if (k === this.selected) tr.className = "selected";
      if (s && !s.pairs[k].inlier) tr.className += " outlier";
      const cells = [k + 1, null, p.u.toFixed(1), p.v.toFixed(1), p.x.toFixed(3), p.y.toFixed(3), p.z.toFixed(3),
                     s && s.pairs[k].residual_px !== null ? s.pairs[k].residual_px.toFixed(2) : "", s ? (s.pairs[k].inlier ? "yes" : "no") : ""];
      cells.forEach((c, j) => {
        const td = document.createElement("td");
        if (j === 1) {
          const input = document.createElement("input");
          input.value = p.label;
          input.onchange = () => { p.label = input.value; this.redraw(); };
          input.onclick = (e) => e.stopPropagation();
          td.appendChild(input);
        } else td.textContent = c;
        tr.appendChild(td);
      });
      const del = document.createElement("td");
      const b = document.createElement("button");
      b.textContent = "delete";
      b.onclick = (e) => { e.stopPropagation(); this.remove(k); };
      del.appendChild(b);
      tr.appendChild(del);
      tr.onclick = () => this.select(k);
      body.appendChild(tr);
    });
    this.redraw();
  }
  async save(close) {
    const r = await api.post("/api/save", { pairs: this.pairs });
    this.status(r.ok ? `saved ${r.rows} pairs to ${r.path}` : r.error);
    this.saved = r.ok;
    if (r.ok && close) { await api.post("/api/quit", {}); this.status(`saved ${r.rows} pairs to ${r.path}; you can close this page`); }
  }
}

window.picker = new Picker();
window.picker.start();
