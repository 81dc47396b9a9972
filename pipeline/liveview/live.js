(function(){
'use strict';
// the report's identity colours (report.js COLORS); here a track's colour follows its id
const COLORS = ['#e6194b','#3cb44b','#4363d8','#f58231','#911eb4','#42d4f4','#f032e6','#bfef45','#fabed4',
                '#469990','#dcbeff','#9a6324','#fffac8','#800000','#aaffc3','#808000'];
const color = id => COLORS[((id % COLORS.length) + COLORS.length) % COLORS.length];
const $ = id => document.getElementById(id);
const PANE_W = 300, PANE_H = 440;
let hello = null, state = null, ws = null, acked = -1, ackedFrame = null;
// what the next animation frame redraws (scheduled only when something changed): everything (a new state),
// the room alone (a new forecast of the set drawn, an orbit), or single camera panes (a new image)
const need = {all: false, room: false, panes: new Set()}; let scheduled = false;
function invalidate(what, cam){
  if (what === 'pane') need.panes.add(cam); else need[what] = true;
  if (!scheduled) { scheduled = true; requestAnimationFrame(tick); }
}
const recent = new Map();   // seq -> state, to draw an image with the detections of its own frame set
const panes = {}, statCells = {};  // per camera: its pane, its row's cells (fps, frames, dropped, skipped)
let whoIds = null;  // the ids the 'who' list shows
const lat = [];             // the page's own latency readout: capture -> drawn, ms
const V3 = RoomView3D($('room'));
V3.orbit(() => invalidate('room'));

function setText(el, text){ if (el.textContent !== text) el.textContent = text; }  // an unchanged text is not laid out again

function onHello(m){
  hello = m; $('panes').innerHTML = ''; whoIds = null;
  // the cameras' table: built once, its cells updated in place
  const tbl = $('camStats'); tbl.innerHTML = '<tr><th>camera</th><th>fps</th><th>frames</th><th>dropped</th><th>skipped by live</th></tr>';
  for (const cam of m.cameras) { const tr = document.createElement('tr'), td = document.createElement('td'); td.textContent = cam; tr.appendChild(td);
    statCells[cam] = [0, 1, 2, 3].map(() => tr.appendChild(document.createElement('td'))); tbl.appendChild(tr); }
  for (const cam of m.cameras) {
    const box = document.createElement('div'); box.className = 'pane'; box.dataset.camera = cam;
    const head = document.createElement('div'); head.className = 'head';
    const b = document.createElement('b'); b.textContent = cam; const info = document.createElement('span'); info.className = 'muted';
    head.appendChild(b); head.appendChild(info); box.appendChild(head);
    const cv = document.createElement('canvas'); cv.width = PANE_W; cv.height = Math.round(PANE_W * 4 / 3); box.appendChild(cv);
    $('panes').appendChild(box);
    panes[cam] = {box, cv, ctx: cv.getContext('2d'), info, bitmap: null, head: null, drawn: false};
  }
  if (m.rig && m.rig.cameras.length) { V3.fit(m.rig.cameras.map(k => k.center_m)); V3.view.zoom = 1.5; }  // the cameras' ring, closer
  document.body.dataset.panes = String(m.cameras.length);
  $('fcPill').hidden = !m.forecast;
  if (m.forecast) $('fcToggle').checked = m.forecast.on;
  invalidate('all');
}

// the page's forecast switch: the server's forecaster stops (no CPU spent) or starts again
$('fcToggle').addEventListener('change', e => {
  if (ws && ws.readyState === 1) ws.send(JSON.stringify({forecast: e.target.checked}));
});

function drawForecast(fc, ids){ // per person: the hips' path on the floor (dashed) and the ghost pose at the horizon
  const J = hello.joint_names.length; let n = 0;
  for (const t of fc.tracks) {
    if (!ids.has(t.id)) continue;  // a forecast of a track no longer in view
    const col = color(t.id), path = [];
    for (let k = 0; k + 2 < t.path.length; k += 3) path.push([t.path[k], t.path[k + 1], 0]);
    const pts = path.filter(V3.fin); if (pts.length < 2) continue;
    for (let k = 1; k < pts.length; k++) V3.line(pts[k - 1], pts[k], col, 3, [7, 5]);
    const end = V3.project(pts[pts.length - 1]);
    if (end) { V3.ctx.strokeStyle = col; V3.ctx.lineWidth = 2; V3.ctx.beginPath(); V3.ctx.arc(end[0], end[1], 6, 0, 7); V3.ctx.stroke(); }
    const ghost = []; for (let j = 0; j < J; j++) ghost.push([t.ghost[3 * j], t.ghost[3 * j + 1], t.ghost[3 * j + 2]]);
    V3.skeleton(ghost, hello.parents, col, 1.8, 0, 0.5, null);
    n++;
  }
  return n;
}

function onImage(buf){
  const n = new DataView(buf).getUint16(0);
  const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 2, n)));
  const blob = new Blob([new Uint8Array(buf, 2 + n)], {type: 'image/jpeg'});
  createImageBitmap(blob).then(bm => { const p = panes[head.cam]; if (!p) { bm.close(); return; }
    if (p.bitmap) p.bitmap.close(); p.bitmap = bm; p.head = head; invalidate('pane', head.cam); }).catch(() => null);
}

