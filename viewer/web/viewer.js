// haptree viewer page: NGL scene from /scene.pdb, live frames over the WebSocket (one binary message each:
// JSON overlays + Float32 positions), the mouse as this tab's haptic device. Test hooks:
// document.body.dataset.frames (frames drawn), .forceN (last |f| shown for this tab's user, N), .ready,
// .user, .grab, .cursors (device cursors drawn), .wsBytes / .wsFrames (frame bytes and messages received).
/* global NGL */
const USER_COLOURS = ['#d62728', '#1f77b4', '#2ca02c', '#9467bd', '#e377c2', '#17becf', '#bcbd22', '#8c564b'];
const ACTIVE = 0xff8c00, RIGID = 0x8fa3b8;
const REACH_MAX = 12.0;   // display units (Å): the largest reach sphere drawn
const ARROW_PER_N = 8.0;   // display units (Å) per newton at the device (shown in the HUD)

const body = document.body;
window.addEventListener('error', (e) => { body.dataset.error = String(e.message || e); });
const stage = new NGL.Stage('stage', { backgroundColor: 'white', tooltip: false, quality: 'low', sampleLevel: 0 });
window.addEventListener('resize', () => stage.handleResize());

let hello = null, comp = null, ballRepr = null, cartoonRepr = null, overlay = null;
let pending = null, framesRendered = 0, lastPos = null;
let activeOfPoint = null, maskDirty = false, lastMaskUpdate = 0;
let grab = null;
let tPos = 0, tOv = 0, tFrame = 0;
const recent = [];
// Per frame the page moves the ball-and-stick buffers itself (direct: sphere centres and bond ends copied
// from the frame through index maps, no NGL proxies); the cartoon (a spline through the backbone, the
// costly rebuild) follows at a lower rate: at most once per CARTOON_MIN_MS, and never more than ~10 % of
// the page's time (interval >= 10 x its last cost).
const CARTOON_MIN_MS = 250, HUD_MIN_MS = 200;
let direct = null, lastCartoon = 0, cartoonMs = 0, lastHud = 0, cartoonUpdates = 0;
const fpsTimes = [];

const scheme = NGL.ColormakerRegistry.addScheme(function () {
  this.atomColor = (atom) => (activeOfPoint && activeOfPoint[atom.index] ? ACTIVE : RIGID);
}, 'haptree-active');

// The token: in the URL once (the server then sets a cookie, so a reload without it works); taken off the
// address bar so it is not shared by a screenshot or a copied link, and given to the WebSocket too.
const token = new URLSearchParams(location.search).get('token');
if (token) history.replaceState(null, '', location.pathname);
const ws = new WebSocket(`${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}/ws` +
  (token ? `?token=${encodeURIComponent(token)}` : ''));
ws.binaryType = 'arraybuffer';
ws.onclose = () => { setStatus('disconnected (session over?)'); };
let wsBytes = 0, wsFrames = 0, wsReceived = 0, lateFrames = 0;   // lateFrames: read > 2 s after they were built
const decoder = new TextDecoder();
ws.onmessage = (ev) => {
  if (typeof ev.data === 'string') {   // the hello
    let m;
    try { m = JSON.parse(ev.data); } catch (e) { return; }
    if (m.t === 'hello') onHello(m);
    return;
  }
  // The viewer sends a few frames ahead of these acknowledgements, no more: a page that falls behind
  // (a slow machine, a busy tab) gets the newest state, not a queue of old ones.
  wsReceived += 1;
  if (ws.readyState === WebSocket.OPEN) ws.send(`{"t":"ack","n":${wsReceived}}`);
  body.dataset.wsReceived = String(wsReceived);
  // a frame: "HTF1", uint32 JSON length, JSON, Float32 x y z per point (absent: the scene did not move)
  const buf = ev.data, dv = new DataView(buf);
  if (buf.byteLength < 8 || dv.getUint32(0, false) !== 0x48544631) return;
  const n = dv.getUint32(4, true);
  if (8 + n > buf.byteLength) return;
  let f;
  try { f = JSON.parse(decoder.decode(new Uint8Array(buf, 8, n))); } catch (e) { return; }
  wsBytes += buf.byteLength; wsFrames += 1;
  // how long after the viewer built it this frame is read (meaningful when the page runs on the viewer's host)
  const ageMs = typeof f.utime === 'number' ? Date.now() - f.utime / 1000 : NaN;
  if (ageMs > 2000) lateFrames += 1;
  body.dataset.frameAgeMs = Number.isFinite(ageMs) ? ageMs.toFixed(0) : '';
  body.dataset.lateFrames = String(lateFrames);
  const pos = buf.byteLength > 8 + n ? new Float32Array(buf, 8 + n) : null;
  // at most one draw per animation frame: a newer frame replaces a pending one, its positions kept
  pending = { pos: pos || (pending && pending.pos), frame: f, active: f.active !== undefined ? f.active : pending && pending.active };
};

