// randt-fleet map viewer: the service's tiles as a 3-D point cloud, the fleet's live positions and
// trajectories, and each tile's PDU. Plain ES module, no build step; everything comes from the
// REST API (docs/api.md), polled:
//   GET maps                                  the map list (the selector)
//   GET maps/<map>/tiles                      tile index: ids, versions, bounds, PDU  (every 3 s)
//   GET maps/<map>/tiles/<ix>/<iy>?format=pcd only tiles whose version changed, TILE_FETCHES at a
//                                             time, each listed in the table as it arrives
//   GET sessions + .../trajectory?corrected=true  the sessions of this map, running or finished
//                                             (every 2 s): trajectories as the pose graph corrected
//                                             them (a finished one's again when the graph moved)
//   GET maps/<map>/graph                      the pose graph's accepted loops, drawn as edges
//                                             between their keyframes (every 2 s; 404: none)
// Frames: the map frame is z up; three.js's camera is told so (camera.up = +z).
// window.randtViewer exposes counters (tiles, points, vehicles, errors) for tests and curious users.

import * as THREE from "three";
import { OrbitControls } from "./vendor/three/OrbitControls.js";

const TILE_POLL_MS = 3000;
const TILE_FETCHES = 6; // tile downloads at a time
const SESSION_POLL_MS = 2000;
const DENSITY_CELL_M = 1.0;

const state = {
  map: null, // selected map name
  tiles: new Map(), // id -> {version, points: THREE.Points, outline: THREE.LineLoop, info}
  vehicles: new Map(), // id -> {line, marker, color}
  trajectories: new Map(), // session id -> its last fetched trajectory (with the graph revision then)
  zRange: [0, 5],
  framed: false,
  token: sessionStorage.getItem("randt-token") || "",
  colorBy: "height",
};
window.randtViewer = {
  ready: false, tiles: 0, points: 0, vehicles: 0, trajectoryPoses: 0, correctedTrajectories: 0, loopEdges: 0,
  finishedVehicles: 0, loading: 0, inFlight: 0, maxInFlight: 0, rowsWhileLoading: 0, errors: [],
};

// ------------------------------------------------------------------ scene
const view = document.getElementById("view");
const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio || 1);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.setClearColor(0x101418);
view.appendChild(renderer.domElement);

const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(55, window.innerWidth / window.innerHeight, 0.5, 20000);
camera.up.set(0, 0, 1);
camera.position.set(-120, -160, 140);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;
const tileGroup = new THREE.Group();
const outlineGroup = new THREE.Group();
const fleetGroup = new THREE.Group();
scene.add(tileGroup, outlineGroup, fleetGroup);

window.addEventListener("resize", () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
});

function animate() {
  controls.update();
  renderer.render(scene, camera);
  requestAnimationFrame(animate);
}
requestAnimationFrame(animate);

// ------------------------------------------------------------------ colours
// Turbo-like ramp (blue -> cyan -> green -> yellow -> red), t in [0, 1].
const RAMP = [
  [0.19, 0.07, 0.23], [0.16, 0.47, 0.93], [0.09, 0.84, 0.75], [0.49, 0.99, 0.33],
  [0.93, 0.82, 0.2], [0.98, 0.45, 0.11], [0.66, 0.05, 0.01],
];
function ramp(t, out, o) {
  const x = Math.min(Math.max(t, 0), 1) * (RAMP.length - 1);
  const i = Math.min(Math.floor(x), RAMP.length - 2);
  const f = x - i;
  for (let c = 0; c < 3; c++) out[o + c] = RAMP[i][c] * (1 - f) + RAMP[i + 1][c] * f;
}
function pduColor(pdu) {
  // PDU <= 0 red, 1 green
  const t = Math.min(Math.max(pdu, 0), 1);
  return new THREE.Color(1 - t, 0.25 + 0.65 * t, 0.2);
}
const VEHICLE_COLORS = [0xff4fd8, 0xffffff, 0xffd400, 0x00e5ff, 0xff7a00, 0x9dff00];

function drawLegend() {
  const stops = [];
  for (let k = 0; k <= 10; k++) {
    const c = [0, 0, 0];
    ramp(k / 10, c, 0);
    stops.push(`rgb(${c.map((v) => Math.round(v * 255)).join(",")}) ${k * 10}%`);
  }
  const legend = document.getElementById("legend");
  legend.style.background = `linear-gradient(to right, ${stops.join(",")})`;
  legend.title = state.colorBy === "height"
    ? `height ${state.zRange[0].toFixed(1)} m … ${state.zRange[1].toFixed(1)} m`
    : `points per ${DENSITY_CELL_M} m cell, low … high`;
}

