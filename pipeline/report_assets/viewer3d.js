// The room in 3D on a 2D canvas: an orbit camera looking at the people (z up), the floor grid, skeletons
// with their uncertainty halo and floor shadow, the cameras as frusta. Shared by the session report
// (report.js) and the live view (pipeline/liveview/live.js); no library, no network.
window.RoomView3D = function(canvas){
  'use strict';
  const ctx = canvas.getContext('2d');
  const view = {yaw: -0.9, pitch: 0.42, zoom: 1.0, center: [0, 0, 0.9], radius: 3};
  const fin = p => p && p[0] !== null && p[1] !== null && p[2] !== null;
  function fit(pts){ // centre and distance that show the points (floor extent); none: keep the view
    if (!pts.length) return;
    const lo = [0, 1].map(a => Math.min(...pts.map(p => p[a]))), hi = [0, 1].map(a => Math.max(...pts.map(p => p[a])));
    view.center = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.9];
    view.radius = Math.max(1.3, 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1]) + 0.7); }
  function project(p){ // orbit camera looking at `center`, z up -> [x px, y px, depth, px per metre]
    const c = view.center, x = p[0] - c[0], y = p[1] - c[1], z = p[2] - c[2];
    const cy = Math.cos(view.yaw), sy = Math.sin(view.yaw), cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    const xr = cy * x - sy * y, yr = sy * x + cy * y;
    const depth = cp * yr + sp * z, up = -sp * yr + cp * z;
    const dist = view.radius * 2.1 / view.zoom, f = canvas.height * 0.95;
    const d = dist + depth; if (d < 0.05) return null;
    return [canvas.width / 2 + f * xr / d, canvas.height * 0.56 - f * up / d, d, f / d]; }
  function line(a, b, col, w, dash){ const p = project(a), q = project(b); if (!p || !q) return;
    ctx.strokeStyle = col; ctx.lineWidth = w; if (dash) ctx.setLineDash(dash); ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]); ctx.stroke(); if (dash) ctx.setLineDash([]); }
  function floorOf(p){ return [p[0], p[1], 0]; }
  function skeleton(pose, parents, col, w, std_m, alpha, box){ // pose: [[x,y,z]|nulls], std_m: halo radius (m)
    if (!pose) return; ctx.globalAlpha = alpha === undefined ? 1 : alpha; ctx.lineCap = 'round';
    ctx.globalAlpha *= 0.35;
    parents.forEach((p, j) => { if (p < 0 || !fin(pose[j]) || !fin(pose[p])) return; line(floorOf(pose[j]), floorOf(pose[p]), '#000', w + 2); });
    ctx.globalAlpha = alpha === undefined ? 1 : alpha;
    parents.forEach((p, j) => { if (p < 0 || !fin(pose[j]) || !fin(pose[p])) return; line(pose[j], pose[p], col, w); });
    pose.forEach(j => { if (!fin(j)) return; const q = project(j); if (!q) return;
      if (box) { box[0] = Math.min(box[0], q[0]); box[1] = Math.min(box[1], q[1]); box[2] = Math.max(box[2], q[0]); box[3] = Math.max(box[3], q[1]); }
      if (std_m) { const r = Math.min(40, std_m * q[3]); ctx.fillStyle = col; ctx.globalAlpha *= 0.18; ctx.beginPath(); ctx.arc(q[0], q[1], Math.max(2, r), 0, 7); ctx.fill(); ctx.globalAlpha = alpha === undefined ? 1 : alpha; }
      ctx.fillStyle = col; ctx.beginPath(); ctx.arc(q[0], q[1], Math.max(1.5, w * 0.8), 0, 7); ctx.fill(); });
    ctx.globalAlpha = 1; }
  function drawCamera(k){ const c0 = k.center_m, a = k.axis, r = k.right || [0, 0, 0], u = k.up || [0, 0, 1];
    const tw = Math.tan((k.fov_deg ? k.fov_deg[0] : 60) * Math.PI / 360) * 0.35, th = Math.tan((k.fov_deg ? k.fov_deg[1] : 40) * Math.PI / 360) * 0.35;
    const corner = (sx, sy) => [0, 1, 2].map(i => c0[i] + 0.35 * a[i] + sx * tw * r[i] + sy * th * u[i]);
    const cs = [corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, 1)];
    for (let i = 0; i < 4; i++) { line(c0, cs[i], '#8f9bb3', 1.2); line(cs[i], cs[(i + 1) % 4], '#8f9bb3', 1.2); }
    line(cs[2], cs[3], '#c9d2e6', 2.4); }
  function background(){ // dark room, 1 m floor grid around the centre
    ctx.fillStyle = '#10141c'; ctx.fillRect(0, 0, canvas.width, canvas.height);
    const c = view.center, g = Math.ceil(view.radius * 1.6);
    for (let i = -g; i <= g; i++) { const cx = Math.round(c[0]) + i, cy = Math.round(c[1]) + i;
      line([cx, Math.round(c[1]) - g, 0], [cx, Math.round(c[1]) + g, 0], '#222a38', 1);
      line([Math.round(c[0]) - g, cy, 0], [Math.round(c[0]) + g, cy, 0], '#222a38', 1); } }
  function orbit(redraw){ // drag to orbit, wheel to zoom
    let drag = null;
    canvas.addEventListener('mousedown', e => drag = [e.clientX, e.clientY]);
    window.addEventListener('mouseup', () => drag = null);
    window.addEventListener('mousemove', e => { if (!drag) return; view.yaw += (e.clientX - drag[0]) * 0.01;
      view.pitch = Math.max(-0.1, Math.min(1.5, view.pitch + (e.clientY - drag[1]) * 0.01)); drag = [e.clientX, e.clientY]; redraw(); });
    canvas.addEventListener('wheel', e => { e.preventDefault(); view.zoom *= e.deltaY < 0 ? 1.1 : 0.9; redraw(); }, {passive: false}); }
  return {ctx, canvas, view, fin, fit, project, line, floorOf, skeleton, drawCamera, background, orbit};
};