function setStatus(s) { document.getElementById('status').textContent = s; }

async function onHello(m) {
  hello = m;
  body.dataset.user = String(m.user);
  body.dataset.role = m.role || '';
  setStatus(m.user >= 0 ? `you are user ${m.user} — ${m.scene}`
    : m.role === 'watch' ? `watching (this link may not pull) — ${m.scene}`
      : `spectator (all ${m.users} users taken) — ${m.scene}`);
  comp = await stage.loadFile('/scene.pdb', { ext: 'pdb', defaultRepresentation: false });
  if (m.kind === 'molecule') {
    cartoonRepr = comp.addRepresentation('cartoon', { color: 'sstruc', opacity: 0.9 });
    ballRepr = comp.addRepresentation('ball+stick', { color: scheme, sele: 'not hydrogen', aspectRatio: 1.5, radiusScale: 0.6 });
  } else {
    // bodies: a sphere per body origin, a stick per joint; size from the typical joint spacing
    const s = comp.structure, a = s.getAtomProxy(), b = s.getAtomProxy(), d = [];
    s.eachBond((bond) => { a.index = bond.atomIndex1; b.index = bond.atomIndex2; d.push(a.distanceTo(b)); });
    d.sort((x, y) => x - y);
    const spacing = d.length ? d[Math.floor(d.length / 2)] : 1;
    // with the robot's own visuals the skeleton stays, thin, inside them
    ballRepr = comp.addRepresentation('ball+stick', { color: scheme, radiusType: 'size',
      radiusSize: (m.meshes ? 0.06 : 0.3) * spacing, aspectRatio: 2 });
    if (m.meshes) {
      await loadMeshes();
      if (lastPos) moveMeshes(lastPos, lastPos.subarray(3 * m.points));   // a frame came while they loaded
    }
  }
  activeOfPoint = new Uint8Array(m.points);
  makeOverlay(m.users);
  if (m.meshes) {   // a robot (URDF: z up): seen from the side, a little from above, not down its z axis
    // Its meshes reach past the box of the body origins NGL clips and fogs by: no fog, a farther clip.
    stage.setParameters({ clipFar: 400, fogNear: 100, fogFar: 100 });
    const vc = stage.viewerControls;
    vc.rotate(new NGL.Quaternion().setFromAxisAngle(new NGL.Vector3(1, 0, 0), Math.PI / 2));
    vc.rotate(new NGL.Quaternion().setFromAxisAngle(new NGL.Vector3(0, 1, 0), -0.6));
    vc.rotate(new NGL.Quaternion().setFromAxisAngle(new NGL.Vector3(1, 0, 0), -0.35));
  }
  comp.autoView();
  body.dataset.ready = '1';
}