// ------------------------------------------------------------------ API access
function authHeaders() {
  return state.token ? { Authorization: `Bearer ${state.token}` } : {};
}
async function api(path, { binary = false } = {}) {
  const response = await fetch(new URL(path, document.baseURI), { headers: authHeaders(), cache: "no-cache" });
  if (response.status === 401) {
    document.getElementById("token-form").hidden = false;
    throw new Error("the API needs a token (RANDT_API_TOKEN)");
  }
  if (!response.ok) throw new Error(`${path}: HTTP ${response.status}`);
  return binary ? response.arrayBuffer() : response.json();
}
function report(where, err) {
  // A failed poll is shown and retried, never thrown: the page keeps working while the service restarts.
  const msg = `${where}: ${err.message || err}`;
  window.randtViewer.errors.push(msg);
  setStatus(msg);
  console.warn(msg);
}
function setStatus(text) {
  document.getElementById("status").textContent = text;
}

// ------------------------------------------------------------------ PCD (binary) parsing
function parsePcd(buffer) {
  const bytes = new Uint8Array(buffer);
  const text = new TextDecoder("ascii").decode(bytes.subarray(0, Math.min(bytes.length, 2048)));
  const end = text.indexOf("\nDATA ");
  if (end < 0) throw new Error("not a PCD file");
  const lineEnd = text.indexOf("\n", end + 1);
  const header = {};
  for (const line of text.slice(0, lineEnd).split("\n")) {
    const [key, ...rest] = line.trim().split(/\s+/);
    if (key && !key.startsWith("#")) header[key] = rest;
  }
  if (header.DATA[0] !== "binary") throw new Error(`PCD DATA ${header.DATA[0]} is not supported`);
  const fields = header.FIELDS;
  const sizes = header.SIZE.map(Number);
  const counts = (header.COUNT || fields.map(() => "1")).map(Number);
  const n = Number(header.POINTS[0]);
  const offsets = {};
  let stride = 0;
  fields.forEach((f, i) => {
    offsets[f] = stride;
    stride += sizes[i] * counts[i];
  });
  const view = new DataView(buffer, lineEnd + 1);
  const xyz = new Float32Array(n * 3);
  for (let i = 0; i < n; i++) {
    const b = i * stride;
    xyz[3 * i] = view.getFloat32(b + offsets.x, true);
    xyz[3 * i + 1] = view.getFloat32(b + offsets.y, true);
    xyz[3 * i + 2] = view.getFloat32(b + offsets.z, true);
  }
  return xyz;
}

// ------------------------------------------------------------------ tiles
function colorsFor(xyz) {
  const n = xyz.length / 3;
  const colors = new Float32Array(n * 3);
  if (state.colorBy === "height") {
    const [z0, z1] = state.zRange;
    const span = Math.max(z1 - z0, 1e-3);
    for (let i = 0; i < n; i++) ramp((xyz[3 * i + 2] - z0) / span, colors, 3 * i);
  } else {
    const cells = new Map();
    const key = (i) => `${Math.floor(xyz[3 * i] / DENSITY_CELL_M)},${Math.floor(xyz[3 * i + 1] / DENSITY_CELL_M)}`;
    for (let i = 0; i < n; i++) cells.set(key(i), (cells.get(key(i)) || 0) + 1);
    let max = 1;
    for (const c of cells.values()) max = Math.max(max, c);
    for (let i = 0; i < n; i++) ramp(Math.log(cells.get(key(i))) / Math.log(max + 1), colors, 3 * i);
  }
  return colors;
}

const pointMaterial = new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true });

async function loadTile(info) {
  const buffer = await api(`maps/${encodeURIComponent(state.map)}/tiles/${info.ix}/${info.iy}?format=pcd`, { binary: true });
  const xyz = parsePcd(buffer);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
  geometry.setAttribute("color", new THREE.BufferAttribute(colorsFor(xyz), 3));
  geometry.computeBoundingSphere();
  const old = state.tiles.get(info.id);
  if (old && old.points) {
    tileGroup.remove(old.points);
    old.points.geometry.dispose();
  }
  const points = new THREE.Points(geometry, pointMaterial);
  tileGroup.add(points);
  return points;
}