function connect(){
  ws = new WebSocket((location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws' + location.search);
  ws.binaryType = 'arraybuffer';
  ws.onopen = () => { $('conn').textContent = 'live'; };
  ws.onmessage = ev => {
    if (typeof ev.data !== 'string') { onImage(ev.data); return; }
    const m = JSON.parse(ev.data);
    if (m.type === 'hello') onHello(m);
    else if (m.type === 'state') {  // a refresh (a new forecast of the set drawn) redraws only the room
      state = m; recent.set(m.seq, m); if (recent.size > 40) recent.delete(recent.keys().next().value);
      invalidate(m.refresh ? 'room' : 'all'); }
  };
  ws.onclose = () => { $('conn').textContent = 'disconnected, retrying…'; setTimeout(connect, 1000); };
}

function drawPose(c, flat, parents, sx, sy, stroke, width, dots){
  const P = j => flat[2 * j] === null || flat[2 * j + 1] === null ? null : [flat[2 * j] * sx, flat[2 * j + 1] * sy];
  c.strokeStyle = stroke; c.lineWidth = width; c.lineCap = 'round';
  parents.forEach((p, j) => { if (p < 0) return; const u = P(j), w = P(p); if (!u || !w) return; c.beginPath(); c.moveTo(u[0], u[1]); c.lineTo(w[0], w[1]); c.stroke(); });
  if (dots) parents.forEach((_, j) => { const u = P(j); if (!u) return; c.fillStyle = dots; c.beginPath(); c.arc(u[0], u[1], 2.4, 0, 7); c.fill(); });
}

function drawPane(cam, p){
  const c = p.ctx, W = p.cv.width;
  if (!p.bitmap) { c.fillStyle = '#181d27'; c.fillRect(0, 0, W, p.cv.height); c.fillStyle = '#8a93a8'; c.fillText('waiting for a frame…', 10, 20); return; }
  const h = p.head, H = Math.round(W * h.h / h.w);
  if (p.cv.height !== H) p.cv.height = H;
  c.drawImage(p.bitmap, 0, 0, W, H);
  const st = recent.get(h.seq) || state, sx = W / h.src_wh[0], sy = H / h.src_wh[1], par = hello.parents;
  if (st) {
    c.globalAlpha = 0.8; for (const d of (st.det[cam] || [])) drawPose(c, d, par, sx, sy, '#ffd23f', 3, null); c.globalAlpha = 1;
    for (const [id, a] of (st.proj[cam] || [])) drawPose(c, a, par, sx, sy, '#ffffff', 1.1, color(id));
    if (hello.hand_parents) { const hp = hello.hand_parents; // hands: thinner, the same colours
      c.globalAlpha = 0.8; for (const d of ((st.hdet || {})[cam] || [])) drawPose(c, d, hp, sx, sy, '#ffd23f', 1.4, null); c.globalAlpha = 1;
      for (const [, a] of ((st.hproj || {})[cam] || [])) drawPose(c, a, hp, sx, sy, '#ffffff', 0.7, null); }
    const s = st.cameras[cam] || {};
    p.info.textContent = `${s.fps === null || s.fps === undefined ? '–' : s.fps} fps · dropped ${s.dropped || 0}`;
  }
  p.drawn = true;
}

function draw3d(){
  V3.background();
  if (hello && hello.rig) for (const k of hello.rig.cameras) V3.drawCamera(k);
  if (!state || !hello) return;
  const c = V3.ctx, J = hello.joint_names.length, fc = state.forecast;
  const nFc = fc && fc.on ? drawForecast(fc, new Set(state.tracks.map(t => t.id))) : 0;
  document.body.dataset.forecastDrawn = String(nFc);
  for (const t of state.tracks) {
    const pose = []; for (let j = 0; j < J; j++) pose.push([t.xyz[3 * j], t.xyz[3 * j + 1], t.xyz[3 * j + 2]]);
    const sd = t.std.filter(v => v !== null), std = sd.length ? sd.reduce((a, b) => a + b, 0) / sd.length : 0;
    V3.skeleton(pose, hello.parents, color(t.id), 3.2, std, 1, null);
    if (t.hands && hello.hand_parents) { const hp = []; for (let j = 0; j < hello.hand_parents.length; j++) hp.push([t.hands[3 * j], t.hands[3 * j + 1], t.hands[3 * j + 2]]);
      V3.skeleton(hp, hello.hand_parents, color(t.id), 1.3, 0, 1, null); }
    const top = pose[hello.joint_names.indexOf('nose')] || pose[0];
    const anchor = V3.fin(top) ? top : pose.find(V3.fin);
    if (anchor) { const q = V3.project([anchor[0], anchor[1], anchor[2] + 0.25]); if (q) {
      c.font = 'bold 12px system-ui,sans-serif'; const label = 'id ' + t.id, w = c.measureText(label).width + 10;
      c.fillStyle = color(t.id); c.fillRect(q[0] - w / 2, q[1] - 16, w, 18); c.fillStyle = '#fff'; c.fillText(label, q[0] - w / 2 + 5, q[1] - 3); } }
  }
  c.fillStyle = '#aab3c5'; c.font = '13px system-ui,sans-serif';
  c.fillText(`frame ${state.frame} · ${state.tracks.length ? state.tracks.length + ' people' : 'nobody in view'}`, 16, 26);
}

function median(a){ if (!a.length) return null; const s = a.slice().sort((x, y) => x - y); return s[s.length >> 1]; }

function render(){
  if (!hello) return;
  // a pane shows its image with the detections of the image's own frame set: redrawn when an image comes
  for (const cam of hello.cameras) if (!panes[cam].drawn) drawPane(cam, panes[cam]);
  draw3d();
  if (!state) return;
  const ids = state.tracks.map(t => t.id);
  setText($('people'), String(ids.length));
  if (ids.join() !== whoIds) { whoIds = ids.join();
    const who = $('who'); who.innerHTML = ''; if (!ids.length) who.textContent = '· nobody in view';
    for (const id of ids) { const s = document.createElement('span'); s.innerHTML = `<i class="swatch" style="background:${color(id)}"></i>`;
      s.appendChild(document.createTextNode('id ' + id)); who.appendChild(s); } }
  setText($('frame'), String(state.frame));
  setText($('sets'), state.live && state.live.processed !== undefined ? `${state.live.processed} · ${state.live.skipped} stale dropped` : '–');
  const jp = $('jumps'), jl = state.live && state.live.jumps_line;  // the clock jumped back: a new track segment
  jp.hidden = !jl; setText(jp, jl || '');
  setText($('loopLatency'), state.live && state.live.latency_ms !== null && state.live.latency_ms !== undefined ? state.live.latency_ms.toFixed(0) + ' ms' : '–');
  const fc = state.forecast;
  if (fc) {
    if (document.activeElement !== $('fcToggle')) $('fcToggle').checked = fc.on;
    setText($('fcCost'), fc.on ? `${fc.horizon_s} s · ${fc.ms.toFixed(1)} ms (${fc.ms_per_set.toFixed(1)} ms/set)` : 'off');
    $('fcCost').title = `model ${fc.model}; CPU of the last forecast, and per processed frame set`;
    document.body.dataset.forecastOn = fc.on ? 'on' : 'off';
  }
  setText($('viewNote'), `${state.view.clients} page(s) · ${state.view.dropped_updates} view updates dropped`);
  for (const cam of hello.cameras) { const s = state.cameras[cam] || {};
    [s.fps, s.frames, s.dropped, s.dropped_live].forEach((v, k) => setText(statCells[cam][k], v === null || v === undefined ? '–' : String(v))); }
  const errs = Object.entries((state.live && state.live.errors) || {});
  setText($('errors'), errs.length ? 'stage errors: ' + errs.map(([k, v]) => `${k}: ${v}`).join('; ') : '');
  // each frame set's first drawing is acknowledged (a refresh, a new forecast of a set already drawn, is not)
  if (state.seq !== acked && (!state.refresh || state.frame !== ackedFrame)) {
    acked = state.seq; ackedFrame = state.frame;
    const ms = Date.now() - state.t_capture_ms; lat.push(ms); if (lat.length > 60) lat.shift();
    const m = median(lat); setText($('latency'), m.toFixed(0) + ' ms');
    document.body.dataset.latencyMs = String(m.toFixed(1));
    if (ws && ws.readyState === 1) ws.send(JSON.stringify({ack: state.seq, t_capture_ms: state.t_capture_ms, t_sent_ms: state.t_sent_ms}));
  }
  document.body.dataset.people = String(ids.length);
  document.body.dataset.nobody = ids.length ? '' : 'nobody in view';
  document.body.dataset.panesDrawn = String(hello.cameras.filter(c => panes[c].bitmap).length);
  document.body.dataset.frame = String(state.frame);
}

function tick(){
  scheduled = false;
  if (hello) for (const cam of need.panes) drawPane(cam, panes[cam]);  // new images (render draws no drawn pane)
  if (need.all) render(); else if (need.room) draw3d();
  need.all = need.room = false; need.panes.clear();
}
connect();
})();