// A robot's visuals (/scene.meshes, the frame's layout: JSON [{body, tris}], then per body float32
// positions in the body frame, normals, colours; 9 floats per triangle each): one NGL mesh per body, named
// "body K" (a click on it grabs body K), moved per frame by the body's pose (frame: the points, which are
// the body origins, then x y z w per body).
let meshBodies = [], meshesFramed = false;
async function loadMeshes() {
  const buf = await (await fetch('/scene.meshes', { credentials: 'same-origin' })).arrayBuffer();
  const dv = new DataView(buf);
  if (buf.byteLength < 8 || dv.getUint32(0, false) !== 0x48544631) throw new Error('scene.meshes: not a mesh list');
  const n = dv.getUint32(4, true);
  const list = JSON.parse(decoder.decode(new Uint8Array(buf, 8, n)));
  let at = 8 + n;
  const shape = new NGL.Shape('robot');
  const take = (k) => { const a = new Float32Array(buf, at, k); at += 4 * k; return a; };
  for (const e of list) {
    const k = 9 * e.tris, local = take(k), localN = take(k), col = take(k);
    shape.addMesh(local.slice(), col.slice(), undefined, localN.slice(), `body ${e.body}`);
    meshBodies.push({ body: e.body, buffer: shape.bufferList[shape.bufferList.length - 1], local, localN,
      out: new Float32Array(k), outN: new Float32Array(k) });
  }
  stage.addComponentFromObject(shape).addRepresentation('buffer');
  body.dataset.meshBodies = String(meshBodies.length);
}
function moveMeshes(pos, quat) {
  for (const m of meshBodies) {
    const k = m.body, x = quat[4 * k], y = quat[4 * k + 1], z = quat[4 * k + 2], w = quat[4 * k + 3];
    const r00 = 1 - 2 * (y * y + z * z), r01 = 2 * (x * y - z * w), r02 = 2 * (x * z + y * w);
    const r10 = 2 * (x * y + z * w), r11 = 1 - 2 * (x * x + z * z), r12 = 2 * (y * z - x * w);
    const r20 = 2 * (x * z - y * w), r21 = 2 * (y * z + x * w), r22 = 1 - 2 * (x * x + y * y);
    const px = pos[3 * k], py = pos[3 * k + 1], pz = pos[3 * k + 2];
    const L = m.local, N = m.localN, P = m.out, Q = m.outN;
    for (let i = 0; i < L.length; i += 3) {
      const a = L[i], b = L[i + 1], c = L[i + 2], na = N[i], nb = N[i + 1], nc = N[i + 2];
      P[i] = px + r00 * a + r01 * b + r02 * c; P[i + 1] = py + r10 * a + r11 * b + r12 * c; P[i + 2] = pz + r20 * a + r21 * b + r22 * c;
      Q[i] = r00 * na + r01 * nb + r02 * nc; Q[i + 1] = r10 * na + r11 * nb + r12 * nc; Q[i + 2] = r20 * na + r21 * nb + r22 * nc;
    }
    m.buffer.setAttributes({ position: P, normal: Q });
  }
  if (!meshesFramed && meshBodies.length) {   // the first placed pose: frame the meshes, not only the origins
    meshesFramed = true;
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const m of meshBodies)
      for (let i = 0; i < m.out.length; ++i) lo[i % 3] = Math.min(lo[i % 3], m.out[i]), hi[i % 3] = Math.max(hi[i % 3], m.out[i]);
    const box = new NGL.Box3(new NGL.Vector3(...lo), new NGL.Vector3(...hi));
    stage.animationControls.zoomMove(box.getCenter(new NGL.Vector3()), stage.getZoomForBox(box), 0);
  }
}

