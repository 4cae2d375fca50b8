// hivemap live map viewer: points of every map (progressively, one level-of-detail part after the other),
// keyframe trajectories and frustums per agent, current agent positions, loop edges, ground truth when the
// server has it (a toggle), filtered events, and a side panel (agents, maps, bandwidth). Polls the REST API.
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

const POLL_MS = 1000;
// 16 well-separated colours, all readable on the dark background; an agent's is a hash of its id (session suffix "#n" ignored), so it is the
// same on every page load and in Foxglove (hivemap.server.foxglove.agent_color uses this hash too).
export const PALETTE = [0x1f77b4, 0xff7f0e, 0x2ca02c, 0xd62728, 0x9467bd, 0x8c564b, 0xe377c2, 0x7f7f7f,
  0xbcbd22, 0x17becf, 0x66ffcc, 0x99cc33, 0xb266ff, 0xffcc00, 0x4da6ff, 0xcc6666];
// the first level of detail holds at most this many points of a map; each further request doubles what is
// drawn (see lodSteps)
const PART_POINTS = 150000;
const LOOP_COLOR = 0xff00ff;
// rendezvous observations (one agent saw another's markers) by state: kept, rejected, not judged yet
const RENDEZVOUS_COLORS = { kept: 0x00e676, rejected: 0xff1744, other: 0xffc400 };
// events shown by default; the rest (candidates, BA and consistency details, info) with "all events"
const DEFAULT_EVENTS = new Set(["merge", "loop", "correction", "gnss_stage", "session", "error", "refused",
  "connect", "disconnect", "mission", "start_anchor", "start_prior", "selfcheck_alarm", "loop_rejected",
  "loop_readmitted", "merge_undone", "merge_confirmed"]);
const state = { maps: [], agents: [], events: [], colors: {}, drawnPoints: 0, allEvents: false,
  kfCounts: "", pointsKey: null, pointsLoading: false, showGt: true };

const canvas = document.getElementById("view");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x14171c);
const camera = new THREE.PerspectiveCamera(55, 1, 0.1, 5000);
camera.up.set(0, 0, 1); // hivemap frames are z-up
camera.position.set(-60, -80, 90);
const controls = new OrbitControls(camera, canvas);
controls.target.set(0, 0, 0);
controls.update();
// the camera's position and orbit target, for tests and scripts that drive the view
controls.addEventListener("change", () => {
  requestRender();
  document.body.dataset.camera = JSON.stringify([camera.position.toArray(), controls.target.toArray()]);
});
const grid = new THREE.GridHelper(200, 20, 0x3a3f47, 0x262a30);
grid.rotation.x = Math.PI / 2;
scene.add(grid);

const pointGroup = new THREE.Group();
const trajGroup = new THREE.Group();
const agentGroup = new THREE.Group();
const frustumGroup = new THREE.Group();
const edgeGroup = new THREE.Group();
const gtGroup = new THREE.Group();
const ellipseGroup = new THREE.Group();
scene.add(pointGroup, trajGroup, agentGroup, frustumGroup, edgeGroup, gtGroup, ellipseGroup);

// FNV-1a, 32 bit, over the UTF-8 bytes of the id
export function hashId(id) {
  let h = 0x811c9dc5;
  for (const b of new TextEncoder().encode(id)) { h ^= b; h = Math.imul(h, 0x01000193) >>> 0; }
  return h >>> 0;
}

function colorOf(agentId) {
  const base = String(agentId).split("#")[0];
  if (!(base in state.colors)) state.colors[base] = PALETTE[hashId(base) % PALETTE.length];
  return state.colors[base];
}