function outline(info) {
  const [x0, y0] = info.bounds.cell_min_xy;
  const [x1, y1] = info.bounds.cell_max_xy;
  const z = state.zRange[0];
  const geometry = new THREE.BufferGeometry().setFromPoints([
    new THREE.Vector3(x0, y0, z), new THREE.Vector3(x1, y0, z),
    new THREE.Vector3(x1, y1, z), new THREE.Vector3(x0, y1, z),
  ]);
  return new THREE.LineLoop(geometry, new THREE.LineBasicMaterial({ color: pduColor(info.pdu) }));
}

// The table lists the tiles loaded so far, as they arrive (worst PDU first), out of the index's.
function renderTileTable(index) {
  const body = document.querySelector("#tiles tbody");
  const loaded = [...state.tiles.values()].map((t) => t.info).sort((a, b) => a.pdu - b.pdu);
  body.replaceChildren(...loaded.map((t) => {
    const tr = document.createElement("tr");
    for (const v of [t.id, t.points, t.version, t.pdu.toFixed(2)]) {
      const td = document.createElement("td");
      td.textContent = v;
      tr.appendChild(td);
    }
    tr.querySelector("td:last-child").style.color = `#${pduColor(t.pdu).getHexString()}`;
    return tr;
  }));
  const total = loaded.reduce((s, t) => s + t.points, 0);
  const mean = loaded.length ? loaded.reduce((s, t) => s + t.pdu, 0) / loaded.length : 0;
  const of = loaded.length < index.tiles.length ? ` (loading ${index.tiles.length - loaded.length} more)` : "";
  document.getElementById("tile-summary").textContent =
    `${loaded.length} tiles${of}, ${total.toLocaleString()} points, mean PDU ${mean.toFixed(2)}`;
  if (window.randtViewer.loading > 0) {
    window.randtViewer.rowsWhileLoading = Math.max(window.randtViewer.rowsWhileLoading, loaded.length);
  }
}

function frameCamera(index) {
  if (state.framed || index.tiles.length === 0) return;
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
  for (const t of index.tiles) {
    x0 = Math.min(x0, t.bounds.min_xyz[0]); y0 = Math.min(y0, t.bounds.min_xyz[1]);
    x1 = Math.max(x1, t.bounds.max_xyz[0]); y1 = Math.max(y1, t.bounds.max_xyz[1]);
  }
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  const r = Math.max(x1 - x0, y1 - y0, 40) / 2;
  controls.target.set(cx, cy, state.zRange[0]);
  camera.position.set(cx - 0.55 * r, cy - 1.35 * r, state.zRange[0] + 1.25 * r);
  camera.far = 40 * r;
  camera.updateProjectionMatrix();
  state.framed = true;
}

async function pollTiles() {
  if (!state.map) return;
  const map = state.map;
  const index = await api(`maps/${encodeURIComponent(map)}/tiles`);
  if (map !== state.map) return;
  if (index.tiles.length) {
    // Height colours span the lower 98 % of the map's tile tops (a few tall poles would wash them out).
    const lows = index.tiles.map((t) => t.bounds.min_xyz[2]);
    const highs = index.tiles.map((t) => t.bounds.max_xyz[2]).sort((a, b) => a - b);
    state.zRange = [Math.min(...lows), highs[Math.floor(0.98 * (highs.length - 1))]];
  }
  frameCamera(index);
  const seen = new Set(index.tiles.map((t) => t.id));
  for (const [id, t] of state.tiles) {
    if (!seen.has(id)) {
      tileGroup.remove(t.points);
      outlineGroup.remove(t.outline);
      state.tiles.delete(id);
    }
  }
  const changed = [];
  for (const info of index.tiles) {
    const have = state.tiles.get(info.id);
    if (!have || have.version !== info.version) {
      changed.push(info);
    } else if (have.info.pdu !== info.pdu) {
      have.outline.material.color = pduColor(info.pdu);
      have.info = info;
    }
  }
  // TILE_FETCHES downloads at a time; each tile is drawn and listed as soon as it arrives.
  window.randtViewer.loading = changed.length;
  let next = 0;
  async function worker() {
    while (next < changed.length && map === state.map) {
      const info = changed[next++];
      window.randtViewer.inFlight += 1;
      window.randtViewer.maxInFlight = Math.max(window.randtViewer.maxInFlight, window.randtViewer.inFlight);
      let points;
      try {
        points = await loadTile(info);
      } finally {
        window.randtViewer.inFlight -= 1;
      }
      if (map !== state.map) return;
      const have = state.tiles.get(info.id);
      if (have && have.outline) outlineGroup.remove(have.outline);
      const line = outline(info);
      outlineGroup.add(line);
      state.tiles.set(info.id, { version: info.version, points, outline: line, info });
      window.randtViewer.loading -= 1;
      renderTileTable(index);
      countTiles();
    }
  }
  await Promise.all(Array.from({ length: Math.min(TILE_FETCHES, changed.length) }, worker));
  window.randtViewer.loading = 0;
  renderTileTable(index);
  countTiles();
}