// Overlays: per user the grabbed point, the device cursor (proxy point) with its reach (a translucent
// sphere through the body origin a press would grab), the spring and the force arrow. The buffers are made
// once and only their attributes change per frame (no new shaders, no new component); hidden primitives
// get radius 0.
let spheres = null, springs = null, arrows = null, reaches = null;
function makeOverlay(n) {
  const z = (k) => new Float32Array(k);
  const col = z(3 * n);
  for (let u = 0; u < n; ++u) {
    const c = new NGL.Color(USER_COLOURS[u % USER_COLOURS.length]);
    col.set([c.r, c.g, c.b], 3 * u);
  }
  const col2 = z(6 * n);
  for (let u = 0; u < n; ++u) { col2.set(col.subarray(3 * u, 3 * u + 3), 6 * u); col2.set(col.subarray(3 * u, 3 * u + 3).map((x) => 0.55 + 0.45 * x), 6 * u + 3); }
  spheres = new NGL.SphereBuffer({ position: z(6 * n), color: col2, radius: z(2 * n) });
  springs = new NGL.CylinderBuffer({ position1: z(3 * n), position2: z(3 * n), color: col, color2: col, radius: z(n) });
  // the force arrow in a darker shade: it lies along the spring (f ∝ stretch) but is wider
  arrows = new NGL.ArrowBuffer({ position1: z(3 * n), position2: z(3 * n), color: col.map((x) => 0.55 * x), radius: z(n) });
  const shape = new NGL.Shape('overlay');
  shape.addBuffer(spheres); shape.addBuffer(springs); shape.addBuffer(arrows);
  overlay = stage.addComponentFromObject(shape);
  overlay.addRepresentation('buffer');
  reaches = new NGL.SphereBuffer({ position: z(3 * n), color: col.map((x) => 0.6 + 0.4 * x), radius: z(n) });
  const rs = new NGL.Shape('reach');
  rs.addBuffer(reaches);
  stage.addComponentFromObject(rs).addRepresentation('buffer', { opacity: 0.18, depthWrite: false });
}
function drawOverlay(f) {
  const n = hello.users;
  const sp = new Float32Array(6 * n), sr = new Float32Array(2 * n), rp = new Float32Array(3 * n), rr = new Float32Array(n);
  const a1 = new Float32Array(3 * n), a2 = new Float32Array(3 * n), ar = new Float32Array(n), cr = new Float32Array(n);
  let cursors = 0, reachShown = 0;
  for (const u of f.users) {
    if (u.id >= n) continue;
    if (u.grab) { sp.set(u.grab, 6 * u.id); sr[2 * u.id] = 1.8; }
    if (u.proxy) {   // every user's device, any kind, grabbing or not
      sp.set(u.proxy, 6 * u.id + 3); sr[2 * u.id + 1] = 1.2;
      cursors += 1;
      if (u.grab) { a1.set(u.grab, 3 * u.id); a2.set(u.proxy, 3 * u.id); cr[u.id] = 0.2; }
      // near the scene only (the display spans ~80 units): a large translucent sphere costs a software
      // rasteriser a full-screen blend and says nothing about aiming
      else if (u.reach > 0 && u.reach <= REACH_MAX) { rp.set(u.proxy, 3 * u.id); rr[u.id] = u.reach; reachShown += 1; }
    }
  }
  reaches.setAttributes({ position: rp, radius: rr });
  body.dataset.cursors = String(cursors);
  body.dataset.reaches = String(reachShown);
  springs.setAttributes({ position1: a1.slice(), position2: a2.slice(), radius: cr });
  a1.fill(0); a2.fill(0);
  for (const u of f.users) {
    if (u.id >= n || !u.proxy || !u.grab || !(u.fn > 1e-4)) continue;
    const L = u.fn * ARROW_PER_N;
    a1.set(u.proxy, 3 * u.id);
    a2.set(u.proxy.map((x, k) => x + (u.f[k] / u.fn) * L), 3 * u.id);
    ar[u.id] = 1.0;
  }
  spheres.setAttributes({ position: sp, radius: sr });
  arrows.setAttributes({ position1: a1, position2: a2, radius: ar });
}

// The coupler's flags of the same FEEDBACK message as |f|: the watchdog gain is below 1 either because
// the inputs are stale (the gain falls to 0 within 5 ms) or because they are fresh again and the gain
// climbs back over 100 ms; the force is then at most gain x the clamp.
function watchdogState(u) {
  if (!u.watchdog) return 'ok';
  return u.stale ? 'stale' : 'ramp-in';
}