// The horizontal (x, y; hivemap frames are z-up) n-sigma ellipse of a 3x3 position covariance: semi-axes
// and the major axis' angle from x, from the eigen-decomposition of its x-y block (closed form for 2x2).
export function horizontalEllipse(cov, nSigma = 2) {
  const a = cov[0][0], b = 0.5 * (cov[0][1] + cov[1][0]), c = cov[1][1];
  const mean = 0.5 * (a + c), half = Math.hypot(0.5 * (a - c), b);
  const l1 = Math.max(mean + half, 0), l2 = Math.max(mean - half, 0);
  return { major: nSigma * Math.sqrt(l1), minor: nSigma * Math.sqrt(l2), angle: 0.5 * Math.atan2(2 * b, a - c) };
}

function ellipseLine(u, color) {
  const e = horizontalEllipse(u.position_cov, 2);
  const [x0, y0, z0] = u.position;
  const n = 64, pos = new Float32Array(3 * n), ca = Math.cos(e.angle), sa = Math.sin(e.angle);
  for (let i = 0; i < n; i++) {
    const t = (2 * Math.PI * i) / n, px = e.major * Math.cos(t), py = e.minor * Math.sin(t);
    pos.set([x0 + ca * px - sa * py, y0 + sa * px + ca * py, z0], 3 * i);
  }
  const geom = new THREE.BufferGeometry();
  geom.setAttribute("position", new THREE.BufferAttribute(pos, 3));
  const line = new THREE.LineLoop(geom, new THREE.LineBasicMaterial({ color }));
  line.userData = { agentId: u.agent_id, major: e.major, minor: e.minor };
  return line;
}

function resize() {
  const w = canvas.clientWidth;
  const h = canvas.clientHeight;
  if (canvas.width !== w || canvas.height !== h) {
    renderer.setSize(w, h, false);
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
    requestRender();
  }
}

async function getJSON(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r.json();
}

// Binary little-endian PLY with x, y, z vertex properties (float or double), other properties skipped.
export function parsePly(buffer) {
  const bytes = new Uint8Array(buffer);
  const headerEnd = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 4096))).indexOf("end_header\n");
  if (headerEnd < 0) throw new Error("PLY: no end_header");
  const header = new TextDecoder().decode(bytes.subarray(0, headerEnd)).split("\n");
  let count = 0;
  const props = [];
  let inVertex = false;
  for (const line of header) {
    const f = line.trim().split(/\s+/);
    if (f[0] === "element") { inVertex = f[1] === "vertex"; if (inVertex) count = parseInt(f[2], 10); }
    else if (f[0] === "property" && inVertex) props.push({ type: f[1], name: f[2] });
  }
  const size = { float: 4, float32: 4, double: 8, float64: 8, uchar: 1, uint8: 1, char: 1, int8: 1,
    short: 2, int16: 2, ushort: 2, uint16: 2, int: 4, int32: 4, uint: 4, uint32: 4 };
  let stride = 0;
  const off = {};
  for (const p of props) { off[p.name] = { o: stride, t: p.type }; stride += size[p.type]; }
  const body = headerEnd + "end_header\n".length;
  if (props.length === 3 && props.every((p, i) => p.name === "xyz"[i] && (p.type === "float" || p.type === "float32"))) {
    return new Float32Array(buffer.slice(body, body + 12 * count)); // the level-of-detail parts: as they are
  }
  const dv = new DataView(buffer, body);
  const xyz = new Float32Array(count * 3);
  const read = (base, p) => (p.t === "double" || p.t === "float64") ? dv.getFloat64(base + p.o, true) : dv.getFloat32(base + p.o, true);
  for (let i = 0; i < count; i++) {
    const base = i * stride;
    xyz[3 * i] = read(base, off.x); xyz[3 * i + 1] = read(base, off.y); xyz[3 * i + 2] = read(base, off.z);
  }
  return xyz;
}

