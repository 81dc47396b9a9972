(function(){
'use strict';
const D = JSON.parse(document.getElementById('data').textContent);
const COLORS = ['#e6194b','#3cb44b','#4363d8','#f58231','#911eb4','#42d4f4','#f032e6','#bfef45','#fabed4',
                '#469990','#dcbeff','#9a6324','#fffac8','#800000','#aaffc3','#808000'];
const CAMCOL = ['#1f77b4','#ff7f0e','#2ca02c','#d62728','#9467bd','#8c564b','#e377c2','#7f7f7f','#bcbd22','#17becf'];
const color = k => COLORS[k % COLORS.length];
const camColor = i => CAMCOL[i % CAMCOL.length];
const $ = id => document.getElementById(id);
const fin = p => p && p[0] !== null && p[1] !== null && p[2] !== null;
const fmt = (v, d) => v === null || v === undefined ? '–' : Number(v).toFixed(d === undefined ? 2 : d);
function row(tbl, cells, head){ const tr = document.createElement('tr');
  for (const c of cells) { const td = document.createElement(head ? 'th' : 'td');
    if (c && typeof c === 'object' && 'v' in c) { td.textContent = c.t; td.className = 'num'; if (c.v !== null) td.dataset.v = c.v; if (c.bg) td.style.background = c.bg; }
    else td.textContent = c; tr.appendChild(td); }
  tbl.appendChild(tr); return tr; }
const num = (v, d) => ({v: v === null || v === undefined ? null : v, t: fmt(v, d)});

// ---------------------------------------------------------------- data prepared once
const BH = D.behaviour && D.behaviour.track_id.length ? D.behaviour : null; let behavStep = 0;
const T = D.tracks, F = D.forecast, Q = D.quality && !D.quality.error ? D.quality : null, V = D.views;
const nFrames = T ? T.xyz.length : 0, nTracks = T ? T.track_id.length : 0;
const fps = T ? (T.fps || 25) : 25;
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
const fxy = p => p && p[0] !== null && p[1] !== null;
// floor paths of the forecast: the file's own (under each track's root), else from the ghosts' roots
const fcPaths = F ? (F.path || fcRoots.map(traj => traj.map(r => r ? [r[0], r[1]] : null))) : [];
const fcTrack = F ? F.track_id.map(id => T ? T.track_id.indexOf(id) : -1) : [];
const rowOfFrame = new Map(); if (T) T.frame_index.forEach((f, t) => rowOfFrame.set(f, t));
function viewerRowOf(fi){ if (!T || !nFrames) return 0; if (rowOfFrame.has(fi)) return rowOfFrame.get(fi);
  let lo = 0, hi = nFrames - 1; while (lo < hi) { const m = (lo + hi + 1) >> 1; if (T.frame_index[m] <= fi) lo = m; else hi = m - 1; } return lo; }

// ---------------------------------------------------------------- header: cards
const dur = T && nFrames ? (T.frame_index[nFrames - 1] - T.frame_index[0] + 1) / (fps * T.step) : 0;
$('subtitle').textContent = `roomcap session report · ${D.rig ? D.rig.cameras.length : 0} cameras · ` +
  (T ? `tracked by ${T.source}` : 'no tracks yet');
const nProblems = (D.problems || []).filter(p => p.level !== 'info').length;
const cards = [[D.rig ? D.rig.cameras.length : '–', 'cameras'], [T ? dur.toFixed(1) + ' s' : '–', 'recording'],
  [T ? nFrames * T.step : '–', 'frames'], [T ? maxPeople : '–', 'people at once'], [T ? nTracks : '–', 'tracks'],
  [Q && Q.mean_px !== null ? Q.mean_px.toFixed(1) + ' px' : '–', 'reprojection error'],
  [nProblems, nProblems === 1 ? 'problem' : 'problems'],
  [F ? (F.model || 'yes') : 'none', 'forecast' + (F && F.xyz[0] ? ` +${(F.xyz[0].length / fcFps).toFixed(1)} s` : '')]];
for (const [v, k] of cards) { const d = document.createElement('div'); d.className = 'card';
  d.innerHTML = '<b></b><span></span>'; d.firstChild.textContent = v; d.lastChild.textContent = k; $('cards').appendChild(d); }

// ---------------------------------------------------------------- problems, warnings, tables
(function problems(){ const el = $('problems'), P = D.problems || [];
  if (!P.length) { el.innerHTML = '<div class="ok">No problems found: the 3D agrees with every camera, tracks are continuous and nothing was logged.</div>'; return; }
  $('problemsNote').textContent = `${P.length} item${P.length > 1 ? 's' : ''}, most serious first`;
  const order = {error: 0, warning: 1, info: 2};
  for (const p of P.slice().sort((a, b) => order[a.level] - order[b.level])) {
    const d = document.createElement('div'); d.className = 'problem ' + p.level;
    const b = document.createElement('b'); b.textContent = p.title; d.appendChild(b);
    const t = document.createElement('div'); t.textContent = p.detail; d.appendChild(t);
    const a = document.createElement('div'); a.className = 'do'; a.textContent = p.action; d.appendChild(a);
    el.appendChild(d); } })();
(function warnings(){ const el = $('warnings'), W = D.warnings || [];
  if (!W.length) { el.innerHTML = '<div class="muted">none</div>'; return; }
  for (const w of W) { const d = document.createElement('div'); d.className = 'warn';
    const i = document.createElement('i'); i.textContent = w.stage || 'run'; d.appendChild(i); d.appendChild(document.createTextNode(w.message)); el.appendChild(d); } })();
(function calibration(){ const ct = $('cams'), figs = D.rig && D.rig.figures;
  if (D.rig && D.rig.cameras.length) {
    const fc = figs && figs.cameras ? figs.cameras : {};
    const extra = figs && figs.unit === 'px' ? ['int. RMS (px)', 'ext. RMS (px)'] : figs && figs.cameras ? ['residual'] : [];
    row(ct, ['camera','image','focal (px)','field of view','position (m)', ...extra], true);
    for (const c of D.rig.cameras) { const f = fc[c.name] || {};
      const ex = figs && figs.unit === 'px' ? [num(f.intrinsic_rms_px, 3), num(f.extrinsic_rms_px, 3)] : figs && figs.cameras ? [num(f.avg_residual, 3)] : [];
      row(ct, [c.name, c.size_wh.join('×'), c.f_px[0].toFixed(0), c.fov_deg ? c.fov_deg.map(v => v.toFixed(0) + '°').join(' × ') : '-',
        c.center_m.map(v => v.toFixed(2)).join(', '), ...ex]); }
    if (figs) { let s = `Calibration figures from ${figs.source}` + (figs.unit ? ` (${figs.unit})` : '') + '.';
      const ba = figs.bundle_adjustment; if (ba && ba.final_rms_px !== undefined) s += ` Bundle adjustment: ${fmt(ba.initial_rms_px, 3)} → ${fmt(ba.final_rms_px, 3)} px.`;
      if (figs.error) s += ' Unreadable: ' + figs.error; $('calibNote').textContent = s; }
    else $('calibNote').textContent = 'The calibration carries no figures of its own (no calib/report/report.toml).'; }
  else row(ct, [D.rig && D.rig.error ? 'calibration unreadable: ' + D.rig.error : 'no calibration']); })();
(function provenance(){ const pt = $('prov'); row(pt, ['stage','version','model sha256','inputs'], true);
  for (const p of D.provenance) row(pt, [p.stage, p.version, p.model_sha256 || '-', p.inputs]); })();
(function reprojTables(){
  const ct = $('reprojCams');
  if (D.quality && D.quality.error) { row(ct, ['poses3d.npz unreadable: ' + D.quality.error]); return; }
  if (!Q) { row(ct, ['no triangulation output (triangulate/poses3d.npz)']); return; }
  const heat = (v, lo, hi) => v === null ? '' : `hsl(${Math.max(0, 120 - 120 * (v - lo) / Math.max(1e-9, hi - lo))}, 70%, 88%)`;
  if (Q.cameras.length) {
    row(ct, ['camera', {v: null, t: 'mean px'}, {v: null, t: 'median'}, {v: null, t: '90%'}, {v: null, t: 'joints'}, {v: null, t: 'share'}], true);
    const vals = Q.cameras.map(c => c.mean_px).filter(v => v !== null), lo = Math.min(...vals, 0), hi = Math.max(...vals, 1);
    Q.cameras.forEach((c, i) => { const tr = row(ct, [c.name, Object.assign(num(c.mean_px), {bg: heat(c.mean_px, lo, hi * 1.2)}), num(c.median_px), num(c.p90_px),
      {v: c.n, t: String(c.n)}, {v: c.share, t: c.share === null ? '–' : (100 * c.share).toFixed(0) + '%'}]);
      tr.dataset.camera = c.name; tr.firstChild.style.borderLeft = '4px solid ' + camColor(i); }); }
  row(ct, ['all (mean over views)', num(Q.mean_px), num(Q.median_px), {v: null, t: ''}, {v: Q.n_joints_3d, t: String(Q.n_joints_3d)}, {v: null, t: ''}]).dataset.camera = '*';
  $('reprojNote').textContent = Q.per_camera_note || 'Per camera: the views that camera contributed to a 3D joint; share: of all triangulated joints.';
  const jt = $('reprojJoints'); row(jt, ['joint', {v: null, t: 'mean px'}, {v: null, t: 'views'}], true);
  const jv = Q.per_joint_mean_px.filter(v => v !== null), jlo = Math.min(...jv, 0), jhi = Math.max(...jv, 1);
  Q.joint_names.forEach((n, j) => { const tr = row(jt, [n, Object.assign(num(Q.per_joint_mean_px[j]), {bg: heat(Q.per_joint_mean_px[j], jlo, jhi)}), num(Q.per_joint_views[j])]); tr.dataset.joint = n; });
  if (Q.cameras.length) { const mt = $('reprojMatrix');
    row(mt, ['', ...Q.cameras.map(c => c.name)], true);
    const all = [].concat(...Q.cameras.map(c => c.per_joint_mean_px)).filter(v => v !== null), mlo = Math.min(...all, 0), mhi = Math.max(...all, 1);
    Q.joint_names.forEach((n, j) => row(mt, [n, ...Q.cameras.map(c => Object.assign(num(c.per_joint_mean_px[j], 1), {bg: heat(c.per_joint_mean_px[j], mlo, mhi)}))])); }
})();
(function viewsHist(){ const cv = $('viewsHist'), c = cv.getContext('2d'), W = cv.width, H = cv.height;
  c.font = '11px system-ui,sans-serif';
  if (!Q || !Q.views_hist.length) { c.fillStyle = '#999'; c.fillText('no triangulated joints', 10, 20); return; }
  const h = Q.views_hist, tot = h.reduce((s, v) => s + v, 0) || 1, n = h.length, v0 = Math.max(1, h.findIndex(v => v > 0));
  const bw = (W - 60) / Math.max(1, n - v0);
  let x = 40; for (let v = v0; v < n; v++) { const f = h[v] / tot, bh = (H - 30) * f;
    c.fillStyle = '#4363d8'; c.fillRect(x, H - 18 - bh, bw - 8, bh); c.fillStyle = '#333';
    c.fillText(`${v} views`, x, H - 4); c.fillText((100 * f).toFixed(0) + '%', x, H - 22 - bh); x += bw; } })();
(function trackTable(){ const tt = $('trackTable');
  if (!T) { row(tt, ['no tracks']); return; }
  const ev = T.events, full = fps * T.step;
  row(tt, ['track', {v: null, t: 'seen (s)'}, {v: null, t: 'not observed (s)'}, {v: null, t: 'interpolated'}, {v: null, t: 'predicted'}, {v: null, t: 'jumps'}], true);
  T.track_id.forEach((id, k) => { const tr = row(tt, ['id ' + id, num(ev.present_frames[k] / full, 1), num(ev.unobserved_frames[k] / full, 1),
    {v: ev.interpolated_frames[k], t: String(ev.interpolated_frames[k])}, {v: ev.predicted_frames[k], t: String(ev.predicted_frames[k])},
    {v: null, t: String(ev.jumps.filter(j => j.track === k).length)}]); tr.firstChild.style.borderLeft = '4px solid ' + color(k); });
  if (ev.jumps.length) { const d = document.createElement('div'); d.className = 'muted'; d.style.marginTop = '6px';
    d.textContent = 'Jumps: ' + ev.jumps.slice(0, 20).map(j => `id ${j.id} @ frame ${j.frame} (${j.dist_m.toFixed(2)} m${j.swap_with !== null ? ', swap with id ' + j.swap_with + '?' : ''})`).join('; ') + (ev.jumps.length > 20 ? ' …' : '');
    tt.parentNode.appendChild(d); } })();

// ---------------------------------------------------------------- time charts
let frame = 0;
function axisSeconds(c, L, R, W, H, n, perSec){ c.fillStyle = '#777'; c.font = '10px system-ui,sans-serif';
  const secs = n / perSec, step = secs > 300 ? 60 : secs > 60 ? 10 : secs > 20 ? 5 : secs > 5 ? 1 : 0.5;
  for (let s = 0; s <= secs + 1e-9; s += step) { const px = L + (W - L - R) * s / Math.max(1e-9, secs); c.fillText(s.toFixed(step < 1 ? 1 : 0) + ' s', px - 8, H - 3); } }
let hatch = null;
function hatchPattern(c){ if (hatch) return hatch; const p = document.createElement('canvas'); p.width = p.height = 8; const g = p.getContext('2d');
  g.strokeStyle = 'rgba(255,255,255,0.85)'; g.lineWidth = 2; g.beginPath(); g.moveTo(0, 8); g.lineTo(8, 0); g.stroke(); hatch = c.createPattern(p, 'repeat'); return hatch; }
function timeline(){ const cv = $('timeline'), c = cv.getContext('2d'), W = cv.width, H = cv.height, L = 56, R = 10;
  c.clearRect(0, 0, W, H); c.font = '11px system-ui,sans-serif';
  if (!T || !nFrames) { c.fillStyle = '#999'; c.fillText('no tracks', 10, 20); return; }
  const n = T.present[0] ? T.present[0].length : nFrames, rowH = Math.max(5, Math.min(20, (H - 26) / Math.max(1, nTracks)));
  const x = t => L + (W - L - R) * t / Math.max(1, n);
  T.present.forEach((pres, k) => { const y = 4 + k * rowH;
    c.fillStyle = '#f3f4f7'; c.fillRect(L, y, W - L - R, rowH - 3);
    c.fillStyle = color(k); let s = -1;
    for (let t = 0; t <= n; t++) { const on = t < n && pres[t];
      if (on && s < 0) s = t; if (!on && s >= 0) { c.fillRect(x(s), y, Math.max(1, x(t) - x(s)), rowH - 3); s = -1; } }
    c.fillStyle = hatchPattern(c);
    for (const [a, b] of T.events.unobserved[k]) c.fillRect(x(a), y, Math.max(1, x(b + 1) - x(a)), rowH - 3);
    c.fillStyle = '#333'; c.fillText('id ' + T.track_id[k], 6, y + rowH - 6); });
  c.fillStyle = '#d62728';
  for (const j of T.events.jumps) { const px = x(j.t), y = 4 + j.track * rowH; c.beginPath(); c.moveTo(px - 4, y - 1); c.lineTo(px + 4, y - 1); c.lineTo(px, y + 6); c.closePath(); c.fill(); c.fillRect(px - 0.75, y, 1.5, rowH - 3); }
  axisSeconds(c, L, R, W, H, n, fps * T.step);
  c.strokeStyle = '#1d2330'; c.lineWidth = 2; const px = x(frame * T.step + 0.5); c.beginPath(); c.moveTo(px, 0); c.lineTo(px, H - 16); c.stroke(); }
$('timeline').addEventListener('click', e => { if (!T || !nFrames) return; const cv = $('timeline'), r = cv.getBoundingClientRect();
  const xx = (e.clientX - r.left) * cv.width / r.width, n = T.present[0].length; setFrame(Math.round(((xx - 56) / (cv.width - 66)) * n / T.step)); });
function reprojTime(){ const cv = $('reprojTime'), c = cv.getContext('2d'), W = cv.width, H = cv.height, L = 56, R = 10, B = 18;
  c.clearRect(0, 0, W, H); c.font = '11px system-ui,sans-serif';
  if (!Q) { c.fillStyle = '#999'; c.fillText('no triangulation output', 10, 20); return; }
  const series = Q.cameras.length ? Q.cameras.map((k, i) => [k.per_frame_mean_px, camColor(i), k.name]) : [[Q.per_frame_mean_px, '#333', 'all']];
  const n = Q.per_frame_mean_px.length; let vals = [];
  for (const [s] of series) for (const v of s) if (v !== null) vals.push(v);
  vals.sort((a, b) => a - b); let maxY = vals.length ? vals[Math.floor(0.99 * (vals.length - 1))] * 1.15 : 10; maxY = Math.max(2, Math.ceil(maxY));
  const x = t => L + (W - L - R) * t / Math.max(1, n - 1), y = v => H - B - (H - B - 6) * Math.min(v, maxY) / maxY;
  c.strokeStyle = '#eceef2'; c.fillStyle = '#777';
  for (let g = 0; g <= maxY + 1e-9; g += maxY / 4) { c.beginPath(); c.moveTo(L, y(g)); c.lineTo(W - R, y(g)); c.stroke(); c.fillText(g.toFixed(1) + ' px', 4, y(g) + 4); }
  for (const [s, col] of series) { c.strokeStyle = col; c.lineWidth = 1.4; c.beginPath(); let pen = false;
    s.forEach((v, t) => { if (v === null) { pen = false; return; } const px = x(t), py = y(v); if (pen) c.lineTo(px, py); else c.moveTo(px, py); pen = true; }); c.stroke(); }
  axisSeconds(c, L, R, W, H, n * (Q.per_frame_bin || 1), fps * (T ? T.step : 1));
  if (T && nFrames) { const fi = T.frame_index[frame], t0 = Q.frame_index0 || 0, tt = (fi - t0) / (Q.per_frame_bin || 1);
    c.strokeStyle = '#1d2330'; c.lineWidth = 2; c.beginPath(); c.moveTo(x(tt), 0); c.lineTo(x(tt), H - B); c.stroke(); } }
if (Q) { const lg = $('reprojLegend'); (Q.cameras.length ? Q.cameras : [{name: 'all'}]).forEach((k, i) => { const s = document.createElement('span');
  s.innerHTML = `<i class="swatch" style="background:${Q.cameras.length ? camColor(i) : '#333'}"></i>`; s.appendChild(document.createTextNode(k.name)); lg.appendChild(s); }); }
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
  axisSeconds(c, L, R, W, H, n, fps * T.step);
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
// the forecast on a floor map (canvas context c, world -> px P, px per metre s): each track's path (dashed,
// dots every second), a stochastic model's samples (thin) and their spread (discs every 0.5 s, radius: the
// samples' RMS distance from their mean)
function drawForecastPaths(c, P, s, only, xmax){
  const pathLine = (pts, from) => { c.beginPath(); let pen = false;
    if (from) { const q = P(from); c.moveTo(q[0], q[1]); pen = true; }
    for (const r of pts) { if (!fxy(r)) continue; const q = P(r); if (pen) c.lineTo(q[0], q[1]); else c.moveTo(q[0], q[1]); pen = true; }
    c.stroke(); };
  fcPaths.forEach((traj, i) => { const k = fcTrack[i]; if (k < 0 || !traj.some(fxy) || (only !== undefined && i !== only)) return;
    const lastObs = roots.length ? roots[nFrames - 1][k] : null, sp = F.sample_paths ? F.sample_paths[i] : null;
    if (sp) { c.strokeStyle = color(k); c.globalAlpha = 0.28; c.lineWidth = 1; for (const s1 of sp) pathLine(s1, lastObs);
      const spr = F.spread_m[i], step = Math.max(1, Math.round(fcFps * 0.5));
      c.fillStyle = color(k); for (let h = step - 1; h < spr.length; h += step) { if (spr[h] === null) continue;
        const pts = sp.map(s1 => s1[h]).filter(fxy); if (!pts.length) continue;
        const m = [0, 1].map(a => pts.reduce((t, p) => t + p[a], 0) / pts.length), q = P(m);
        c.globalAlpha = 0.13; c.beginPath(); c.arc(q[0], q[1], Math.max(2, spr[h] * s), 0, 7); c.fill(); }
      c.globalAlpha = 1; }
    c.strokeStyle = color(k); c.lineWidth = 2.2; c.setLineDash([6, 4]); pathLine(traj, lastObs); c.setLineDash([]);
    c.fillStyle = color(k); for (let h = Math.round(fcFps) - 1; h < traj.length; h += Math.round(fcFps)) { if (!fxy(traj[h])) continue;
      const q = P(traj[h]); c.beginPath(); c.arc(q[0], q[1], 2.6, 0, 7); c.fill(); }
    const end = traj.filter(fxy).pop(); if (end) { const q = P(end), txt = `+${(traj.length / fcFps).toFixed(1)} s`;
      c.font = '10px system-ui,sans-serif'; c.fillStyle = '#1d2330'; const w = c.measureText(txt).width;
      c.fillText(txt, q[0] + 6 + w > (xmax === undefined ? c.canvas.width : xmax) ? q[0] - 6 - w : q[0] + 6, q[1] + 3); } });
}
(function layout(){ const cv = $('layout'), c = cv.getContext('2d'), W = cv.width, H = cv.height;
  c.fillStyle = '#fbfbfd'; c.fillRect(0, 0, W, H);
  const pts = [];
  if (D.rig) for (const k of D.rig.cameras) pts.push(k.center_m);
  for (const fr of roots) for (const r of fr) if (r) pts.push(r);
  for (const traj of fcPaths) for (const r of traj) if (fxy(r)) pts.push(r);
  if (F && F.sample_paths) for (const sp of F.sample_paths) for (const s1 of sp) for (const r of s1) if (fxy(r)) pts.push(r);
  if (!pts.length) { c.fillStyle = '#999'; c.fillText('nothing to draw', 10, 20); return; }
  let minX = Math.min(...pts.map(p => p[0])) - 0.6, maxX = Math.max(...pts.map(p => p[0])) + 0.6;
  let minY = Math.min(...pts.map(p => p[1])) - 0.6, maxY = Math.max(...pts.map(p => p[1])) + 0.6;
  const s = Math.min((W - 30) / (maxX - minX), (H - 30) / (maxY - minY));
  const ox = (W - s * (maxX - minX)) / 2, oy = (H - s * (maxY - minY)) / 2;
  const P = p => [ox + (p[0] - minX) * s, H - oy - (p[1] - minY) * s];   // world x right, world y up on the page
  c.strokeStyle = '#e6e8ee'; c.lineWidth = 1;
  for (let g = Math.ceil(minX); g <= maxX; g++) { const a = P([g, minY]), b = P([g, maxY]); c.beginPath(); c.moveTo(a[0], a[1]); c.lineTo(b[0], b[1]); c.stroke(); }
  for (let g = Math.ceil(minY); g <= maxY; g++) { const a = P([minX, g]), b = P([maxX, g]); c.beginPath(); c.moveTo(a[0], a[1]); c.lineTo(b[0], b[1]); c.stroke(); }
  c.fillStyle = '#999'; c.font = '10px system-ui,sans-serif'; c.fillText('grid: 1 m · x →, y ↑', 8, H - 8);
  if (D.rig) D.rig.cameras.forEach((k, i) => { if (!k.footprint_m) return; c.save(); c.beginPath();
    k.footprint_m.forEach((p, n) => { const q = P(p); if (n) c.lineTo(q[0], q[1]); else c.moveTo(q[0], q[1]); }); c.closePath();
    c.fillStyle = camColor(i) + '0b'; c.fill(); c.strokeStyle = camColor(i) + '90'; c.lineWidth = 1.2; c.setLineDash([4, 3]); c.stroke(); c.restore(); });
  if (D.rig) D.rig.cameras.forEach((k, i) => { const [x, y] = P(k.center_m), a = k.axis, h = Math.hypot(a[0], a[1]);
    if (h > 1e-6) { c.strokeStyle = camColor(i); c.lineWidth = 2; c.beginPath(); c.moveTo(x, y); c.lineTo(x + 18 * a[0] / h, y - 18 * a[1] / h); c.stroke(); }
    c.fillStyle = camColor(i); c.beginPath(); c.arc(x, y, 5, 0, 7); c.fill();
    c.fillStyle = '#1d2330'; c.font = '11px system-ui,sans-serif'; c.fillText(k.name, x + 8, y - 6); });
  for (let k = 0; k < nTracks; k++) { c.strokeStyle = color(k); c.lineWidth = 2.2; c.beginPath(); let pen = false, last = null, first = null;
    for (let t = 0; t < nFrames; t++) { const r = roots[t][k]; if (!r) { pen = false; continue; } const q = P(r);
      if (pen) c.lineTo(q[0], q[1]); else c.moveTo(q[0], q[1]); pen = true; last = q; first = first || q; }
    c.stroke(); if (first) { c.fillStyle = color(k); c.beginPath(); c.arc(first[0], first[1], 3, 0, 7); c.fill(); }
    if (last) { c.beginPath(); c.arc(last[0], last[1], 5, 0, 7); c.fill(); } }
  drawForecastPaths(c, P, s);
  if (F) { const H = F.xyz[0] ? F.xyz[0].length : 0, sec = (H / fcFps).toFixed(1);
    $('layoutNote').textContent = `Dashed: each person's forecast path for the next ${sec} s by ${F.model || 'the forecast'} (dots every second). ` +
      (F.sample_paths ? `Thin lines: its ${F.sample_paths[0] ? F.sample_paths[0].length : 0} samples; shaded discs: their spread every 0.5 s (RMS distance from their mean).`
        : F.stochastic === false ? `This model is deterministic: it gives one path, so there is no spread to draw (a stochastic model, e.g. [forecast] model = "forecast/checkpoints/intention_cmuall.pt", draws samples).`
        : 'The forecast file holds one path per person (no samples).'); }
})();

// the forecast paths from above, one panel per person centred on them (one scale for all): the last 2 s
// walked (solid), then the forecast
(function forecastMap(){ const cv = $('fcmap'); if (!F || !T || !nFrames) return;
  const back = Math.round(2 * fps), who = [];
  fcTrack.forEach((k, i) => { if (k < 0 || !roots[nFrames - 1][k] || !fcPaths[i].some(fxy)) return;
    const pts = [];
    for (let t = Math.max(0, nFrames - back); t < nFrames; t++) if (roots[t][k]) pts.push(roots[t][k]);
    for (const r of fcPaths[i]) if (fxy(r)) pts.push(r);
    if (F.sample_paths) for (const s1 of F.sample_paths[i]) for (const r of s1) if (fxy(r)) pts.push(r);
    who.push([i, k, pts]); });
  if (!who.length) return;
  $('fcsec').style.display = 'block';
  const cols = Math.min(3, who.length), rows = Math.ceil(who.length / cols), side = Math.floor(cv.width / cols);
  cv.height = rows * side; const c = cv.getContext('2d'), W = cv.width, H = cv.height;
  c.fillStyle = '#fff'; c.fillRect(0, 0, W, H);
  const box = pts => { const lo = [0, 1].map(a => Math.min(...pts.map(p => p[a]))), hi = [0, 1].map(a => Math.max(...pts.map(p => p[a])));
    return [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, Math.max(hi[0] - lo[0], hi[1] - lo[1]) / 2]; };
  const half = Math.max(0.75, ...who.map(w => box(w[2])[2] * 1.15 + 0.25)), s = side / (2 * half), g = half > 2.5 ? 1 : 0.5;
  who.forEach(([i, k, pts], n) => { const x0 = (n % cols) * side, y0 = Math.floor(n / cols) * side, [cx, cy] = box(pts);
    const P = p => [x0 + side / 2 + (p[0] - cx) * s, y0 + side / 2 - (p[1] - cy) * s];
    c.save(); c.beginPath(); c.rect(x0 + 3, y0 + 3, side - 6, side - 6); c.clip();
    c.fillStyle = '#fbfbfd'; c.fillRect(x0, y0, side, side); c.strokeStyle = '#e6e8ee'; c.lineWidth = 1;
    for (let x = Math.floor((cx - half) / g) * g; x <= cx + half; x += g) { const q = P([x, 0]); c.beginPath(); c.moveTo(q[0], y0); c.lineTo(q[0], y0 + side); c.stroke(); }
    for (let y = Math.floor((cy - half) / g) * g; y <= cy + half; y += g) { const q = P([0, y]); c.beginPath(); c.moveTo(x0, q[1]); c.lineTo(x0 + side, q[1]); c.stroke(); }
    c.strokeStyle = color(k); c.lineWidth = 2.5; c.beginPath(); let pen = false;
    for (let t = Math.max(0, nFrames - back); t < nFrames; t++) { const r = roots[t][k]; if (!r) { pen = false; continue; } const q = P(r);
      if (pen) c.lineTo(q[0], q[1]); else c.moveTo(q[0], q[1]); pen = true; } c.stroke();
    const q = P(roots[nFrames - 1][k]); c.fillStyle = color(k); c.beginPath(); c.arc(q[0], q[1], 5, 0, 7); c.fill();
    drawForecastPaths(c, P, s, i, x0 + side - 4);
    c.restore(); c.fillStyle = color(k); c.font = 'bold 12px system-ui,sans-serif'; c.fillText('id ' + T.track_id[k], x0 + 10, y0 + 20);
    if (F.spread_m && F.spread_m[i]) { const sp = F.spread_m[i].filter(v => v !== null); if (sp.length) { c.fillStyle = '#555'; c.font = '11px system-ui,sans-serif';
      c.fillText(`spread at +${(F.spread_m[i].length / fcFps).toFixed(1)} s: ${(100 * sp[sp.length - 1]).toFixed(0)} cm`, x0 + 10, y0 + 36); } } });
  $('fcNote').textContent = `grid: ${g} m, the same scale in every panel · solid: the last 2 s walked · dashed: the forecast` + (F.sample_paths ? ' · thin: its samples · discs: their spread every 0.5 s' : F.stochastic === false ? ` · ${F.model || 'the model'} is deterministic: one path, no spread` : '');
})();

// ---------------------------------------------------------------- 3D viewer (viewer3d.js)
const cv = $('viewer'), V3 = RoomView3D(cv), ctx = V3.ctx, project = V3.project, line = V3.line, floorOf = V3.floorOf;
let playing = false;
(function fit(){ const pts = []; for (const fr of roots) for (const r of fr) if (r) pts.push(r);
  for (const traj of fcRoots) for (const r of traj) if (r) pts.push(r);
  if (!pts.length && D.rig) for (const k of D.rig.cameras) pts.push(k.center_m);
  V3.fit(pts);
})();
// hand joints (COCO-WholeBody names: <side>_hand_root, <side>_thumb1..4, <side>_<finger>_finger1..4): drawn
// thin after the body, from the wrists; a body track has none and draws as before
const handJoint = T ? T.joint_names.map(n => /_(hand_root|thumb[1-4]|finger[1-4])$/.test(n)) : [];
const hasHands = handJoint.some(h => h);
const wristJoint = T ? T.joint_names.map(n => n === 'left_wrist' || n === 'right_wrist') : [];
function skeleton(pose, col, w, std_m, alpha, box){
  if (!hasHands || !pose) { V3.skeleton(pose, T.parents, col, w, std_m, alpha, box); return; }
  V3.skeleton(pose.map((p, j) => handJoint[j] ? null : p), T.parents, col, w, std_m, alpha, box);
  V3.skeleton(pose.map((p, j) => handJoint[j] || wristJoint[j] ? p : null), T.parents, col, Math.max(1, w * 0.4), 0, alpha); }
const overlaps = (a, b) => a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
function cameraLabels(boxes){ // after the people: a label goes where it covers no one (and no other label), else it fades
  if (!D.rig) return; ctx.font = '12px system-ui,sans-serif'; const taken = boxes.slice();
  for (const k of D.rig.cameras) { const q = project(k.center_m); if (!q) continue;
    const w = ctx.measureText(k.name).width, h = 14; let placed = null;
    const near = [[6, -6], [6, 16], [-w - 6, -6], [-w - 6, 16], [-w / 2, -14], [-w / 2, 26], [14, 5], [-w - 14, 5]];
    const far = []; for (const r of [45, 80, 120]) for (let a = 0; a < 8; a++) { const t = -Math.PI / 2 + a * Math.PI / 4;
      far.push([r * Math.cos(t) - w / 2, r * Math.sin(t) + 5, true]); }
    for (const [dx, dy, lead] of near.concat(far)) {
      const b = [q[0] + dx - 2, q[1] + dy - h + 2, q[0] + dx + w + 2, q[1] + dy + 4];
      if (b[0] < 0 || b[1] < 0 || b[2] > cv.width || b[3] > cv.height) continue;
      if (!taken.some(t => overlaps(t, b))) { placed = [dx, dy, b, lead]; break; } }
    ctx.fillStyle = '#aab3c5'; ctx.globalAlpha = placed ? 1 : 0.3; const [dx, dy] = placed || [6, -6];
    if (placed && placed[3]) { ctx.strokeStyle = '#5d6882'; ctx.lineWidth = 1; ctx.setLineDash([2, 3]); ctx.beginPath(); ctx.moveTo(q[0], q[1]);
      ctx.lineTo(q[0] + dx + w / 2, q[1] + dy - 4); ctx.stroke(); ctx.setLineDash([]); }
    ctx.fillText(k.name, q[0] + dx, q[1] + dy); ctx.globalAlpha = 1; if (placed) taken.push(placed[2]); } }
function draw(){
  V3.background();
  if (D.rig) for (const k of D.rig.cameras) V3.drawCamera(k);
  if (!T || !nFrames) { ctx.fillStyle = '#aab3c5'; ctx.font = '16px system-ui,sans-serif'; ctx.fillText('No tracks in this session yet.', 30, 40); cameraLabels([]); return; }
  const trail = Math.round(fps * 1.0);
  for (let k = 0; k < nTracks; k++) { let prev = null;
    for (let t = 0; t <= frame; t++) { const r = roots[t][k]; if (!r) { prev = null; continue; }
      if (prev) { ctx.globalAlpha = t > frame - trail ? 0.9 : 0.22; line(floorOf(prev), floorOf(r), color(k), t > frame - trail ? 2.5 : 1.5); } prev = r; }
    ctx.globalAlpha = 1; }
  const nearEnd = frame >= nFrames - 1 - Math.round(fps * 0.5);
  fcRoots.forEach((traj, i) => { const k = fcTrack[i]; if (k < 0) return; let prev = roots[nFrames - 1][k];
    ctx.globalAlpha = nearEnd ? 0.95 : 0.45;
    for (const r of traj) { if (!r) continue; if (prev) line(floorOf(prev), floorOf(r), color(k), 2, [6, 5]); prev = r; }
    if (nearEnd && F.sample_paths && F.sample_paths[i]) { ctx.globalAlpha = 0.3; // the samples, on the floor
      for (const s1 of F.sample_paths[i]) { let q0 = roots[nFrames - 1][k];
        for (const r of s1) { if (!fxy(r)) continue; const q = [r[0], r[1], 0]; if (q0) line(floorOf(q0), q, color(k), 1); q0 = q; } } }
    ctx.globalAlpha = 1;
    if (nearEnd) { const H = traj.length, step = Math.max(1, Math.round(fcFps * 0.5));
      for (let h = step - 1; h < H; h += step) skeleton(F.xyz[i][h], color(k), 1.6, 0, 0.16 + 0.3 * (1 - h / H)); } });
  const behavLabels = [];
  if (BH && BH.poses && nearEnd) BH.track_id.forEach((id, i) => { const k = T.track_id.indexOf(id), pose = BH.poses[i][behavStep];
    if (!pose) return; const col = k >= 0 ? color(k) : '#ffffff';
    V3.skeleton(pose, BH.parents, '#ffffff', 3.4, 0, 0.35); V3.skeleton(pose, BH.parents, col, 2, 0, 0.8);
    const top = pose.filter(fin).reduce((a, b) => (b[2] > a[2] ? b : a), [0, 0, -1e9]), q = top[2] > -1e9 ? project([top[0], top[1], top[2] + 0.7]) : null;
    if (q) behavLabels.push([q, `+${behavStep + 1}: ${BH.actions[i][behavStep]} ${Math.round(100 * BH.prob[i][behavStep])}%`, col]); });
  const fr = T.xyz[frame], boxes = [];
  fr.forEach((pose, k) => { const box = [1e9, 1e9, -1e9, -1e9];
    skeleton(pose, color(k), 3.2, T.mean_std_m.length ? T.mean_std_m[k][frame] : 0, 1, box);
    const top = pose ? (fin(pose[jHead]) ? pose[jHead] : rootOf(pose)) : null;
    if (top) { const q = project([top[0], top[1], top[2] + 0.25]); if (q) { ctx.font = 'bold 12px system-ui,sans-serif';
      const label = 'id ' + T.track_id[k], w = ctx.measureText(label).width + 10; ctx.fillStyle = color(k); ctx.globalAlpha = 0.9;
      ctx.beginPath(); ctx.roundRect ? ctx.roundRect(q[0] - w / 2, q[1] - 16, w, 18, 9) : ctx.rect(q[0] - w / 2, q[1] - 16, w, 18); ctx.fill();
      ctx.globalAlpha = 1; ctx.fillStyle = '#fff'; ctx.fillText(label, q[0] - w / 2 + 5, q[1] - 3);
      box[1] = Math.min(box[1], q[1] - 16); box[0] = Math.min(box[0], q[0] - w / 2); box[2] = Math.max(box[2], q[0] + w / 2); } }
    if (box[2] > box[0]) boxes.push([box[0] - 4, box[1] - 4, box[2] + 4, box[3] + 4]); });
  for (const [q, txt, col] of behavLabels) { // the behaviour step's label: above the pose, clear of the people's tags
    ctx.font = '12px system-ui,sans-serif'; const w = ctx.measureText(txt).width + 10;
    let b = null; for (const dy of [0, -22, -44, 22, -66]) { const c0 = [q[0] - w / 2, q[1] - 15 + dy, q[0] + w / 2, q[1] + 3 + dy];
      if (!boxes.some(t => overlaps(t, c0))) { b = c0; break; } }
    b = b || [q[0] - w / 2, q[1] - 15, q[0] + w / 2, q[1] + 3]; boxes.push(b);
    ctx.fillStyle = '#10141cdd'; ctx.strokeStyle = col; ctx.lineWidth = 1.5; ctx.beginPath(); ctx.rect(b[0], b[1], w, 18); ctx.fill(); ctx.stroke();
    ctx.fillStyle = '#fff'; ctx.fillText(txt, b[0] + 5, b[1] + 13); }
  cameraLabels(boxes);
  ctx.fillStyle = '#aab3c5'; ctx.font = '13px system-ui,sans-serif';
  const tSec = (T.frame_index[frame] - T.frame_index[0]) / (fps * T.step);
  ctx.fillText(`${tSec.toFixed(2)} s · frame ${T.frame_index[frame]} · ${peopleAt[frame]} people`, 16, 26);
  if (F && nearEnd) ctx.fillText(`forecast: ${F.model}, ghosts every 0.5 s`, 16, 46);
  if (BH && BH.poses && nearEnd) ctx.fillText(`behaviour forecast: step +${behavStep + 1}'s characteristic pose (${BH.model})`, 16, F ? 66 : 46);
  $('frameLabel').textContent = `frame ${T.frame_index[frame]} / ${T.frame_index[nFrames - 1]}`;
}

// ---------------------------------------------------------------- camera filmstrips
const films = [];
let filmIdx = 0;
const showDet = $('showDet'), showProj = $('showProj');
function filmIndexOf(fi){ const fr = V.frames; let lo = 0, hi = fr.length - 1; if (fi <= fr[0]) return 0;
  while (lo < hi) { const m = (lo + hi + 1) >> 1; if (fr[m] <= fi) lo = m; else hi = m - 1; }
  return (lo + 1 < fr.length && fr[lo + 1] - fi < fi - fr[lo]) ? lo + 1 : lo; }
function drawFilm(f){ const c = f.ctx, W = f.cv.width, H = f.cv.height, v = f.view, i = filmIdx;
  const img = f.imgs[i];
  if (img && img.complete && img.naturalWidth) c.drawImage(img, 0, 0, W, H);
  else { c.fillStyle = '#181d27'; c.fillRect(0, 0, W, H); if (img) img.onload = () => { if (filmIdx === i) drawFilm(f); }; }
  const src = v.video_wh || v.size_wh, sx = W / src[0], sy = H / src[1], ov = v.overlays[i] || {det: [], proj: []}, par = V.parents;
  const P = (a, j) => a[2 * j] === null || a[2 * j + 1] === null ? null : [a[2 * j] * sx, a[2 * j + 1] * sy];
  c.lineCap = 'round';
  if (showDet.checked) for (const [k, a] of ov.det) { c.strokeStyle = k >= 0 ? color(k) : '#aaaaaa'; c.lineWidth = 3.2; c.globalAlpha = 0.85;
    par.forEach((p, j) => { if (p < 0) return; const u = P(a, j), w = P(a, p); if (!u || !w) return; c.beginPath(); c.moveTo(u[0], u[1]); c.lineTo(w[0], w[1]); c.stroke(); }); }
  c.globalAlpha = 1;
  if (showProj.checked) for (const [k, a] of ov.proj) { c.strokeStyle = '#ffffff'; c.lineWidth = 1.1;
    par.forEach((p, j) => { if (p < 0) return; const u = P(a, j), w = P(a, p); if (!u || !w) return; c.beginPath(); c.moveTo(u[0], u[1]); c.lineTo(w[0], w[1]); c.stroke(); });
    c.fillStyle = V.untracked ? '#ffffff' : color(k);
    par.forEach((p, j) => { const u = P(a, j); if (!u) return; c.beginPath(); c.arc(u[0], u[1], 2.6, 0, 7); c.fill(); c.strokeStyle = '#fff'; c.lineWidth = 0.8; c.stroke(); }); }
  if (V.hand_parents) { const hp = V.hand_parents; // hands: thin, the detection's in its track's colour, the reprojection white
    const bones = (a, col, w) => { c.strokeStyle = col; c.lineWidth = w; hp.forEach((p, j) => { if (p < 0) return; const u = P(a, j), q = P(a, p); if (!u || !q) return;
      c.beginPath(); c.moveTo(u[0], u[1]); c.lineTo(q[0], q[1]); c.stroke(); }); };
    if (showDet.checked) for (const [k, a] of ov.hdet || []) { c.globalAlpha = 0.85; bones(a, k >= 0 ? color(k) : '#aaaaaa', 1.6); }
    c.globalAlpha = 1;
    if (showProj.checked) for (const [k, a] of ov.hproj || []) { bones(a, '#ffffff', 0.8); c.fillStyle = V.untracked ? '#ffffff' : color(k);
      hp.forEach((p, j) => { if (j < 2) return; const u = P(a, j); if (!u) return; c.beginPath(); c.arc(u[0], u[1], 1.3, 0, 7); c.fill(); }); } }
  f.label.textContent = `frame ${V.frames[i]}` + (ov.err !== null && ov.err !== undefined ? ` · ${ov.err.toFixed(1)} px` : '');
  if (f.strip) { if (f.on) f.on.classList.remove('on'); const t = f.strip.children[i]; if (t) { t.classList.add('on'); f.on = t;
    const s = f.strip, left = t.offsetLeft - s.offsetLeft; if (left < s.scrollLeft || left + t.offsetWidth > s.scrollLeft + s.clientWidth) s.scrollLeft = left - s.clientWidth / 2; } } }
function drawFilms(){ for (const f of films) drawFilm(f);
  if (V) { $('filmLabel').textContent = `frame ${V.frames[filmIdx]} (${filmIdx + 1} of ${V.frames.length} sampled)`; $('filmFrame').value = filmIdx; } }
(function buildFilms(){
  if (!V || !V.cameras.length) { $('films').innerHTML = '<div class="muted">No camera views: no detections in this session.</div>'; return; }
  const every = V.sampled_every > 1.01 ? `every ${V.sampled_every.toFixed(1)} frames (sampled to keep the file small)` : 'every frame';
  $('filmNote').textContent = `${V.cameras.length} cameras · ${V.frames.length} frames, ${every}` + (V.untracked ? ' · untracked 3D poses (white)' : '');
  $('filmFrame').max = V.frames.length - 1;
  for (const v of V.cameras) {
    const box = document.createElement('div'); box.className = 'film'; box.dataset.camera = v.name;
    const head = document.createElement('div'); head.className = 'head'; const b = document.createElement('b'); b.textContent = v.name;
    const label = document.createElement('span'); head.appendChild(b); head.appendChild(label); box.appendChild(head);
    const cvs = document.createElement('canvas'); const src = v.video_wh || v.size_wh, maxW = 460, maxH = 420;
    const s = Math.min(maxW / src[0], maxH / src[1]); cvs.width = Math.round(src[0] * s); cvs.height = Math.round(src[1] * s);
    cvs.style.maxWidth = cvs.width + 'px'; cvs.style.margin = '0 auto'; cvs.className = 'filmcanvas'; box.appendChild(cvs);
    if (v.note) { const n = document.createElement('div'); n.className = 'note'; n.textContent = v.note; box.appendChild(n); }
    const imgs = v.images.map(u => { if (!u) return null; const im = new Image(); im.src = u; return im; });
    let strip = null;
    if (v.images.some(u => u)) { strip = document.createElement('div'); strip.className = 'strip';
      v.images.forEach((u, i) => { const t = document.createElement('img'); t.loading = 'lazy'; t.decoding = 'async'; t.alt = `frame ${V.frames[i]}`;
        if (u) t.src = u; t.addEventListener('click', () => setFilm(i)); strip.appendChild(t); }); box.appendChild(strip); }
    $('films').appendChild(box);
    films.push({view: v, cv: cvs, ctx: cvs.getContext('2d'), imgs, label, strip, on: null, box});
  }
  showDet.addEventListener('change', drawFilms); showProj.addEventListener('change', drawFilms);
  $('filmFrame').addEventListener('input', () => setFilm(+$('filmFrame').value));
})();

// ---------------------------------------------------------------- one frame for everything
function redraw(){ draw(); timeline(); uncertainty(); reprojTime(); drawFilms(); }
function setFrame(t){ if (!T || !nFrames) return; frame = Math.max(0, Math.min(nFrames - 1, t | 0)); slider.value = frame;
  if (V) filmIdx = filmIndexOf(T.frame_index[frame]); redraw(); }
function setFilm(i){ if (!V) return; filmIdx = Math.max(0, Math.min(V.frames.length - 1, i | 0));
  if (T && nFrames) { frame = viewerRowOf(V.frames[filmIdx]); slider.value = frame; } redraw(); }
const slider = $('frame'); slider.max = Math.max(0, nFrames - 1);
slider.addEventListener('input', () => setFrame(+slider.value));
$('play').addEventListener('click', () => { playing = !playing; $('play').innerHTML = playing ? '&#10074;&#10074; Pause' : '&#9654; Play'; });
V3.orbit(draw);
if (T) { const lg = $('legend'); T.track_id.forEach((id, k) => { const s = document.createElement('span');
  const first = T.present[k].indexOf(1), last = T.present[k].lastIndexOf(1);
  s.innerHTML = `<i class="swatch" style="background:${color(k)}"></i>`; s.appendChild(document.createTextNode(
    `id ${id} (${first < 0 ? 0 : ((last - first + 1) / (fps * T.step)).toFixed(1)} s)`)); lg.appendChild(s); }); }
$('viewerNote').textContent = T ? `${nTracks} tracks, ${maxPeople} people at most at once` : '';
// start where a still picture says most: the last frame with its forecast, else the frame with the most people
let start = 0;
if (T && nFrames) { peopleAt.forEach((n, t) => { if (n >= peopleAt[start]) start = t; }); if (F && peopleAt[nFrames - 1] > 0) start = nFrames - 1; }
if (T && nFrames) setFrame(start); else { if (V) setFilm(0); draw(); timeline(); uncertainty(); reprojTime(); }
// where each camera view is on the page (tests crop their screenshots with it)
function rects(){ const out = {}; for (const f of films) { const r = f.cv.getBoundingClientRect();
  out[f.view.name] = [Math.round(r.left + window.scrollX), Math.round(r.top + window.scrollY), Math.round(r.width), Math.round(r.height)]; }
  document.body.setAttribute('data-film-rects', JSON.stringify(out)); }
rects(); window.addEventListener('resize', rects);
Promise.all(films.flatMap(f => f.imgs.filter(Boolean).slice(0, 1).concat(f.imgs.filter(Boolean).slice(filmIdx, filmIdx + 1)).map(im => im.decode ? im.decode().catch(() => null) : null)))
  .then(() => { drawFilms(); rects(); document.body.setAttribute('data-films', String(films.length)); });
document.body.setAttribute('data-rendered', T ? String(nTracks) : '0');
let last = 0;
function tick(ts){ if (playing && T && nFrames > 1 && ts - last > 1000 / Math.min(30, fps)) {
  frame = (frame + 1) % nFrames; slider.value = frame; if (V) filmIdx = filmIndexOf(T.frame_index[frame]); redraw(); last = ts; } requestAnimationFrame(tick); }
requestAnimationFrame(tick);
// behaviour forecast (forecast/behaviour.npz): a timeline per person (the labelled steps over time, then
// the next M actions with their probabilities), the table, and the step whose pose the 3D view draws
const ACTCOL = ['#8dd3c7', '#fdb462', '#bebada', '#fb8072', '#80b1d3', '#b3de69', '#fccde5', '#ffed6f', '#bc80bd', '#d9d9d9'];
function behaviourTimeline(){ const B = BH, cv = $('behavTimeline'), c = cv.getContext('2d');
  const K = B.track_id.length, M = B.actions[0].length, rowH = 50, top = 24, L = 64, W = cv.width;
  cv.height = top + K * rowH + 24; const H = cv.height; c.clearRect(0, 0, W, H); const font = (px, b) => { c.font = (b ? 'bold ' : '') + px + 'px system-ui,sans-serif'; }; font(14);
  const labels = B.labels.length ? B.labels : [...new Set([].concat(...B.actions, ...B.observed).filter(x => x))];
  const acol = a => ACTCOL[Math.max(0, labels.indexOf(a)) % ACTCOL.length];
  const S = B.step_start_s, E = B.step_end_s, Tc = B.step_time_s;
  const ts = [].concat(...(S || []), ...(E || []), ...(Tc || [])).filter(v => v !== null);
  const t0 = ts.length ? Math.min(0, ...ts) : 0, t1 = ts.length ? Math.max(...ts, t0 + 0.1) : 1;
  const obsR = L + Math.round((W - L) * 0.4), fx = obsR + 26, sw = (W - 4 - fx) / M;
  const tx = t => L + (obsR - L) * (t - t0) / (t1 - t0);
  c.fillStyle = '#6b7385'; c.fillText('observed (labels)', L, 15); for (let m = 0; m < M; m++) c.fillText(`+${m + 1}`, fx + m * sw + 2, 15);
  c.strokeStyle = '#1d2330'; c.lineWidth = 1.5; c.setLineDash([3, 3]); c.beginPath(); c.moveTo(obsR + 12, top - 6); c.lineTo(obsR + 12, H - 18); c.stroke(); c.setLineDash([]);
  c.fillStyle = '#1d2330'; font(13); c.fillText('now', obsR, H - 6);
  const fit = (txt, w) => { if (c.measureText(txt).width <= w) return txt; while (txt.length > 1 && c.measureText(txt + '…').width > w) txt = txt.slice(0, -1); return txt.length > 1 ? txt + '…' : ''; };
  B.track_id.forEach((id, i) => { const y = top + i * rowH, k = T ? T.track_id.indexOf(id) : -1;
    c.fillStyle = k >= 0 ? color(k) : '#333'; c.fillRect(0, y + 4, 4, rowH - 12); c.fillStyle = '#1d2330'; font(15, true); c.fillText('id ' + id, 10, y + rowH / 2 + 2);
    font(14); c.fillStyle = '#f3f4f7'; c.fillRect(L, y + 4, obsR - L, rowH - 12);
    (B.observed[i] || []).forEach((a, n) => { if (!a) return;
      const s0 = S && S[i][n] !== null ? S[i][n] : null, s1 = E && E[i][n] !== null ? E[i][n] : null;
      if (s0 !== null && s1 !== null) { const x0 = tx(s0), x1 = tx(s1); c.fillStyle = acol(a); c.fillRect(x0, y + 4, Math.max(2, x1 - x0 - 1), rowH - 12);
        c.fillStyle = '#1d2330'; c.fillText(fit(a, x1 - x0 - 8), x0 + 5, y + rowH / 2 + 2); }
      else if (Tc && Tc[i][n] !== null) { const x = tx(Tc[i][n]); c.fillStyle = acol(a); c.beginPath(); c.arc(x, y + rowH / 2 - 2, 6, 0, 7); c.fill();
        c.fillStyle = '#1d2330'; c.fillText(a, x + 8, y + rowH / 2 + 2); }
      if (Tc && Tc[i][n] !== null) { const x = tx(Tc[i][n]); c.fillStyle = '#1d2330'; c.beginPath(); c.moveTo(x - 3, y + rowH - 8); c.lineTo(x + 3, y + rowH - 8); c.lineTo(x, y + rowH - 13); c.fill(); } });
    for (let m = 0; m < M; m++) { const x = fx + m * sw, p = B.probs ? B.probs[i][m] : null, a = B.actions[i][m];
      c.fillStyle = '#f3f4f7'; c.fillRect(x, y + 4, sw - 6, rowH - 12);
      if (p) { const order = p.map((v, j) => [v, j]).sort((u, v) => v[0] - u[0]); let xx = x; const bw = sw - 6;
        for (const [v, j] of order) { const w = bw * v; c.fillStyle = ACTCOL[j % ACTCOL.length]; c.globalAlpha = j === labels.indexOf(a) ? 1 : 0.55; c.fillRect(xx, y + rowH - 20, w, 11); xx += w; }
        c.globalAlpha = 1; }
      else { c.fillStyle = acol(a); c.fillRect(x, y + rowH - 20, (sw - 6) * B.prob[i][m], 11); }
      c.fillStyle = acol(a); c.fillRect(x, y + 4, 5, rowH - 25);
      const pct = `${Math.round(100 * B.prob[i][m])}%`; font(13); const pw = c.measureText(pct).width;
      c.fillStyle = '#6b7385'; c.fillText(pct, x + sw - 10 - pw, y + 20);
      c.fillStyle = '#1d2330'; font(14, m === behavStep); c.fillText(fit(a, sw - 22 - pw), x + 10, y + 20);
      if (m === behavStep && B.poses) { c.strokeStyle = '#1d2330'; c.lineWidth = 1.5; c.strokeRect(x - 1, y + 3, sw - 4, rowH - 10); } } });
  font(12); c.fillStyle = '#777'; const step = (t1 - t0) > 20 ? 5 : (t1 - t0) > 5 ? 1 : (t1 - t0) > 2 ? 0.5 : 0.25;
  for (let t = Math.ceil(t0 / step) * step; t <= t1 + 1e-9; t += step) c.fillText(t.toFixed(step < 1 ? 2 : 0) + ' s', tx(t) - 10, H - 6);
  return {fx, sw, top, rowH, M}; }
if (BH) {
  $('behavsec').style.display = 'block'; $('behavNote').textContent = BH.model;
  const t = $('behaviour'); const M = BH.actions[0].length;
  const h = t.insertRow(); ['track', 'observed'].concat(Array.from({length: M}, (_, k) => `+${k + 1}`)).forEach(x => {
    const c = document.createElement('th'); c.textContent = x; h.appendChild(c); });
  BH.track_id.forEach((id, i) => { const r = t.insertRow(); r.insertCell().textContent = id;
    r.insertCell().textContent = (BH.observed[i] || []).filter(x => x).join(' → ');
    BH.actions[i].forEach((a, k) => { r.insertCell().textContent = `${a} (${Math.round(100 * BH.prob[i][k])}%)`; }); });
  const labels = BH.labels.length ? BH.labels : [];
  labels.forEach((a, j) => { const sp = document.createElement('span'); sp.innerHTML = `<i class="swatch" style="background:${ACTCOL[j % ACTCOL.length]}"></i>`;
    sp.appendChild(document.createTextNode(a)); $('behavLegend').appendChild(sp); });
  let geo = behaviourTimeline();
  const pick = m => { behavStep = m; geo = behaviourTimeline();
    [...$('behavSteps').children].forEach((b, j) => b.classList.toggle('on', j === m));
    if (T && nFrames) setFrame(nFrames - 1); };
  if (BH.poses) for (let m = 0; m < M; m++) { const b = document.createElement('button'); b.textContent = `+${m + 1}`; b.className = 'step' + (m ? '' : ' on');
    b.addEventListener('click', () => pick(m)); $('behavSteps').appendChild(b); }
  else $('behavSteps').textContent = 'none: the forecast file holds no poses';
  $('behavTimeline').addEventListener('click', e => { if (!BH.poses) return; const cv = $('behavTimeline'), r = cv.getBoundingClientRect();
    const x = (e.clientX - r.left) * cv.width / r.width, m = Math.floor((x - geo.fx) / geo.sw); if (x >= geo.fx && m >= 0 && m < geo.M) pick(m); });
  document.body.setAttribute('data-behaviour', String(BH.track_id.length));
}
if (!navigator.webdriver && !/HeadlessChrome/.test(navigator.userAgent)) { playing = true; $('play').innerHTML = '&#10074;&#10074; Pause'; }
})();