function hud(f, fps) {
  const rows = [
    ['sim step', `${f.step_ms.toFixed(2)} ms (${Math.round(f.sim_rate)} steps/s)`],
    ['active / total DOF', `${f.active_dofs} / ${f.dof}`],
    ['sim time', `${f.sim_time.toFixed(3)} · scene state ${f.scene_age_ms.toFixed(0)} ms old`],
    ['frames/s', `${fps.toFixed(1)} · arrow ${ARROW_PER_N} Å per N`],
  ];
  let html = rows.map(([k, v]) => `<tr><td class="k">${k}</td><td colspan="2">${v}</td></tr>`).join('');
  for (const u of f.users) {
    const col = USER_COLOURS[u.id % USER_COLOURS.length];
    const frac = u.max_force_n > 0 ? Math.min(1, u.fn / u.max_force_n) : 0;
    const ws = watchdogState(u);
    const wd = ws === 'ok' ? 'ok' : ws === 'stale' ? '<b style="color:#c00">WATCHDOG: stale, force ramping to 0</b>'
      : '<b style="color:#b60">watchdog: fresh again, force ramping in</b>';
    html += `<tr><td class="k" style="color:${col}">user ${u.id}${u.id === f.you ? ' (you)' : ''}</td>` +
      `<td>|f| ${u.fn.toFixed(3)} N${u.clamped ? ' (clamped)' : ''}</td>` +
      `<td><span class="bar"><i style="width:${(100 * frac).toFixed(0)}%;background:${col}"></i></span></td></tr>` +
      `<tr><td></td><td colspan="2">coupler ${(u.rate_hz / 1000).toFixed(1)} kHz · ` +
      `${u.age_ms >= 0 ? `snapshot age ${u.age_ms.toFixed(1)} ms` : 'no grab'} · ${wd}` +
      `${u.body ? ' · body ' + u.body : ''}</td></tr>`;
  }
  document.getElementById('hudtab').innerHTML = html;
}

// Index maps from the frame's points to the ball-and-stick buffers (sphere k = k-th selected atom, cylinder
// k = k-th bond of the selection, NGL's order), checked once against the buffers NGL built: if they do not
// match (another NGL, mesh instead of impostor buffers) the page falls back to NGL's own update.
function makeDirect() {
  const data = ballRepr.repr.dataList && ballRepr.repr.dataList[0];
  if (!data || !data.bufferList || !data.bufferList.length) return null;   // not built yet: next frame
  if (data.bufferList.length !== 2) return `${data.bufferList.length} buffers`;
  const isCyl = (b) => !!(b.geometry && b.geometry.attributes.position1);   // NGL lists the bonds first
  const cb = data.bufferList.find(isCyl), sb = data.bufferList.find((b) => !isCyl(b));
  if (!cb || !sb) return 'no sphere and cylinder buffers';
  // NGL's own order: ask the representation for its atom and bond data with every atom placed at x =
  // its index (exact in float32 below 2^24), then put the coordinates back.
  const repr = ballRepr.repr, st = comp.structure.atomStore, n = comp.structure.atomCount;
  const keep = [st.x.slice(0, n), st.y.slice(0, n), st.z.slice(0, n)];
  for (let i = 0; i < n; ++i) { st.x[i] = i; st.y[i] = 0; st.z[i] = 0; }
  let ad, bd;
  try {
    ad = repr.getAtomData(data.sview, { position: true });
    bd = repr.getBondData(data.sview, { position: true });
  } finally {
    st.x.set(keep[0]); st.y.set(keep[1]); st.z.set(keep[2]);
  }
  const every3 = (a) => Int32Array.from({ length: a.length / 3 }, (_, k) => a[3 * k]);
  const ai = every3(ad.position), i1 = every3(bd.position1), i2 = every3(bd.position2);
  const d = { sb, cb, ai, i1, i2, sp: new Float32Array(3 * ai.length), p1: new Float32Array(3 * i1.length),
    p2: new Float32Array(3 * i2.length) };
  // the check: NGL's impostor buffers hold each centre mappingSize times, the first copy at 3*k*mappingSize
  const bad = (buf, idx, name) => {
    const a = buf.geometry && buf.geometry.attributes[name], ms = buf.mappingSize;
    if (!a || !ms || buf.size !== idx.length) return `${name}: ${!a ? 'no attribute' : !ms ? 'not mapped' : `${buf.size} != ${idx.length}`}`;
    const x = comp.structure.atomStore;
    for (let k = 0; k < idx.length; k += Math.max(1, idx.length >> 6)) {
      const o = 3 * k * ms, i = idx[k];
      if (Math.abs(a.array[o] - x.x[i]) > 1e-3 || Math.abs(a.array[o + 1] - x.y[i]) > 1e-3 ||
          Math.abs(a.array[o + 2] - x.z[i]) > 1e-3) return `${name}: item ${k} is not atom ${i}`;
    }
    return '';
  };
  const why = bad(sb, ai, 'position') || bad(cb, i1, 'position1') || bad(cb, i2, 'position2');
  if (!why) direct = d;
  return why;
}
// For tests: why the direct update is off ('' = on).
window.haptreeDirectCheck = () => (ballRepr ? makeDirect() ?? 'not built' : 'no ball+stick');
function gather(out, idx, pos) {
  for (let k = 0; k < idx.length; ++k) {
    const s = 3 * idx[k], o = 3 * k;
    out[o] = pos[s]; out[o + 1] = pos[s + 1]; out[o + 2] = pos[s + 2];
  }
}
function movePositions(pos, now) {
  if (direct === null && ballRepr) {   // before the atoms move: the buffers must still match them
    const why = makeDirect();
    if (why) { direct = false; body.dataset.directWhy = why; }   // null: NGL still building, try again
  }
  comp.structure.updatePosition(pos, false);   // the atoms themselves: picking, the grab, the cartoon
  if (direct) {
    gather(direct.sp, direct.ai, pos);
    gather(direct.p1, direct.i1, pos);
    gather(direct.p2, direct.i2, pos);
    direct.sb.setAttributes({ position: direct.sp });
    direct.cb.setAttributes({ position1: direct.p1, position2: direct.p2 });
  } else if (ballRepr) {   // also while NGL is still building: the update then waits for the build
    ballRepr.update({ position: true });
  }
  if (cartoonRepr && now - lastCartoon >= Math.max(CARTOON_MIN_MS, 10 * cartoonMs)) {
    const t0 = performance.now();
    cartoonRepr.update({ position: true });
    cartoonMs = performance.now() - t0;
    lastCartoon = now;
    cartoonUpdates += 1;
    body.dataset.msCartoon = cartoonMs.toFixed(2);
    body.dataset.cartoonUpdates = String(cartoonUpdates);
  }
  body.dataset.direct = direct ? '1' : '0';
}