// First data: frame the map on robust bounds (5th-95th percentile per axis; far outliers ignored).
function fitCamera(arrays) {
  const lo = [], hi = [];
  for (let ax = 0; ax < 3; ax++) {
    const v = [];
    for (const a of arrays) for (let i = ax; i < a.length; i += 3 * Math.max(1, Math.floor(a.length / 30000))) if (Number.isFinite(a[i])) v.push(a[i]);
    v.sort((x, y) => x - y);
    lo.push(v[Math.floor(0.05 * (v.length - 1))] ?? 0);
    hi.push(v[Math.floor(0.95 * (v.length - 1))] ?? 0);
  }
  const center = new THREE.Vector3((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
  const size = Math.max(10, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]));
  state.sceneSize = size;
  controls.target.copy(center);
  camera.position.set(center.x - 0.5 * size, center.y - 0.7 * size, center.z + 0.8 * size);
  controls.update();
  state.fitted = true;
  state.kfCounts = ""; // the loop arcs' height follows the scene size: rebuilt at the next poll
}

// The requests (part K of P, GET /maps/ID/points?part=K&parts=P) that load a map of ``points`` points coarse
// to fine: part 0 of P (P the power of two that makes it at most PART_POINTS), then P/2 of P, P/4 of P/2,
// ..., 1 of 2. Part K of P is a point hash's residue K mod P, so these are disjoint, hold every point, and
// each doubles the density drawn: log2(P) + 1 requests, and the frames drawn while loading cost about twice
// the full map's.
export function lodSteps(points) {
  let p = 1;
  while (points / p > PART_POINTS) p *= 2;
  const steps = [[0, p]];
  for (let q = p; q > 1; q /= 2) steps.push([q / 2, q]);
  return steps;
}

// Every map's points, level after level of detail: the first load draws each part as it arrives, so
// the whole map shows at low density after one request per map; a reload (the counts changed) builds the
// new cloud aside and swaps it in once complete, so the drawn map never thins out.
async function loadPoints(key) {
  state.pointsLoading = true;
  const progressive = pointGroup.children.length === 0;
  const group = new THREE.Group();
  if (progressive) pointGroup.add(group);
  const mat = new THREE.PointsMaterial({ size: 0.12, color: 0xd0d4da, sizeAttenuation: true });
  const maps = state.maps.map((m) => ({ id: m.id, steps: lodSteps(m.points || 0), gone: false }));
  const levels = Math.max(0, ...maps.map((m) => m.steps.length));
  let total = 0;
  document.body.dataset.pointsLevel = "coarse";
  try {
    for (let k = 0; k < levels; k++) {
      for (const m of maps) {
        if (k >= m.steps.length || m.gone) continue;
        const [part, parts] = m.steps[k];
        const r = await fetch(`/maps/${m.id}/points?part=${part}&parts=${parts}`);
        if (!r.ok) { m.gone = true; continue; } // merged away since /maps was read
        const xyz = parsePly(await r.arrayBuffer());
        if (!xyz.length) continue;
        const geom = new THREE.BufferGeometry();
        geom.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
        const pts = new THREE.Points(geom, mat);
        pts.userData.mapId = m.id;
        group.add(pts);
        requestRender();
        total += xyz.length / 3;
        if (progressive) {
          state.drawnPoints = total;
          document.body.dataset.points = String(total);
        }
      }
      // framed on the first level of detail of every map (an even subsample: the same bounds as all)
      if (k === 0 && progressive && !state.fitted && total > 0) fitCamera(group.children.map((c) => c.geometry.getAttribute("position").array));
    }
  } finally {
    state.pointsLoading = false;
  }
  if (!progressive) {
    pointGroup.clear();
    pointGroup.add(group);
  }
  if (!state.fitted && total > 0) fitCamera(group.children.map((c) => c.geometry.getAttribute("position").array));
  requestRender();
  state.pointsKey = key;
  state.drawnPoints = total;
  document.body.dataset.points = String(total);
  document.body.dataset.pointsLevel = "full";
  if (total) state.allPoints = true;
}