function countTiles() {
  window.randtViewer.tiles = state.tiles.size;
  window.randtViewer.points = [...state.tiles.values()].reduce((s, t) => s + t.points.geometry.attributes.position.count, 0);
}

function recolor() {
  for (const t of state.tiles.values()) {
    const xyz = t.points.geometry.attributes.position.array;
    t.points.geometry.setAttribute("color", new THREE.BufferAttribute(colorsFor(xyz), 3));
  }
  drawLegend();
}

// ------------------------------------------------------------------ vehicles
async function pollVehicles() {
  if (!state.map) return;
  // Every session of this map (those joined to it too), running or finished: a finished one's
  // trajectory is fetched again only when the pose graph's revision moved.
  const revision = await pollGraph();
  const sessions = (await api("sessions")).filter((s) => s.map === state.map || s.joined === state.map);
  const seen = new Set();
  let poses = 0;
  let corrected = 0;
  let finished = 0;
  for (const s of sessions) {
    seen.add(s.id);
    const running = s.state === "active";
    finished += running ? 0 : 1;
    let traj = state.trajectories.get(s.id);
    if (running || !traj || traj.revision !== revision) {
      traj = await api(
        `sessions/${encodeURIComponent(s.vehicle)}/${encodeURIComponent(s.session)}/trajectory?format=json&corrected=true`,
      );
      traj.revision = revision;
      state.trajectories.set(s.id, traj);
    }
    corrected += traj.corrected ? 1 : 0;
    const pts = traj.poses.map((p) => new THREE.Vector3(p.pose[0][3], p.pose[1][3], p.pose[2][3]));
    poses += pts.length;
    if (pts.length === 0) continue;
    let v = state.vehicles.get(s.id);
    if (!v) {
      const color = VEHICLE_COLORS[state.vehicles.size % VEHICLE_COLORS.length];
      const line = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color }));
      // The vehicle: a ball on a 12 m pin, visible from afar above the cloud.
      const marker = new THREE.Group();
      const ball = new THREE.Mesh(new THREE.SphereGeometry(3, 16, 12), new THREE.MeshBasicMaterial({ color }));
      ball.position.z = 12;
      const pin = new THREE.Line(
        new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(0, 0, 0), new THREE.Vector3(0, 0, 12)]),
        new THREE.LineBasicMaterial({ color }),
      );
      marker.add(ball, pin);
      fleetGroup.add(line, marker);
      v = { line, marker, color };
      state.vehicles.set(s.id, v);
    }
    v.line.geometry.dispose();
    v.line.geometry = new THREE.BufferGeometry().setFromPoints(pts);
    v.marker.position.copy(pts[pts.length - 1]);
    v.summary = s;
    v.corrected = traj.corrected;
    v.position = pts[pts.length - 1];
  }
  for (const [id, v] of state.vehicles) {
    if (!seen.has(id)) {
      fleetGroup.remove(v.line, v.marker);
      state.vehicles.delete(id);
    }
  }
  const list = document.getElementById("vehicles");
  if (state.vehicles.size === 0) {
    list.innerHTML = '<li class="muted">none in this map</li>';
  } else {
    list.replaceChildren(...[...state.vehicles.entries()].map(([id, v]) => {
      const li = document.createElement("li");
      const sw = document.createElement("span");
      sw.className = "swatch";
      sw.style.background = `#${new THREE.Color(v.color).getHexString()}`;
      const p = v.position;
      const how = v.corrected ? ", corrected by the pose graph" : "";
      const joined = v.summary.joined ? `, joined from its own map` : "";
      const where = v.summary.state === "active" ? `queue ${v.summary.queue_depth}` : v.summary.state;
      li.append(sw, `${id}: ${v.summary.scans} scans, (${p.x.toFixed(1)}, ${p.y.toFixed(1)}) m, ${where}${how}${joined}`);
      return li;
    }));
  }
  window.randtViewer.vehicles = state.vehicles.size;
  window.randtViewer.trajectoryPoses = poses;
  window.randtViewer.correctedTrajectories = corrected;
  window.randtViewer.finishedVehicles = finished;
}