function render(now) {
  requestAnimationFrame(render);
  if (!comp || !pending || !reaches) return;   // reaches: the overlays are made (after a robot's meshes)
  const now0 = performance.now();
  const { pos, frame: f, active } = pending;
  pending = null;
  if (pos) lastPos = pos;
  if (pos && pos.length >= 3 * hello.points) {
    movePositions(pos.subarray(0, 3 * hello.points), now);
    if (hello.quats && meshBodies.length && pos.length === 3 * hello.points + 4 * (hello.bodies + 1))
      moveMeshes(pos, pos.subarray(3 * hello.points));
  }
  if (typeof active === 'string') {   // per body, sent when the active region changed
    const pb = hello.point_body;
    for (let i = 0; i < pb.length; ++i) activeOfPoint[i] = active.charCodeAt(pb[i]) === 49 ? 1 : 0;
    maskDirty = true;
  }
  if (maskDirty && now - lastMaskUpdate > 250) {   // recolouring costs a buffer update: at most 4 per second
    ballRepr.update({ color: true });
    maskDirty = false;
    lastMaskUpdate = now;
  }
  const t1 = performance.now();
  drawOverlay(f);
  stage.viewer.requestRender();   // one draw per frame that arrived, none otherwise
  const t2 = performance.now();
  fpsTimes.push(now);
  while (fpsTimes.length && now - fpsTimes[0] > 1000) fpsTimes.shift();
  framesRendered += 1;
  body.dataset.frames = String(framesRendered);
  body.dataset.wsBytes = String(wsBytes);
  body.dataset.wsFrames = String(wsFrames);
  const me = f.users.find((u) => u.id === f.you);
  body.dataset.forceN = me ? me.fn.toFixed(4) : '0';
  body.dataset.grab = me && me.grab ? '1' : '0';
  body.dataset.grabBody = me && me.body ? String(me.body) : '0';
  body.dataset.clamped = me && me.clamped ? '1' : '0';
  body.dataset.watchdog = me ? watchdogState(me) : '';
  if (now - lastHud >= HUD_MIN_MS) {   // the HUD is DOM layout: a few times a second is enough to read
    hud(f, fpsTimes.length);
    lastHud = now;
  }
  const t3 = performance.now();
  tPos += t1 - now0; tOv += t2 - t1; tFrame += t3 - now0;
  recent.push(t1 - now0);   // steady state: the median of the last 64 frames (the mean keeps the start-up)
  if (recent.length > 64) recent.shift();
  body.dataset.msPosMedian = [...recent].sort((a, b) => a - b)[recent.length >> 1].toFixed(2);
  body.dataset.msPos = (tPos / framesRendered).toFixed(2);
  body.dataset.msOverlay = (tOv / framesRendered).toFixed(2);
  body.dataset.msFrame = (tFrame / framesRendered).toFixed(2);
}
requestAnimationFrame(render);