// A pyramid per keyframe (apex at the camera centre, 60 x 45 degree field of view), as line segments.
function frustumSegments(T, depth) {
  const hx = Math.tan(Math.PI / 6) * depth, hy = Math.tan(Math.PI / 8) * depth;
  const c = [[-hx, -hy, depth], [hx, -hy, depth], [hx, hy, depth], [-hx, hy, depth]].map(([x, y, z]) =>
    [T[0][0] * x + T[0][1] * y + T[0][2] * z + T[0][3], T[1][0] * x + T[1][1] * y + T[1][2] * z + T[1][3],
      T[2][0] * x + T[2][1] * y + T[2][2] * z + T[2][3]]);
  const o = [T[0][3], T[1][3], T[2][3]];
  const out = [];
  for (let i = 0; i < 4; i++) out.push(o, c[i], c[i], c[(i + 1) % 4]);
  return out;
}

async function refreshKeyframes() {
  const counts = JSON.stringify(state.maps.map((m) => [m.id, m.keyframes]));
  if (counts === state.kfCounts) return;
  const byAgent = {};
  const loops = [];
  const sightings = { kept: [], rejected: [], other: [] };
  for (const m of state.maps) {
    let kfs, edges, rv;
    try {
      [kfs, edges, rv] = await Promise.all([getJSON(`/maps/${m.id}/keyframes?limit=10000`), getJSON(`/maps/${m.id}/edges`),
        getJSON(`/maps/${m.id}/rendezvous`)]);
    } catch { continue; }
    for (const k of kfs.keyframes) (byAgent[k.agent_id] ??= []).push(k.world_from_cam);
    loops.push(...edges.segments);
    // a line from the observer to the observed agent where the observation places it (in this map's frame)
    for (const r of rv.rendezvous) {
      if (!r.observer_position || !r.observed_position || r.position_map !== m.id) continue;
      (sightings[r.state] ?? sightings.other).push(...r.observer_position, ...r.observed_position);
    }
  }
  frustumGroup.clear();
  let n = 0;
  for (const [agent, poses] of Object.entries(byAgent)) {
    const pts = poses.flatMap((T) => frustumSegments(T, 0.6)).flat();
    const geom = new THREE.BufferGeometry();
    geom.setAttribute("position", new THREE.BufferAttribute(new Float32Array(pts), 3));
    frustumGroup.add(new THREE.LineSegments(geom, new THREE.LineBasicMaterial({ color: colorOf(agent), transparent: true, opacity: 0.7 })));
    n += poses.length;
  }
  edgeGroup.clear();
  if (loops.length) {
    // each loop edge as an arc raised above its two keyframes: a loop joins places that are close in the
    // corrected map, so a straight segment would hide under the trajectory
    const pts = [];
    for (const [a, b] of loops) {
      const lift = 0.05 * (state.sceneSize ?? 20) + 0.5 * Math.hypot(b[0] - a[0], b[1] - a[1], b[2] - a[2]);
      const curve = new THREE.QuadraticBezierCurve3(new THREE.Vector3(...a),
        new THREE.Vector3((a[0] + b[0]) / 2, (a[1] + b[1]) / 2, (a[2] + b[2]) / 2 + 2 * lift), new THREE.Vector3(...b));
      const c = curve.getPoints(12);
      for (let i = 0; i < c.length - 1; i++) pts.push(c[i].x, c[i].y, c[i].z, c[i + 1].x, c[i + 1].y, c[i + 1].z);
    }
    const geom = new THREE.BufferGeometry();
    geom.setAttribute("position", new THREE.BufferAttribute(new Float32Array(pts), 3));
    edgeGroup.add(new THREE.LineSegments(geom, new THREE.LineBasicMaterial({ color: LOOP_COLOR })));
  }
  for (const [st, pts] of Object.entries(sightings)) {
    if (!pts.length) continue;
    const geom = new THREE.BufferGeometry();
    geom.setAttribute("position", new THREE.BufferAttribute(new Float32Array(pts), 3));
    edgeGroup.add(new THREE.LineSegments(geom, new THREE.LineBasicMaterial({ color: RENDEZVOUS_COLORS[st] })));
  }
  state.kfCounts = counts;
  requestRender();
  document.body.dataset.rendezvous = String(Object.values(sightings).reduce((n, p) => n + p.length / 6, 0));
  document.body.dataset.frustums = String(n);
  document.body.dataset.loopEdges = String(loops.length);
  await refreshGroundTruth();
}

