# ruff: noqa: E501  (the embedded HTML/JavaScript keeps its own line lengths)
"""The session report: one self-contained HTML file (no network needed to open it).

Sections: summary and calibration (camera table and layout), per-camera
detection rates over time, a 3D viewer of the tracks with playback and
per-person colours (cameras drawn in the same view, forecasts as faded
skeletons), track timelines, and per-joint uncertainty. All data is embedded
as JSON; the viewer is a few hundred lines of plain canvas JavaScript.
Script errors are collected into ``#errors`` so tests (and people) see them.
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np

from capture.fileio import atomic_write_text, load_npz, load_toml
from capture.session import SessionLayout

_MAX_FRAMES = 2000  # frames embedded in the viewer (subsampled beyond)


def _r(a: np.ndarray, nd: int = 3) -> Any:
    """Round and turn NaN into None for JSON."""
    a = np.round(np.asarray(a, dtype=np.float64), nd)
    return np.where(np.isfinite(a), a, None).tolist()


def _rig_data(lay: SessionLayout) -> dict[str, Any] | None:
    if not lay.rig_toml.exists():
        return None
    try:
        from calibrate.camera import CameraRig

        rig = CameraRig.load(lay.rig_toml)
    except Exception as e:  # the report shows what it can
        return {"error": str(e), "cameras": []}
    cams = []
    for cam in rig.cameras:
        R = np.asarray(cam.R)
        cams.append({"name": cam.name, "size_wh": list(cam.size_wh), "f_px": _r([cam.K[0, 0], cam.K[1, 1]], 1),
                     "c_px": _r([cam.K[0, 2], cam.K[1, 2]], 1), "model": cam.model,
                     "center_m": _r(cam.center), "axis": _r(R[2]), "up": _r(-R[1])})
    return {"cameras": cams, "sha256": rig.sha256()}


def _detection_rates(lay: SessionLayout) -> dict[str, Any]:
    out = {}
    for cam in lay.detection_cameras():
        d = load_npz(lay.detections(cam))
        xy = d["xy_px"]
        people = np.isfinite(xy[..., 0]).any(-1).sum(-1) if xy.size else np.zeros(len(d["frame_index"]))
        joints = np.isfinite(xy[..., 0]).sum((-1, -2)) if xy.size else np.zeros(len(d["frame_index"]))
        out[cam] = {"people": people.astype(int).tolist(), "joints": joints.astype(int).tolist()}
    return out


def _tracks_data(lay: SessionLayout) -> dict[str, Any] | None:
    if not lay.tracks.exists():
        return None
    d = load_npz(lay.tracks)
    xyz = d["xyz_m"]
    T = xyz.shape[0]
    step = max(1, int(np.ceil(T / _MAX_FRAMES)))
    sel = np.arange(0, T, step)
    std = d["std_m"]
    present = np.isfinite(xyz[..., 0]).any(-1)  # (T,K)
    ok = np.isfinite(std)
    mean_std = np.where(ok.any(-1), np.where(ok, std, 0).sum(-1) / np.maximum(ok.sum(-1), 1), np.nan)
    return {
        "fps": float(d["fps"]) / step, "frame_index": d["frame_index"][sel].tolist(),
        "track_id": d["track_id"].tolist(), "joint_names": d["joint_names"].tolist(),
        "parents": d["parents"].tolist(), "xyz": _r(xyz[sel]), "present": present.astype(int).T.tolist(),
        "mean_std_m": _r(mean_std.T, 4) if std.size else [], "source": str(d["source"]),
        "step": step,
    }


def _forecast_data(lay: SessionLayout) -> dict[str, Any] | None:
    path = lay.root / "forecast" / "preview.npz"
    if not path.exists():
        return None
    d = load_npz(path)
    keys = {"xyz_m", "track_id", "start_index"}
    if not keys <= set(d):
        return None
    xyz = d["xyz_m"]
    if xyz.ndim != 4:  # (K,H,J,3) expected
        return None
    return {"xyz": _r(xyz), "track_id": d["track_id"].tolist(), "start_index": int(d["start_index"]),
            "model": str(d.get("model", "")), "fps": float(d["fps"]) if "fps" in d else None}


def _provenance(lay: SessionLayout) -> list[dict[str, Any]]:
    from pipeline.config import STAGES

    rows = []
    for stage in STAGES:
        p = lay.root / ".roomcap" / "provenance" / f"{stage}.json"
        if not p.exists():
            continue
        try:
            rec = json.loads(p.read_text())
            rows.append({"stage": rec["stage"], "version": rec["version"],
                         "model_sha256": rec.get("model_sha256", "")[:12], "inputs": len(rec["inputs"])})
        except (json.JSONDecodeError, KeyError):
            continue
    return rows


def collect(lay: SessionLayout, title: str) -> dict[str, Any]:
    meta = {}
    if lay.session_toml.exists():
        try:
            meta = load_toml(lay.session_toml)
        except Exception:
            meta = {}
    return {"title": title, "rig": _rig_data(lay), "detections": _detection_rates(lay),
            "tracks": _tracks_data(lay), "forecast": _forecast_data(lay), "provenance": _provenance(lay),
            "session": {k: v for k, v in meta.items() if isinstance(v, (str, int, float))}}


def render(data: dict[str, Any]) -> str:
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    return (_TEMPLATE.replace("__TITLE__", html.escape(data["title"]))
            .replace("__DATA__", payload).replace("__SCRIPT__", _SCRIPT))


def write_report(lay: SessionLayout, title: str = "") -> Path:
    atomic_write_text(lay.report_html, render(collect(lay, title or lay.root.name)))
    return lay.report_html


_TEMPLATE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__ — roomcap report</title>
<style>
body{font-family:system-ui,sans-serif;margin:0;background:#f4f5f7;color:#1d2330}
header{background:#1d2330;color:#fff;padding:14px 24px}header h1{margin:0;font-size:20px}
main{display:grid;grid-template-columns:minmax(520px,3fr) minmax(320px,2fr);gap:16px;padding:16px}
section{background:#fff;border-radius:8px;padding:12px 16px;box-shadow:0 1px 3px #0002}
h2{font-size:15px;margin:4px 0 10px}table{border-collapse:collapse;font-size:12px;width:100%}
td,th{border-bottom:1px solid #e3e5ea;padding:3px 6px;text-align:left}canvas{display:block;width:100%}
#viewer{background:#10141c;border-radius:6px;cursor:grab}.controls{display:flex;gap:8px;align-items:center;margin-top:6px}
.controls input[type=range]{flex:1}.legend span{display:inline-block;margin-right:10px;font-size:12px}
.swatch{display:inline-block;width:10px;height:10px;border-radius:2px;margin-right:4px}
#errors{color:#b00;white-space:pre-wrap;font-size:12px}.muted{color:#777;font-size:12px}
</style></head><body>
<header><h1>__TITLE__</h1><div class="muted" id="subtitle"></div></header>
<main>
<div>
<section><h2>3D tracks</h2><canvas id="viewer" width="960" height="600"></canvas>
<div class="controls"><button id="play">Pause</button><input id="frame" type="range" min="0" max="0" value="0">
<span id="frameLabel" class="muted"></span></div><div class="legend" id="legend"></div>
<div class="muted">Drag to orbit, wheel to zoom. Faded skeletons: forecast preview. Joint size grows with uncertainty.</div>
</section>
<section><h2>Track timelines</h2><canvas id="timeline" width="960" height="160"></canvas></section>
<section><h2>Uncertainty (mean per-joint std, mm)</h2><canvas id="uncertainty" width="960" height="160"></canvas></section>
</div>
<div>
<section><h2>Summary</h2><table id="summary"></table></section>
<section><h2>Calibration</h2><table id="cams"></table><canvas id="layout" width="480" height="300"></canvas></section>
<section><h2>Detections per camera (people per frame)</h2><canvas id="detections" width="480" height="220"></canvas></section>
<section><h2>Provenance</h2><table id="prov"></table></section>
<section><h2>Page errors</h2><div id="errors"></div></section>
</div>
</main>
<script>
window.__errors=[];
window.addEventListener('error',function(e){window.__errors.push(String(e.message));
  var el=document.getElementById('errors');if(el)el.textContent=window.__errors.join('\\n');});
(function(){var ce=console.error;console.error=function(){window.__errors.push(Array.from(arguments).join(' '));
  var el=document.getElementById('errors');if(el)el.textContent=window.__errors.join('\\n');ce.apply(console,arguments);};})();
</script>
<script id="data" type="application/json">__DATA__</script>
<script>__SCRIPT__</script>
</body></html>
"""