// ---- the mouse as a device -------------------------------------------------------------------------
function canvasXY(e) {
  const r = stage.viewer.renderer.domElement.getBoundingClientRect();
  return [e.clientX - r.left, r.height - (e.clientY - r.top), r];
}
// Rotation taking a vector in the camera's plane (x right, y up, z into the screen) to model coordinates,
// as NGL pans an atom (TrackballControls._transformPanVector), and the canvas pixel size at the point.
function panFrame(p) {
  const v = stage.viewer;
  const cam = new NGL.Matrix4().extractRotation(v.camera.matrixWorld).multiply(new NGL.Matrix4().makeRotationY(Math.PI));
  const m = new NGL.Matrix4().extractRotation(comp.transform).premultiply(v.rotationGroup.matrix).invert().multiply(cam);
  const pv = p.clone().add(v.translationGroup.position).applyMatrix4(v.rotationGroup.matrix);
  return { m, scale: stage.viewerControls.getCanvasScaleFactor(pv.z) };
}
let sent = 0;
function send(o) {
  if (ws.readyState !== WebSocket.OPEN) return;
  ws.send(JSON.stringify(o));
  body.dataset.sent = String(++sent);
}
function finite(p) { return Number.isFinite(p.x) && Number.isFinite(p.y) && Number.isFinite(p.z); }

window.addEventListener('mousedown', (e) => {
  if (e.button !== 0 || !comp || !hello || hello.user < 0) return;
  const [x, y, r] = canvasXY(e);
  if (x < 0 || y < 0 || x > r.width || y > r.height) return;
  const pp = stage.pickingControls.pick(x, y);
  // an atom, the nearer atom of a picked bond, or a robot's mesh (its body's point: body scenes have one
  // point per body); anything else (empty space, an overlay): NGL rotates
  const mesh = pp && pp.mesh && /^body (\d+)$/.exec(pp.mesh.name || '');
  const atom = mesh ? comp.structure.getAtomProxy(Number(mesh[1]))
    : pp ? (pp.atom || (pp.bond ? pp.closestBondAtom : undefined)) : undefined;
  body.dataset.pick = mesh ? `mesh body ${mesh[1]}` : atom ? `atom ${atom.index}` : pp ? pp.type : 'nothing';
  if (!atom) return;
  e.stopPropagation();
  e.preventDefault();
  const p = new NGL.Vector3(); atom.positionToVector3(p);
  grab = { i: atom.index, p, x: e.clientX, y: e.clientY };
  send({ t: 'down', i: grab.i, p: [p.x, p.y, p.z] });
}, true);
window.addEventListener('mousemove', (e) => {
  if (!grab) return;
  e.stopPropagation();
  const { m, scale } = panFrame(grab.p);
  const d = new NGL.Vector3((e.clientX - grab.x) * scale, -(e.clientY - grab.y) * scale, 0).applyMatrix4(m);
  grab.x = e.clientX; grab.y = e.clientY;
  const p = grab.p.clone().add(d);
  if (!finite(p)) return;   // never forward a NaN pointer
  grab.p = p;
  send({ t: 'move', p: [p.x, p.y, p.z] });
}, true);
window.addEventListener('mouseup', (e) => {
  if (!grab) return;
  e.stopPropagation();
  grab = null;
  send({ t: 'up' });
}, true);
window.addEventListener('wheel', (e) => {
  if (!grab) return;
  e.stopPropagation();
  e.preventDefault();
  const { m, scale } = panFrame(grab.p);
  const d = new NGL.Vector3(0, 0, e.deltaY * 0.25 * scale).applyMatrix4(m);
  const p = grab.p.clone().add(d);
  if (!finite(p)) return;
  grab.p = p;
  send({ t: 'move', p: [p.x, p.y, p.z] });
}, { capture: true, passive: false });
window.addEventListener('blur', () => { if (grab) { grab = null; send({ t: 'up' }); } });