// Ground truth of each map's agents (when the server was given a ground-truth folder), aligned to the map
// by the server, drawn dashed in the agent's colour; the "ground truth" toggle shows or hides it.
async function refreshGroundTruth() {
  const lines = [];
  let configured = false;
  for (const m of state.maps) {
    let gt;
    try { gt = await getJSON(`/maps/${m.id}/groundtruth`); } catch { continue; }
    configured ||= gt.configured;
    for (const a of gt.agents || []) {
      if (a.positions.length < 2) continue;
      const geom = new THREE.BufferGeometry();
      geom.setAttribute("position", new THREE.BufferAttribute(new Float32Array(a.positions.flat()), 3));
      const line = new THREE.Line(geom, new THREE.LineDashedMaterial({ color: colorOf(a.agent_id), dashSize: 0.6, gapSize: 0.4 }));
      line.computeLineDistances();
      line.userData.agentId = a.agent_id;
      lines.push(line);
    }
  }
  gtGroup.clear();
  for (const l of lines) gtGroup.add(l);
  requestRender();
  gtGroup.visible = state.showGt;
  document.getElementById("gt-toggle").hidden = !configured;
  document.body.dataset.groundtruth = String(lines.length);
  document.body.dataset.groundtruthShown = String(state.showGt ? lines.length : 0);
}

async function refreshTrajectories() {
  const fetched = [];
  for (const a of state.agents) {
    if (!a.keyframes) continue; // configured but nothing received yet
    try { fetched.push([a, await getJSON(`/agents/${encodeURIComponent(a.agent_id)}/trajectory?frame=global&format=json`)]); }
    catch { continue; }
  }
  // redrawn (and the frame rendered) only when a trajectory changed
  const key = JSON.stringify(fetched.map(([a, traj]) => [a.agent_id, traj.poses || traj, a.uncertainty ?? null]));
  if (key === state.trajKey) return;
  state.trajKey = key;
  requestRender();
  trajGroup.clear();
  agentGroup.clear();
  ellipseGroup.clear();
  for (const [a, traj] of fetched) {
    // the 2-sigma position ellipse of the agent's latest keyframe (the back-end's pose-graph marginal)
    if (a.uncertainty) ellipseGroup.add(ellipseLine(a.uncertainty, colorOf(a.agent_id)));
    const poses = traj.poses || traj;
    if (!poses.length) continue;
    const pos = new Float32Array(poses.length * 3);
    poses.forEach((p, i) => { const t = p.t || p.position || [p.x, p.y, p.z]; pos.set(t, 3 * i); });
    const geom = new THREE.BufferGeometry();
    geom.setAttribute("position", new THREE.BufferAttribute(pos, 3));
    trajGroup.add(new THREE.Line(geom, new THREE.LineBasicMaterial({ color: colorOf(a.agent_id) })));
    const head = new THREE.Mesh(new THREE.SphereGeometry(0.8, 16, 12), new THREE.MeshBasicMaterial({ color: colorOf(a.agent_id) }));
    head.position.set(pos[pos.length - 3], pos[pos.length - 2], pos[pos.length - 1]);
    head.userData.agentId = a.agent_id;
    agentGroup.add(head);
  }
  document.body.dataset.agentsDrawn = String(agentGroup.children.length);
  document.body.dataset.ellipses = JSON.stringify(Object.fromEntries(
    ellipseGroup.children.map((l) => [l.userData.agentId, [l.userData.major, l.userData.minor]])));
  document.body.dataset.colors = JSON.stringify(Object.fromEntries(
    state.agents.map((a) => [a.agent_id, "#" + colorOf(a.agent_id).toString(16).padStart(6, "0")])));
}