// ------------------------------------------------------------------ pose graph
// Accepted loops of the selected map's pose graph, as segments between their two keyframes'
// optimized positions (a map without a graph answers 404: nothing drawn).
const loopMaterial = new THREE.LineBasicMaterial({ color: 0xff2bd6 });
let loopLines = null;
async function pollGraph() {
  const map = state.map;
  let graph = null;
  try {
    graph = await api(`maps/${encodeURIComponent(map)}/graph`);
  } catch (err) {
    if (!String(err).includes("404")) throw err;
  }
  if (loopLines) {
    fleetGroup.remove(loopLines);
    loopLines.geometry.dispose();
    loopLines = null;
  }
  const where = new Map();
  for (const k of graph ? graph.keyframes : []) {
    if (k.pose) where.set(`${k.vehicle}/${k.session}/${k.seq}`, k.pose);
  }
  const ends = [];
  for (const loop of graph ? graph.loops : []) {
    const a = where.get(loop.a.join("/"));
    const b = where.get(loop.b.join("/"));
    if (!loop.accepted || !a || !b) continue;
    ends.push(new THREE.Vector3(a[0][3], a[1][3], a[2][3] + 2), new THREE.Vector3(b[0][3], b[1][3], b[2][3] + 2));
  }
  if (ends.length) {
    loopLines = new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(ends), loopMaterial);
    fleetGroup.add(loopLines);
  }
  window.randtViewer.loopEdges = ends.length / 2;
  const info = document.getElementById("graph-info");
  if (info) {
    const joined = graph ? Object.keys(graph.joined || {}) : [];
    info.textContent = graph
      ? `pose graph: ${graph.keyframes.length} keyframes, ${ends.length / 2} loops (magenta), revision ${graph.revision}` +
        (joined.length ? `; joined without GNSS: ${joined.join(", ")}` : "")
      : "pose graph: none for this map yet";
  }
  return graph ? graph.revision : null;
}

// ------------------------------------------------------------------ wiring
async function pollStatus() {
  const status = await api("status");
  setStatus(`${status.instance}: ${status.sessions.length} active sessions, ${status.scans_processed} scans, ` +
    `${status.scans_dropped} dropped, up ${Math.round(status.uptime_s)} s`);
}

async function loadMaps() {
  const { maps } = await api("maps");
  const select = document.getElementById("map-select");
  const names = maps.map((m) => m.name);
  if (names.join() !== [...select.options].map((o) => o.value).join()) {
    select.replaceChildren(...names.map((n) => new Option(n, n)));
  }
  if (!state.map || !names.includes(state.map)) {
    state.map = names.includes("default") ? "default" : names[0] || null;
  }
  if (state.map) select.value = state.map;
}

function clearMap() {
  for (const t of state.tiles.values()) {
    tileGroup.remove(t.points);
    outlineGroup.remove(t.outline);
  }
  state.tiles.clear();
  for (const v of state.vehicles.values()) fleetGroup.remove(v.line, v.marker);
  state.vehicles.clear();
  state.trajectories.clear();
  if (loopLines) fleetGroup.remove(loopLines);
  loopLines = null;
  state.framed = false;
}

document.getElementById("map-select").addEventListener("change", (e) => {
  state.map = e.target.value;
  clearMap();
  refreshTiles();
  refreshVehicles();
});
document.getElementById("color-select").addEventListener("change", (e) => {
  state.colorBy = e.target.value;
  recolor();
});
document.getElementById("show-grid").addEventListener("change", (e) => {
  outlineGroup.visible = e.target.checked;
});
document.getElementById("token-form").addEventListener("submit", (e) => {
  e.preventDefault();
  state.token = document.getElementById("token-input").value.trim();
  sessionStorage.setItem("randt-token", state.token);
  document.getElementById("token-form").hidden = true;
  start();
});

// One poll of each kind at a time: a slow tile download must not pile up requests behind it.
const busy = { tiles: false, vehicles: false };
async function refreshTiles() {
  if (busy.tiles) return;
  busy.tiles = true;
  try {
    await loadMaps();
    await pollTiles();
    drawLegend();
    window.randtViewer.ready = true;
    document.body.dataset.state = "ready";
  } catch (err) {
    report("tiles", err);
  } finally {
    busy.tiles = false;
  }
}
async function refreshVehicles() {
  if (busy.vehicles) return;
  busy.vehicles = true;
  try {
    await pollVehicles();
    await pollStatus();
  } catch (err) {
    report("vehicles", err);
  } finally {
    busy.vehicles = false;
  }
}

let timers = [];
function start() {
  timers.forEach(clearInterval);
  drawLegend();
  refreshTiles().then(refreshVehicles);
  timers = [setInterval(refreshTiles, TILE_POLL_MS), setInterval(refreshVehicles, SESSION_POLL_MS)];
}
start();