_SCRIPT = r"""
(function(){
const D = JSON.parse(document.getElementById('data').textContent);
const COLORS = ['#e6194b','#3cb44b','#4363d8','#f58231','#911eb4','#42d4f4','#f032e6','#bfef45','#fabed4',
                '#469990','#dcbeff','#9a6324','#fffac8','#800000','#aaffc3','#808000'];
const color = k => COLORS[k % COLORS.length];
const $ = id => document.getElementById(id);
function row(tbl, cells, head){const tr=document.createElement('tr');for(const c of cells){const td=document.createElement(head?'th':'td');td.textContent=c;tr.appendChild(td);}tbl.appendChild(tr);}

// ---------------------------------------------------------------- summary, cameras, provenance
const T = D.tracks;
const nFrames = T ? T.xyz.length : 0, nTracks = T ? T.track_id.length : 0;
$('subtitle').textContent = (T ? `${nTracks} tracks · ${nFrames} frames shown · ` : '') +
  `${Object.keys(D.detections).length} cameras with detections`;
const sm = $('summary');
row(sm, ['cameras (rig)', D.rig ? D.rig.cameras.length : 'no calibration']);
row(sm, ['tracks', T ? nTracks : 'no track file']);
row(sm, ['frames', T ? T.frame_index.length * T.step : '-']);
row(sm, ['track source', T ? T.source : '-']);
row(sm, ['forecast preview', D.forecast ? (D.forecast.model || 'yes') : 'none']);
for (const [k, v] of Object.entries(D.session || {})) row(sm, [k, String(v)]);
const ct = $('cams');
if (D.rig) { row(ct, ['camera','size','f (px)','centre (m)'], true);
  for (const c of D.rig.cameras) row(ct, [c.name, c.size_wh.join('×'), c.f_px.join(', '), c.center_m.map(v=>v.toFixed(2)).join(', ')]); }
const pt = $('prov'); row(pt, ['stage','version','model','inputs'], true);
for (const p of D.provenance) row(pt, [p.stage, p.version, p.model_sha256 || '-', p.inputs]);

// ---------------------------------------------------------------- small line plots
function plot(canvas, series, opts){
  const ctx = canvas.getContext('2d'), W = canvas.width, H = canvas.height, pad = 28;
  ctx.fillStyle = '#fff'; ctx.fillRect(0,0,W,H);
  let maxX = 1, maxY = 1e-9;
  for (const s of series) { maxX = Math.max(maxX, s.y.length - 1); for (const v of s.y) if (v !== null && v > maxY) maxY = v; }
  ctx.strokeStyle = '#ccd'; ctx.beginPath(); ctx.moveTo(pad, 4); ctx.lineTo(pad, H - pad); ctx.lineTo(W - 4, H - pad); ctx.stroke();
  ctx.fillStyle = '#555'; ctx.font = '11px sans-serif'; ctx.fillText(maxY.toFixed(opts.digits||0), 2, 12); ctx.fillText('0', 2, H - pad);
  ctx.fillText(opts.xlabel || 'frame', W - 60, H - 8);
  series.forEach((s, i) => { ctx.strokeStyle = s.color || color(i); ctx.lineWidth = 1.5; ctx.beginPath(); let pen = false;
    s.y.forEach((v, x) => { if (v === null) { pen = false; return; }
      const px = pad + (W - pad - 6) * x / maxX, py = H - pad - (H - pad - 8) * v / maxY;
      if (pen) ctx.lineTo(px, py); else ctx.moveTo(px, py); pen = true; }); ctx.stroke();
    if (s.label) { ctx.fillStyle = s.color || color(i); ctx.fillText(s.label, pad + 6 + 70 * i, 12); } });
}
plot($('detections'), Object.entries(D.detections).map(([cam, d], i) => ({label: cam, y: d.people, color: color(i)})), {});
if (T) {
  plot($('uncertainty'), T.track_id.map((id, k) => ({label: 'id ' + id, color: color(k),
    y: (T.mean_std_m[k] || []).map(v => v === null ? null : 1000 * v)})), {digits: 0});
  const tl = $('timeline'), c = tl.getContext('2d'), W = tl.width, H = tl.height;
  c.fillStyle = '#fff'; c.fillRect(0, 0, W, H);
  const rowH = Math.max(4, Math.min(18, (H - 10) / Math.max(1, nTracks)));
  T.present.forEach((pres, k) => { c.fillStyle = color(k); const n = pres.length;
    pres.forEach((p, t) => { if (p) c.fillRect(60 + (W - 70) * t / n, 5 + k * rowH, Math.max(1, (W - 70) / n), rowH - 2); });
    c.fillStyle = '#333'; c.font = '11px sans-serif'; c.fillText('id ' + T.track_id[k], 4, 5 + k * rowH + rowH - 4); });
}

// ---------------------------------------------------------------- camera layout (top view)
(function(){ const cv = $('layout'), c = cv.getContext('2d'), W = cv.width, H = cv.height;
  c.fillStyle = '#fff'; c.fillRect(0, 0, W, H); if (!D.rig || !D.rig.cameras.length) return;
  const pts = D.rig.cameras.map(k => k.center_m);
  let xs = pts.map(p => p[0]), ys = pts.map(p => p[1]);
  const minX = Math.min(...xs) - 0.5, maxX = Math.max(...xs) + 0.5, minY = Math.min(...ys) - 0.5, maxY = Math.max(...ys) + 0.5;
  const s = Math.min((W - 20) / (maxX - minX), (H - 20) / (maxY - minY));
  const P = p => [10 + (p[0] - minX) * s, H - 10 - (p[1] - minY) * s];
  c.strokeStyle = '#eee'; for (let g = Math.ceil(minX); g <= maxX; g++) { const a = P([g, minY]), b = P([g, maxY]); c.beginPath(); c.moveTo(...a); c.lineTo(...b); c.stroke(); }
  D.rig.cameras.forEach((k, i) => { const [x, y] = P(k.center_m); const a = k.axis;
    c.fillStyle = color(i); c.beginPath(); c.arc(x, y, 5, 0, 7); c.fill();
    c.strokeStyle = color(i); c.beginPath(); c.moveTo(x, y); c.lineTo(x + a[0] * 30, y - a[1] * 30); c.stroke();
    c.fillStyle = '#333'; c.font = '11px sans-serif'; c.fillText(k.name, x + 7, y - 7); });
})();

// ---------------------------------------------------------------- 3D viewer
const cv = $('viewer'), ctx = cv.getContext('2d');
let yaw = -0.6, pitch = 0.45, zoom = 1.0, frame = 0, playing = true;
let center = [0, 0, 1], radius = 4;
(function fit(){ const pts = [];
  if (T) for (const fr of T.xyz) for (const tr of fr) for (const j of tr) if (j && j[0] !== null) pts.push(j);
  if (!pts.length && D.rig) for (const k of D.rig.cameras) pts.push(k.center_m);
  if (!pts.length) return;
  const mean = [0, 1, 2].map(a => pts.reduce((s, p) => s + p[a], 0) / pts.length);
  center = mean; radius = Math.max(1.5, Math.sqrt(pts.reduce((s, p) => s + (p[0]-mean[0])**2 + (p[1]-mean[1])**2, 0) / pts.length) * 2.5);
})();
function project(p){ // orbit camera looking at `center`, z up
  const x = p[0] - center[0], y = p[1] - center[1], z = p[2] - center[2];
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const xr = cy * x - sy * y, yr = sy * x + cy * y;           // yaw about z
  const depth = cp * yr + sp * z, up = -sp * yr + cp * z;      // pitch
  const dist = radius * 2.2 / zoom, f = cv.height * 0.9;
  const d = dist + depth; if (d < 0.05) return null;
  return [cv.width / 2 + f * xr / d, cv.height / 2 - f * up / d, d];
}
function line(a, b, col, w){ const p = project(a), q = project(b); if (!p || !q) return;
  ctx.strokeStyle = col; ctx.lineWidth = w; ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]); ctx.stroke(); }
function skeleton(pose, col, w, std_m){
  if (!pose) return;
  const r = 2 + Math.min(8, (std_m || 0) * 200);  // joint marker grows with the track's uncertainty
  T.parents.forEach((p, j) => { if (p < 0) return; const a = pose[j], b = pose[p];
    if (a && b && a[0] !== null && b[0] !== null) line(a, b, col, w); });
  pose.forEach((j, i) => { if (!j || j[0] === null) return; const q = project(j); if (!q) return;
    ctx.fillStyle = col; ctx.beginPath(); ctx.arc(q[0], q[1], r, 0, 7); ctx.fill(); });
}
function draw(){
  ctx.fillStyle = '#10141c'; ctx.fillRect(0, 0, cv.width, cv.height);
  const g = Math.ceil(radius * 1.5);
  for (let i = -g; i <= g; i++) { line([center[0] + i, center[1] - g, 0], [center[0] + i, center[1] + g, 0], '#2a3242', 1);
    line([center[0] - g, center[1] + i, 0], [center[0] + g, center[1] + i, 0], '#2a3242', 1); }
  if (D.rig) for (const k of D.rig.cameras) { const c0 = k.center_m, a = k.axis;
    line(c0, [c0[0] + 0.4 * a[0], c0[1] + 0.4 * a[1], c0[2] + 0.4 * a[2]], '#8894aa', 2);
    const q = project(c0); if (q) { ctx.fillStyle = '#8894aa'; ctx.fillRect(q[0] - 3, q[1] - 3, 6, 6);
      ctx.font = '11px sans-serif'; ctx.fillText(k.name, q[0] + 5, q[1] - 5); } }
  if (T && nFrames) {
    const fr = T.xyz[frame];
    fr.forEach((pose, k) => skeleton(pose, color(k), 3, T.mean_std_m.length ? T.mean_std_m[k][frame] : 0));
    if (D.forecast && frame === nFrames - 1) D.forecast.xyz.forEach((traj, i) => {
      const k = T.track_id.indexOf(D.forecast.track_id[i]);
      for (let h = 4; h < traj.length; h += 5) { ctx.globalAlpha = 0.25; skeleton(traj[h], color(Math.max(k, 0)), 1.5); }
      ctx.globalAlpha = 1; });
    $('frameLabel').textContent = `frame ${T.frame_index[frame]} / ${T.frame_index[nFrames - 1]}`;
  }
}
const slider = $('frame'); slider.max = Math.max(0, nFrames - 1);
slider.addEventListener('input', () => { frame = +slider.value; draw(); });
$('play').addEventListener('click', () => { playing = !playing; $('play').textContent = playing ? 'Pause' : 'Play'; });
let drag = null;
cv.addEventListener('mousedown', e => drag = [e.clientX, e.clientY]);
window.addEventListener('mouseup', () => drag = null);
window.addEventListener('mousemove', e => { if (!drag) return; yaw += (e.clientX - drag[0]) * 0.01;
  pitch = Math.max(-1.4, Math.min(1.4, pitch + (e.clientY - drag[1]) * 0.01)); drag = [e.clientX, e.clientY]; draw(); });
cv.addEventListener('wheel', e => { e.preventDefault(); zoom *= e.deltaY < 0 ? 1.1 : 0.9; draw(); }, {passive: false});
if (T) { const lg = $('legend'); T.track_id.forEach((id, k) => { const s = document.createElement('span');
  s.innerHTML = `<i class="swatch" style="background:${color(k)}"></i>id ${id}`; lg.appendChild(s); }); }
// start on the frame with the most people so a still screenshot shows them
if (T && nFrames) { let best = 0, bestN = -1;
  T.xyz.forEach((fr, t) => { const n = fr.filter(p => p.some(j => j && j[0] !== null)).length; if (n > bestN) { bestN = n; best = t; } });
  frame = best; slider.value = best; }
draw();
document.body.setAttribute('data-rendered', T ? String(nTracks) : '0');
let last = 0;
function tick(ts){ if (playing && T && nFrames > 1 && ts - last > 1000 / Math.min(30, T.fps || 25)) {
  frame = (frame + 1) % nFrames; slider.value = frame; draw(); last = ts; } requestAnimationFrame(tick); }
if (!navigator.webdriver && !/HeadlessChrome/.test(navigator.userAgent)) requestAnimationFrame(tick);
})();
"""