// For tests: client coordinates of the centre of body k's mesh as drawn now (null: no mesh), and of the
// centres of n of its triangles.
function onScreen(c) {
  const s = stage.viewerControls.getPositionOnCanvas(c);
  const r = stage.viewer.renderer.domElement.getBoundingClientRect();
  return { x: r.left + s.x, y: r.top + (r.height - s.y) };
}
window.haptreeMeshOnScreen = (k) => {
  const m = meshBodies.find((e) => e.body === k);
  if (!m) return null;
  const c = new NGL.Vector3();
  for (let i = 0; i < m.out.length; i += 3) c.x += m.out[i], c.y += m.out[i + 1], c.z += m.out[i + 2];
  return onScreen(c.multiplyScalar(3 / m.out.length));
};
window.haptreeMeshTrianglesOnScreen = (k, n) => {
  const m = meshBodies.find((e) => e.body === k);
  if (!m) return [];
  const tris = m.out.length / 9, out = [];
  for (let t = 0; t < tris; t += Math.max(1, Math.floor(tris / n))) {
    const o = 9 * t, P = m.out;
    out.push(onScreen(new NGL.Vector3((P[o] + P[o + 3] + P[o + 6]) / 3, (P[o + 1] + P[o + 4] + P[o + 7]) / 3,
      (P[o + 2] + P[o + 5] + P[o + 8]) / 3)));
  }
  return out;
};

// For tests and scripts: canvas-relative client coordinates of display point i.
window.haptreePointOnScreen = (i) => {
  const a = comp.structure.getAtomProxy(i), p = new NGL.Vector3();
  a.positionToVector3(p);
  const c = stage.viewerControls.getPositionOnCanvas(p);
  const r = stage.viewer.renderer.domElement.getBoundingClientRect();
  return { x: r.left + c.x, y: r.top + (r.height - c.y) };
};

// For the benchmark (tests/browser/viewer_fps.py): ms per draw of the current scene, drawn n times and
// waited for (a 1-pixel read makes the GL work finish), with all representations, without the cartoon,
// without ball-and-stick, and with neither: where SwiftShader's time goes.
window.haptreeRasterMs = (n) => {
  const v = stage.viewer, gl = v.renderer.getContext(), px = new Uint8Array(4);
  const time = () => {
    v.render(); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);   // warm
    const t0 = performance.now();
    for (let k = 0; k < n; ++k) { v.render(); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px); }
    return (performance.now() - t0) / n;
  };
  const out = { all: time() };
  if (cartoonRepr) { cartoonRepr.setVisibility(false); out.no_cartoon = time(); cartoonRepr.setVisibility(true); }
  if (ballRepr) { ballRepr.setVisibility(false); out.no_ball_stick = time(); ballRepr.setVisibility(true); }
  if (cartoonRepr && ballRepr) {
    cartoonRepr.setVisibility(false); ballRepr.setVisibility(false);
    out.none = time();
    cartoonRepr.setVisibility(true); ballRepr.setVisibility(true);
  }
  return out;
};