function fmtRate(b) { return b > 1024 ? `${(b / 1024).toFixed(1)} KB/s` : `${Math.round(b)} B/s`; }

function renderPanel() {
  const agents = state.agents.map((a) => {
    const c = "#" + colorOf(a.agent_id).toString(16).padStart(6, "0");
    const bw = a.bandwidth || {};
    return `<tr data-agent="${a.agent_id}"><td><span class="sw" style="background:${c}"></span>${a.agent_id}</td>` +
      `<td>${a.kind ?? ""}</td><td>${a.state ?? ""}</td><td>${a.keyframes ?? 0}</td><td>${a.map_id ?? ""}</td>` +
      `<td>${fmtRate(bw.up_avg ?? 0)} / ${fmtRate(bw.up_peak ?? 0)}</td><td>${fmtRate(bw.down_avg ?? 0)}</td></tr>`;
  }).join("");
  const maps = state.maps.map((m) => `<tr><td>${m.id}</td><td>${(m.agents || []).join(", ")}</td>` +
    `<td>${m.keyframes ?? ""}</td><td>${m.points ?? ""}</td></tr>`).join("");
  const shown = state.events.filter((e) => state.allEvents || DEFAULT_EVENTS.has(e.kind));
  const events = shown.slice(-12).reverse().map((e) => `<li data-kind="${e.kind}">${e.kind}: ${e.message ?? ""}</li>`).join("");
  document.getElementById("agents").innerHTML = agents;
  document.getElementById("maps").innerHTML = maps;
  document.getElementById("events").innerHTML = events;
  document.getElementById("status").textContent = `${state.drawnPoints} points, ${state.agents.length} agents, ${state.maps.length} maps`;
}

let lastPointsFetch = 0;
async function poll() {
  try {
    const [agents, maps, events] = await Promise.all([getJSON("/agents"), getJSON("/maps"), getJSON("/events")]);
    state.agents = agents.agents || agents;
    state.maps = maps.maps || maps;
    state.events = events.events || events;
    const counts = JSON.stringify(state.maps.map((m) => [m.id, m.points]));
    const now = Date.now();
    if (counts !== state.pointsKey && !state.pointsLoading && now - lastPointsFetch > 2000) {
      lastPointsFetch = now;
      // not awaited: the panel, trajectories and frustums go on updating while the parts arrive
      loadPoints(counts).catch((err) => { document.getElementById("status").textContent = `points: ${err.message}`; });
    }
    await refreshTrajectories();
    await refreshKeyframes();
    renderPanel();
    document.body.dataset.ready = "1";
  } catch (err) {
    document.getElementById("status").textContent = `connection problem: ${err.message}`;
  }
  setTimeout(poll, POLL_MS);
}

// Drawn on demand (the view moved, data arrived, the window changed): a frame of millions of points is
// expensive, so an idle page draws nothing.
let needsRender = true;
function requestRender() { needsRender = true; }

function animate() {
  resize();
  controls.update();
  if (needsRender) {
    needsRender = false;
    renderer.render(scene, camera);
    // times from navigation to the first frame with points and to the first with all of them
    const d = document.body.dataset;
    if (state.drawnPoints > 0 && !d.pointsFirstMs) d.pointsFirstMs = String(Math.round(performance.now()));
    if (state.allPoints && !d.pointsAllMs) d.pointsAllMs = String(Math.round(performance.now()));
  }
  requestAnimationFrame(animate);
}

document.getElementById("all-events").addEventListener("change", (e) => { state.allEvents = e.target.checked; renderPanel(); });
document.getElementById("show-gt").addEventListener("change", (e) => {
  state.showGt = e.target.checked;
  gtGroup.visible = state.showGt;
  requestRender();
  document.body.dataset.groundtruthShown = String(state.showGt ? gtGroup.children.length : 0);
});
animate();
poll();
