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
from core.redact import redact

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
        w, h = cam.size_wh
        fx, fy = float(cam.K[0, 0]), float(cam.K[1, 1])
        cams.append(
            {
                "name": cam.name,
                "size_wh": list(cam.size_wh),
                "f_px": _r([fx, fy], 1),
                "c_px": _r([cam.K[0, 2], cam.K[1, 2]], 1),
                "model": cam.model,
                "fov_deg": _r(np.degrees(2 * np.arctan([w / (2 * fx), h / (2 * fy)])), 1),
                "center_m": _r(cam.center),
                "axis": _r(R[2]),
                "right": _r(R[0]),
                "up": _r(-R[1]),
            }
        )
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
        "fps": float(d["fps"]) / step,
        "frame_index": d["frame_index"][sel].tolist(),
        "track_id": d["track_id"].tolist(),
        "joint_names": d["joint_names"].tolist(),
        "parents": d["parents"].tolist(),
        "xyz": _r(xyz[sel]),
        "present": present.astype(int).T.tolist(),
        "mean_std_m": _r(mean_std.T, 4) if std.size else [],
        "source": str(d["source"]),
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
    return {
        "xyz": _r(xyz),
        "track_id": d["track_id"].tolist(),
        "start_index": int(d["start_index"]),
        "model": str(d.get("model", "")),
        "fps": float(d["fps"]) if "fps" in d else None,
    }


def _provenance(lay: SessionLayout) -> list[dict[str, Any]]:
    from pipeline.config import STAGES

    rows = []
    for stage in STAGES:
        p = lay.root / ".roomcap" / "provenance" / f"{stage}.json"
        if not p.exists():
            continue
        try:
            rec = json.loads(p.read_text())
            rows.append(
                {
                    "stage": rec["stage"],
                    "version": rec["version"],
                    "model_sha256": rec.get("model_sha256", "")[:12],
                    "inputs": len(rec["inputs"]),
                }
            )
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
    return {
        "title": title,
        "rig": _rig_data(lay),
        "detections": _detection_rates(lay),
        "tracks": _tracks_data(lay),
        "forecast": _forecast_data(lay),
        "provenance": _provenance(lay),
        # redacted again: a session recorded by an older version may hold a camera URL with its password
        "session": {
            k: redact(v) if isinstance(v, str) else v
            for k, v in meta.items()
            if isinstance(v, (str, int, float))
        },
    }


def render(data: dict[str, Any]) -> str:
    payload = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    return (
        _TEMPLATE.replace("__TITLE__", html.escape(data["title"]))
        .replace("__DATA__", payload)
        .replace("__SCRIPT__", _SCRIPT)
    )


def write_report(lay: SessionLayout, title: str = "") -> Path:
    atomic_write_text(lay.report_html, render(collect(lay, title or lay.root.name)))
    return lay.report_html


_TEMPLATE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__ — roomcap report</title>
<style>
:root{--ink:#1d2330;--muted:#6b7385;--card:#fff;--bg:#eef0f4;--line:#e3e5ea}
*{box-sizing:border-box}
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:0;background:var(--bg);color:var(--ink)}
header{background:linear-gradient(90deg,#161b26,#243049);color:#fff;padding:16px 24px 18px}
header h1{margin:0;font-size:22px;font-weight:600;letter-spacing:.2px}
header .sub{color:#aab3c5;font-size:13px;margin-top:3px}
.cards{display:flex;gap:12px;flex-wrap:wrap;margin-top:14px}
.card{background:#ffffff14;border:1px solid #ffffff22;border-radius:10px;padding:8px 14px;min-width:110px}
.card b{display:block;font-size:22px;font-weight:600}.card span{font-size:11px;color:#aab3c5;text-transform:uppercase;letter-spacing:.6px}
main{display:grid;grid-template-columns:minmax(560px,3fr) minmax(340px,2fr);gap:16px;padding:16px}
section{background:var(--card);border-radius:10px;padding:12px 16px 14px;box-shadow:0 1px 3px #0001,0 4px 14px #0000000a;margin-bottom:16px}
h2{font-size:14px;margin:2px 0 10px;font-weight:600}h2 small{font-weight:400;color:var(--muted);margin-left:6px}
table{border-collapse:collapse;font-size:12px;width:100%}td,th{border-bottom:1px solid var(--line);padding:4px 6px;text-align:left}
th{color:var(--muted);font-weight:500}canvas{display:block;width:100%}
#viewer{background:#10141c;border-radius:8px;cursor:grab}
.controls{display:flex;gap:10px;align-items:center;margin-top:8px}.controls input[type=range]{flex:1;accent-color:#4363d8}
button{border:0;background:#1d2330;color:#fff;border-radius:6px;padding:5px 12px;font-size:12px;cursor:pointer}
.legend{margin-top:6px}.legend span{display:inline-flex;align-items:center;margin-right:12px;font-size:12px}
.swatch{display:inline-block;width:11px;height:11px;border-radius:3px;margin-right:5px}
.muted{color:var(--muted);font-size:12px}details summary{cursor:pointer;font-size:13px;font-weight:600}
#errors{color:#b00;white-space:pre-wrap;font-size:12px}#errsec{display:none}
</style></head><body>
<header><h1>__TITLE__</h1><div class="sub" id="subtitle"></div><div class="cards" id="cards"></div></header>
<main>
<div>
<section><h2>People in 3D<small id="viewerNote"></small></h2><canvas id="viewer" width="1000" height="620"></canvas>
<div class="controls"><button id="play">&#9654; Play</button><input id="frame" type="range" min="0" max="0" value="0">
<span id="frameLabel" class="muted"></span></div><div class="legend" id="legend"></div>
<div class="muted">Drag to orbit, wheel to zoom. Floor lines: where each person walked; dashed: the forecast after the last frame (ghosts). Halo size: positional uncertainty.</div>
</section>
<section><h2>Who was there when<small>one row per track</small></h2><canvas id="timeline" width="1000" height="150"></canvas></section>
<section><h2>Uncertainty<small>mean per-joint standard deviation, mm</small></h2><canvas id="uncertainty" width="1000" height="150"></canvas></section>
</div>
<div>
<section><h2>Room from above<small>cameras, their fields of view and the paths walked</small></h2><canvas id="layout" width="560" height="420"></canvas></section>
<section><h2>Detections per camera<small>people found in each frame</small></h2><canvas id="detections" width="560" height="170"></canvas></section>
<section><h2>Calibration</h2><table id="cams"></table></section>
<section><details><summary>Provenance (what each output was made from)</summary><table id="prov"></table></details></section>
<section id="errsec"><h2>Page errors</h2><div id="errors"></div></section>
</div>
</main>
<script>
window.__errors=[];
function __showErr(){var el=document.getElementById('errors');if(el){el.textContent=window.__errors.join('\\n');document.getElementById('errsec').style.display='block';}}
window.addEventListener('error',function(e){window.__errors.push(String(e.message));__showErr();});
(function(){var ce=console.error;console.error=function(){window.__errors.push(Array.from(arguments).join(' '));__showErr();ce.apply(console,arguments);};})();
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
const fin = p => p && p[0] !== null && p[1] !== null && p[2] !== null;
function row(tbl, cells, head){const tr=document.createElement('tr');for(const c of cells){const td=document.createElement(head?'th':'td');td.textContent=c;tr.appendChild(td);}tbl.appendChild(tr);}
function hidpi(cv){ const r = window.devicePixelRatio || 1; if (r !== 1) { const w = cv.width, h = cv.height; cv.width = w * r; cv.height = h * r; cv.getContext('2d').scale(r, r); cv._w = w; cv._h = h; } else { cv._w = cv.width; cv._h = cv.height; } return cv.getContext('2d'); }

// ---------------------------------------------------------------- data prepared once
const T = D.tracks, F = D.forecast;
const nFrames = T ? T.xyz.length : 0, nTracks = T ? T.track_id.length : 0;
const fps = T ? (T.fps || 25) : 25;
const J = T ? T.joint_names.length : 0;
const jPelvis = T ? T.joint_names.indexOf('pelvis') : -1;
const jHips = T ? [T.joint_names.indexOf('left_hip'), T.joint_names.indexOf('right_hip')] : [-1, -1];
const jHead = T ? Math.max(T.joint_names.indexOf('nose'), T.joint_names.indexOf('neck')) : -1;
function rootOf(pose){ if (!pose) return null;
  if (jPelvis >= 0 && fin(pose[jPelvis])) return pose[jPelvis];
  const h = jHips.filter(j => j >= 0 && fin(pose[j])).map(j => pose[j]);
  if (h.length) return [0,1,2].map(a => h.reduce((s, p) => s + p[a], 0) / h.length);
  const any = pose.filter(fin); if (!any.length) return null;
  return [0,1,2].map(a => any.reduce((s, p) => s + p[a], 0) / any.length); }
const roots = T ? T.xyz.map(fr => fr.map(rootOf)) : [];              // [t][k] -> xyz | null
const peopleAt = roots.map(fr => fr.filter(r => r).length);
const maxPeople = peopleAt.length ? Math.max(...peopleAt) : 0;
const fcRoots = F ? F.xyz.map(traj => traj.map(rootOf)) : [];
const fcFps = F ? (F.fps || fps) : fps;
const fcTrack = F ? F.track_id.map(id => T ? T.track_id.indexOf(id) : -1) : [];

// ---------------------------------------------------------------- header: cards, tables
const dur = T && nFrames ? (T.frame_index[nFrames - 1] - T.frame_index[0] + 1) / (fps * T.step) : 0;
$('subtitle').textContent = `roomcap session report · ${D.rig ? D.rig.cameras.length : 0} cameras · ` +
  (T ? `tracked by ${T.source}` : 'no tracks yet');
const cards = [[D.rig ? D.rig.cameras.length : '–', 'cameras'], [T ? dur.toFixed(1) + ' s' : '–', 'recording'],
  [T ? nFrames * T.step : '–', 'frames'], [T ? maxPeople : '–', 'people at once'], [T ? nTracks : '–', 'tracks'],
  [F ? (F.model || 'yes') : 'none', 'forecast' + (F && F.xyz[0] ? ` +${(F.xyz[0].length / fcFps).toFixed(1)} s` : '')]];
for (const [v, k] of cards) { const d = document.createElement('div'); d.className = 'card';
  d.innerHTML = '<b></b><span></span>'; d.firstChild.textContent = v; d.lastChild.textContent = k; $('cards').appendChild(d); }
const ct = $('cams');
if (D.rig && D.rig.cameras.length) { row(ct, ['camera','image','focal (px)','field of view','position (m)'], true);
  for (const c of D.rig.cameras) row(ct, [c.name, c.size_wh.join('×'), c.f_px[0].toFixed(0), c.fov_deg ? c.fov_deg.map(v => v.toFixed(0) + '°').join(' × ') : '-',
    c.center_m.map(v => v.toFixed(2)).join(', ')]); }
else row(ct, [D.rig && D.rig.error ? 'calibration unreadable: ' + D.rig.error : 'no calibration']);
const pt = $('prov'); row(pt, ['stage','version','model sha256','inputs'], true);
for (const p of D.provenance) row(pt, [p.stage, p.version, p.model_sha256 || '-', p.inputs]);

// ---------------------------------------------------------------- timeline, uncertainty, detections
let frame = 0;
const charts = [];
function timeline(){ const cv = $('timeline'), c = cv.getContext('2d'), W = cv.width, H = cv.height, L = 56, R = 10;
  c.clearRect(0, 0, W, H); c.font = '11px system-ui,sans-serif';
  if (!T || !nFrames) { c.fillStyle = '#999'; c.fillText('no tracks', 10, 20); return; }
  const n = T.present[0] ? T.present[0].length : nFrames, rowH = Math.max(5, Math.min(20, (H - 26) / Math.max(1, nTracks)));
  const x = t => L + (W - L - R) * t / Math.max(1, n);
  T.present.forEach((pres, k) => { const y = 4 + k * rowH;
    c.fillStyle = '#f3f4f7'; c.fillRect(L, y, W - L - R, rowH - 3);
    c.fillStyle = color(k); let s = -1;
    for (let t = 0; t <= n; t++) { const on = t < n && pres[t];
      if (on && s < 0) s = t; if (!on && s >= 0) { c.beginPath(); c.roundRect ? c.roundRect(x(s), y, x(t) - x(s), rowH - 3, 3) : c.rect(x(s), y, x(t) - x(s), rowH - 3); c.fill(); s = -1; } }
    c.fillStyle = '#333'; c.fillText('id ' + T.track_id[k], 6, y + rowH - 6); });
  axisSeconds(c, L, R, W, H, n);
  c.strokeStyle = '#1d2330'; c.lineWidth = 2; const px = x(frame * T.step + 0.5); c.beginPath(); c.moveTo(px, 0); c.lineTo(px, H - 16); c.stroke(); }
function axisSeconds(c, L, R, W, H, n){ c.fillStyle = '#777'; c.font = '10px system-ui,sans-serif';
  const secs = n / (fps * (T ? T.step : 1)), step = secs > 60 ? 10 : secs > 20 ? 5 : secs > 5 ? 1 : 0.5;
  for (let s = 0; s <= secs + 1e-9; s += step) { const px = L + (W - L - R) * s / Math.max(1e-9, secs); c.fillText(s.toFixed(step < 1 ? 1 : 0) + ' s', px - 8, H - 3); } }
function uncertainty(){ const cv = $('uncertainty'), c = cv.getContext('2d'), W = cv.width, H = cv.height, L = 56, R = 10, B = 18;
  c.clearRect(0, 0, W, H); c.font = '11px system-ui,sans-serif';
  if (!T || !T.mean_std_m.length) { c.fillStyle = '#999'; c.fillText('no uncertainty in the track file', 10, 20); return; }
  const n = T.mean_std_m[0].length; let maxY = 1;
  for (const s of T.mean_std_m) for (const v of s) if (v !== null && 1000 * v > maxY) maxY = 1000 * v;
  maxY = Math.ceil(maxY / 10) * 10;
  const x = t => L + (W - L - R) * t / Math.max(1, n - 1), y = v => H - B - (H - B - 6) * v / maxY;
  c.strokeStyle = '#eceef2'; c.fillStyle = '#777';
  for (let g = 0; g <= maxY; g += maxY / 4) { c.beginPath(); c.moveTo(L, y(g)); c.lineTo(W - R, y(g)); c.stroke(); c.fillText(g.toFixed(0) + ' mm', 4, y(g) + 4); }
  T.mean_std_m.forEach((s, k) => { c.strokeStyle = color(k); c.lineWidth = 1.6; c.beginPath(); let pen = false;
    s.forEach((v, t) => { if (v === null) { pen = false; return; } const px = x(t), py = y(1000 * v); if (pen) c.lineTo(px, py); else c.moveTo(px, py); pen = true; }); c.stroke(); });
  axisSeconds(c, L, R, W, H, n);
  c.strokeStyle = '#1d2330'; c.lineWidth = 2; const px = x(frame * T.step); c.beginPath(); c.moveTo(px, 0); c.lineTo(px, H - B); c.stroke(); }
(function detections(){ const cv = $('detections'), c = cv.getContext('2d'), W = cv.width, L = 64, R = 8;
  const cams = Object.keys(D.detections); c.font = '11px system-ui,sans-serif';
  if (!cams.length) { c.fillStyle = '#999'; c.fillText('no detections', 10, 20); return; }
  const rowH = Math.min(30, (cv.height - 24) / cams.length); let maxP = 1;
  for (const k of cams) for (const v of D.detections[k].people) if (v > maxP) maxP = v;
  cams.forEach((cam, i) => { const p = D.detections[cam].people, n = p.length, y = 4 + i * rowH;
    const bins = Math.min(n, W - L - R), bw = (W - L - R) / Math.max(1, bins);
    for (let b = 0; b < bins; b++) { const a = Math.floor(b * n / bins), e = Math.max(a + 1, Math.floor((b + 1) * n / bins));
      let s = 0; for (let t = a; t < e; t++) s += p[t]; const v = s / (e - a) / maxP;
      c.fillStyle = v <= 0 ? '#f1f2f5' : `hsl(${220 - 190 * v}, 70%, ${88 - 45 * v}%)`; c.fillRect(L + b * bw, y, Math.ceil(bw), rowH - 4); }
    const mean = p.reduce((s, v) => s + v, 0) / Math.max(1, n);
    c.fillStyle = '#333'; c.fillText(cam, 4, y + rowH / 2 + 2); c.fillStyle = '#777'; c.fillText(mean.toFixed(1) + '/frame', 4, y + rowH / 2 + 13 > y + rowH ? y + rowH : y + rowH / 2 + 13); });
  const y0 = 4 + cams.length * rowH + 4; c.fillStyle = '#777'; c.fillText('0', L, y0 + 10);
  for (let i = 0; i <= 20; i++) { const v = i / 20; c.fillStyle = `hsl(${220 - 190 * v}, 70%, ${88 - 45 * v}%)`; c.fillRect(L + 12 + i * 6, y0 + 2, 6, 10); }
  c.fillStyle = '#777'; c.fillText(maxP + ' people', L + 12 + 21 * 6 + 4, y0 + 10);
})();

// ---------------------------------------------------------------- room from above
(function layout(){ const cv = $('layout'), c = cv.getContext('2d'), W = cv.width, H = cv.height;
  c.fillStyle = '#fbfbfd'; c.fillRect(0, 0, W, H);
  const pts = [];
  if (D.rig) for (const k of D.rig.cameras) pts.push(k.center_m);
  for (const fr of roots) for (const r of fr) if (r) pts.push(r);
  if (!pts.length) { c.fillStyle = '#999'; c.fillText('nothing to draw', 10, 20); return; }
  let minX = Math.min(...pts.map(p => p[0])) - 0.6, maxX = Math.max(...pts.map(p => p[0])) + 0.6;
  let minY = Math.min(...pts.map(p => p[1])) - 0.6, maxY = Math.max(...pts.map(p => p[1])) + 0.6;
  const s = Math.min((W - 30) / (maxX - minX), (H - 30) / (maxY - minY));
  const ox = (W - s * (maxX - minX)) / 2, oy = (H - s * (maxY - minY)) / 2;
  const P = p => [ox + (p[0] - minX) * s, H - oy - (p[1] - minY) * s];
  c.strokeStyle = '#e6e8ee'; c.lineWidth = 1;
  for (let g = Math.ceil(minX); g <= maxX; g++) { const a = P([g, minY]), b = P([g, maxY]); c.beginPath(); c.moveTo(a[0], a[1]); c.lineTo(b[0], b[1]); c.stroke(); }
  for (let g = Math.ceil(minY); g <= maxY; g++) { const a = P([minX, g]), b = P([maxX, g]); c.beginPath(); c.moveTo(a[0], a[1]); c.lineTo(b[0], b[1]); c.stroke(); }
  c.fillStyle = '#999'; c.font = '10px system-ui,sans-serif'; c.fillText('grid: 1 m', 8, H - 8);
  if (D.rig) D.rig.cameras.forEach(k => { const [x, y] = P(k.center_m), a = k.axis, h = Math.atan2(a[1], a[0]);
    const half = (k.fov_deg ? k.fov_deg[0] : 60) * Math.PI / 360, r = 2.5 * s;
    c.fillStyle = '#4363d814'; c.beginPath(); c.moveTo(x, y); c.arc(x, y, r, -(h + half), -(h - half)); c.closePath(); c.fill();
    c.fillStyle = '#1d2330'; c.beginPath(); c.arc(x, y, 5, 0, 7); c.fill();
    c.font = '11px system-ui,sans-serif'; c.fillText(k.name, x + 8, y - 6); });
  for (let k = 0; k < nTracks; k++) { c.strokeStyle = color(k); c.lineWidth = 2.2; c.beginPath(); let pen = false, last = null, first = null;
    for (let t = 0; t < nFrames; t++) { const r = roots[t][k]; if (!r) { pen = false; continue; } const q = P(r);
      if (pen) c.lineTo(q[0], q[1]); else c.moveTo(q[0], q[1]); pen = true; last = q; first = first || q; }
    c.stroke(); if (first) { c.fillStyle = color(k); c.beginPath(); c.arc(first[0], first[1], 3, 0, 7); c.fill(); }
    if (last) { c.beginPath(); c.arc(last[0], last[1], 5, 0, 7); c.fill(); } }
  fcRoots.forEach((traj, i) => { const k = fcTrack[i]; const r0 = traj.find(r => r); if (!r0 || k < 0) return;
    c.strokeStyle = color(k); c.lineWidth = 2; c.setLineDash([5, 4]); c.beginPath(); let pen = false;
    const lastObs = roots.length ? roots[nFrames - 1][k] : null; if (lastObs) { const q = P(lastObs); c.moveTo(q[0], q[1]); pen = true; }
    for (const r of traj) { if (!r) continue; const q = P(r); if (pen) c.lineTo(q[0], q[1]); else c.moveTo(q[0], q[1]); pen = true; }
    c.stroke(); c.setLineDash([]); });
})();

// ---------------------------------------------------------------- 3D viewer
const cv = $('viewer'), ctx = cv.getContext('2d');
let yaw = -0.9, pitch = 0.42, zoom = 1.0, playing = false;
let center = [0, 0, 0.9], radius = 3;
(function fit(){ const pts = []; for (const fr of roots) for (const r of fr) if (r) pts.push(r);
  for (const traj of fcRoots) for (const r of traj) if (r) pts.push(r);
  if (!pts.length && D.rig) for (const k of D.rig.cameras) pts.push(k.center_m);
  if (!pts.length) return;
  const lo = [0, 1].map(a => Math.min(...pts.map(p => p[a]))), hi = [0, 1].map(a => Math.max(...pts.map(p => p[a])));
  center = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.9];
  radius = Math.max(1.3, 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1]) + 0.7);
})();
function project(p){ // orbit camera looking at `center`, z up
  const x = p[0] - center[0], y = p[1] - center[1], z = p[2] - center[2];
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const xr = cy * x - sy * y, yr = sy * x + cy * y;
  const depth = cp * yr + sp * z, up = -sp * yr + cp * z;
  const dist = radius * 2.1 / zoom, f = cv.height * 0.95;
  const d = dist + depth; if (d < 0.05) return null;
  return [cv.width / 2 + f * xr / d, cv.height * 0.56 - f * up / d, d, f / d];
}
function line(a, b, col, w, dash){ const p = project(a), q = project(b); if (!p || !q) return;
  ctx.strokeStyle = col; ctx.lineWidth = w; if (dash) ctx.setLineDash(dash); ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]); ctx.stroke(); if (dash) ctx.setLineDash([]); }
function floorOf(p){ return [p[0], p[1], 0]; }
function skeleton(pose, col, w, std_m, alpha){
  if (!pose) return; ctx.globalAlpha = alpha === undefined ? 1 : alpha; ctx.lineCap = 'round';
  // shadow on the floor first
  ctx.globalAlpha *= 0.35;
  T.parents.forEach((p, j) => { if (p < 0 || !fin(pose[j]) || !fin(pose[p])) return; line(floorOf(pose[j]), floorOf(pose[p]), '#000', w + 2); });
  ctx.globalAlpha = alpha === undefined ? 1 : alpha;
  T.parents.forEach((p, j) => { if (p < 0 || !fin(pose[j]) || !fin(pose[p])) return; line(pose[j], pose[p], col, w); });
  pose.forEach(j => { if (!fin(j)) return; const q = project(j); if (!q) return;
    if (std_m) { const r = Math.min(40, std_m * q[3]); ctx.fillStyle = col; ctx.globalAlpha *= 0.18; ctx.beginPath(); ctx.arc(q[0], q[1], Math.max(2, r), 0, 7); ctx.fill(); ctx.globalAlpha = alpha === undefined ? 1 : alpha; }
    ctx.fillStyle = col; ctx.beginPath(); ctx.arc(q[0], q[1], Math.max(1.5, w * 0.8), 0, 7); ctx.fill(); });
  ctx.globalAlpha = 1;
}
function drawCamera(k){ const c0 = k.center_m, a = k.axis, r = k.right || [0, 0, 0], u = k.up || [0, 0, 1];
  const tw = Math.tan((k.fov_deg ? k.fov_deg[0] : 60) * Math.PI / 360) * 0.35, th = Math.tan((k.fov_deg ? k.fov_deg[1] : 40) * Math.PI / 360) * 0.35;
  const corner = (sx, sy) => [0, 1, 2].map(i => c0[i] + 0.35 * a[i] + sx * tw * r[i] + sy * th * u[i]);
  const cs = [corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, 1)];
  for (let i = 0; i < 4; i++) { line(c0, cs[i], '#8f9bb3', 1.2); line(cs[i], cs[(i + 1) % 4], '#8f9bb3', 1.2); }
  line(cs[2], cs[3], '#c9d2e6', 2.4); // top edge: which way is up
  const q = project(c0); if (q) { ctx.fillStyle = '#aab3c5'; ctx.font = '12px system-ui,sans-serif'; ctx.fillText(k.name, q[0] + 6, q[1] - 6); } }
function draw(){
  ctx.fillStyle = '#10141c'; ctx.fillRect(0, 0, cv.width, cv.height);
  const g = Math.ceil(radius * 1.6);
  for (let i = -g; i <= g; i++) { const cx = Math.round(center[0]) + i, cy = Math.round(center[1]) + i;
    line([cx, Math.round(center[1]) - g, 0], [cx, Math.round(center[1]) + g, 0], '#222a38', 1);
    line([Math.round(center[0]) - g, cy, 0], [Math.round(center[0]) + g, cy, 0], '#222a38', 1); }
  if (D.rig) for (const k of D.rig.cameras) drawCamera(k);
  if (!T || !nFrames) { ctx.fillStyle = '#aab3c5'; ctx.font = '16px system-ui,sans-serif'; ctx.fillText('No tracks in this session yet.', 30, 40); return; }
  // floor paths: the whole track faintly, the last second brightly
  const trail = Math.round(fps * 1.0);
  for (let k = 0; k < nTracks; k++) { let prev = null;
    for (let t = 0; t <= frame; t++) { const r = roots[t][k]; if (!r) { prev = null; continue; }
      if (prev) { ctx.globalAlpha = t > frame - trail ? 0.9 : 0.22; line(floorOf(prev), floorOf(r), color(k), t > frame - trail ? 2.5 : 1.5); } prev = r; }
    ctx.globalAlpha = 1; }
  // forecast: dashed future paths from the last frame; ghosts near the end of playback
  const nearEnd = frame >= nFrames - 1 - Math.round(fps * 0.5);
  fcRoots.forEach((traj, i) => { const k = fcTrack[i]; if (k < 0) return; let prev = roots[nFrames - 1][k];
    ctx.globalAlpha = nearEnd ? 0.95 : 0.45;
    for (const r of traj) { if (!r) continue; if (prev) line(floorOf(prev), floorOf(r), color(k), 2, [6, 5]); prev = r; }
    ctx.globalAlpha = 1;
    if (nearEnd) { const H = traj.length, step = Math.max(1, Math.round(fcFps * 0.5));
      for (let h = step - 1; h < H; h += step) skeleton(F.xyz[i][h], color(k), 1.6, 0, 0.16 + 0.3 * (1 - h / H)); } });
  const fr = T.xyz[frame];
  fr.forEach((pose, k) => { skeleton(pose, color(k), 3.2, T.mean_std_m.length ? T.mean_std_m[k][frame] : 0);
    const top = pose ? (fin(pose[jHead]) ? pose[jHead] : rootOf(pose)) : null;
    if (top) { const q = project([top[0], top[1], top[2] + 0.25]); if (q) { ctx.font = 'bold 12px system-ui,sans-serif';
      const label = 'id ' + T.track_id[k], w = ctx.measureText(label).width + 10; ctx.fillStyle = color(k); ctx.globalAlpha = 0.9;
      ctx.beginPath(); ctx.roundRect ? ctx.roundRect(q[0] - w / 2, q[1] - 16, w, 18, 9) : ctx.rect(q[0] - w / 2, q[1] - 16, w, 18); ctx.fill();
      ctx.globalAlpha = 1; ctx.fillStyle = '#fff'; ctx.fillText(label, q[0] - w / 2 + 5, q[1] - 3); } } });
  ctx.fillStyle = '#aab3c5'; ctx.font = '13px system-ui,sans-serif';
  const tSec = (T.frame_index[frame] - T.frame_index[0]) / (fps * T.step);
  ctx.fillText(`${tSec.toFixed(2)} s · frame ${T.frame_index[frame]} · ${peopleAt[frame]} people`, 16, 26);
  if (F && nearEnd) ctx.fillText(`forecast: ${F.model}, ghosts every 0.5 s`, 16, 46);
  $('frameLabel').textContent = `frame ${T.frame_index[frame]} / ${T.frame_index[nFrames - 1]}`;
  timeline(); uncertainty();
}
const slider = $('frame'); slider.max = Math.max(0, nFrames - 1);
slider.addEventListener('input', () => { frame = +slider.value; draw(); });
$('play').addEventListener('click', () => { playing = !playing; $('play').innerHTML = playing ? '&#10074;&#10074; Pause' : '&#9654; Play'; });
let drag = null;
cv.addEventListener('mousedown', e => drag = [e.clientX, e.clientY]);
window.addEventListener('mouseup', () => drag = null);
window.addEventListener('mousemove', e => { if (!drag) return; yaw += (e.clientX - drag[0]) * 0.01;
  pitch = Math.max(-0.1, Math.min(1.5, pitch + (e.clientY - drag[1]) * 0.01)); drag = [e.clientX, e.clientY]; draw(); });
cv.addEventListener('wheel', e => { e.preventDefault(); zoom *= e.deltaY < 0 ? 1.1 : 0.9; draw(); }, {passive: false});
if (T) { const lg = $('legend'); T.track_id.forEach((id, k) => { const s = document.createElement('span');
  const first = T.present[k].indexOf(1), last = T.present[k].lastIndexOf(1);
  s.innerHTML = `<i class="swatch" style="background:${color(k)}"></i>`; s.appendChild(document.createTextNode(
    `id ${id} (${first < 0 ? 0 : ((last - first + 1) / (fps * T.step)).toFixed(1)} s)`)); lg.appendChild(s); }); }
$('viewerNote').textContent = T ? `${nTracks} tracks, ${maxPeople} people at most at once` : '';
// start where a still picture says most: the last frame with its forecast, else the frame with the most people
if (T && nFrames) { let best = 0; peopleAt.forEach((n, t) => { if (n >= peopleAt[best]) best = t; });
  if (F && peopleAt[nFrames - 1] > 0) best = nFrames - 1; frame = best; slider.value = best; }
draw();
document.body.setAttribute('data-rendered', T ? String(nTracks) : '0');
let last = 0;
function tick(ts){ if (playing && T && nFrames > 1 && ts - last > 1000 / Math.min(30, fps)) {
  frame = (frame + 1) % nFrames; slider.value = frame; draw(); last = ts; } requestAnimationFrame(tick); }
requestAnimationFrame(tick);
if (!navigator.webdriver && !/HeadlessChrome/.test(navigator.userAgent)) { playing = true; $('play').innerHTML = '&#10074;&#10074; Pause'; }
})();
"""
