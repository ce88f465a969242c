// mi-amr view: the page. One websocket to the server (mi_amr/view/server.py):
// JSON messages out (camera, tf, denoise, snapshot, ack), JSON and binary
// frames in. Every control change is sent at most once per animation frame;
// the server renders the newest state and drops what went stale.

const $ = (id) => document.getElementById(id);
const token = new URLSearchParams(location.search).get("token") || "";
const view = $("view"), ctx = view.getContext("2d");
const editor = $("tf-editor"), ectx = editor.getContext("2d");

let ws = null, camera = null, tf = null, histogram = null;
let colormapStops = {};          // name -> colours over u, from the server (matplotlib's own)
let version = 0;                 // change messages sent (the server's view version)
const changeTimes = new Map();   // version -> time it was sent
let dragging = null;             // camera drag state
let pendingCamera = false, pendingTf = false;
const denoisedShown = { version: -1, full: false };   // of the newest version

// Figures read by people (the stats line) and by tests (window.viewerStats).
const stats = window.viewerStats = {
  frames: 0, denoisedFrames: 0, lastFrame: null, frameTimes: [], latencies: [],
  denoiseLatencies: [], fullDenoiseLatencies: [], lastChange: 0, errors: [], snapshots: [], ready: false,
};

function send(msg) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg)); }

function changed() {             // a change message is about to go out
  version += 1;
  const now = performance.now();
  changeTimes.set(version, now);
  stats.lastChange = now;
  if (changeTimes.size > 500) changeTimes.delete(changeTimes.keys().next().value);
}

function flush() {               // once per animation frame: the newest camera and TF
  if (pendingCamera) { pendingCamera = false; changed(); send({ type: "camera", ...cameraMessage() }); }
  if (pendingTf) { pendingTf = false; changed(); send({ type: "tf", ...tf }); }
  requestAnimationFrame(flush);
}

function cameraMessage() {
  return { azimuth: camera.azimuth, elevation: camera.elevation, distance: camera.distance, target: camera.target };
}

// ---- connection ----------------------------------------------------------------
function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  ws = new WebSocket(`${proto}//${location.host}/ws?token=${encodeURIComponent(token)}`);
  ws.binaryType = "arraybuffer";
  ws.onmessage = (ev) => (typeof ev.data === "string" ? onJson(JSON.parse(ev.data)) : onFrame(ev.data));
  ws.onclose = () => { showStatus("disconnected from the server (reload to reconnect)"); };
}

function showStatus(text) { const s = $("status"); s.textContent = text; s.classList.toggle("hidden", !text); }

function onJson(msg) {
  if (msg.type === "status") {
    if (msg.state === "error") showStatus(`could not load the data: ${msg.desc}`);
    else if (msg.state !== "ready") {
      const pct = msg.total ? ` ${Math.round(100 * msg.done / msg.total)}%` : "";
      showStatus(`loading: ${msg.desc}${pct}`);
    }
  } else if (msg.type === "hello") {
    camera = msg.camera; tf = msg.tf;
    view.width = msg.size[0]; view.height = msg.size[1];
    view.style.height = `${512 * msg.size[1] / msg.size[0]}px`;
    $("data").textContent = msg.data;
    const sel = $("colormap");
    sel.innerHTML = msg.colormaps.map((c) => `<option>${c}</option>`).join("");
    colormapStops = msg.colormap_stops;
    $("log").disabled = !msg.log_available;
    if (!msg.log_available) $("log").title = "the data hold values <= 0: no log10 display";
    $("denoise").checked = msg.denoise;
    $("denoise").disabled = !msg.denoiser;
    $("denoise-note").textContent = msg.denoiser ? "" : `denoiser missing: ${msg.denoiser_missing}`;
    syncControls();
    showStatus("rendering…");
    stats.ready = true;
  } else if (msg.type === "histogram") {
    histogram = msg; drawEditor();
  } else if (msg.type === "snapshot") {
    stats.snapshots.push(msg);
    $("snapshot-result").textContent = `wrote ${msg.files.map((f) => f.split("/").pop()).join(", ")} (${msg.spp} spp)`;
  } else if (msg.type === "error") {
    stats.errors.push(msg);
    $("message").textContent = `server: ${msg.message}`;
    if (msg.about === "snapshot") $("snapshot-result").textContent = msg.message;
  }
}

async function onFrame(buffer) {
  const n = new DataView(buffer).getUint32(0);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, n)));
  const bitmap = await createImageBitmap(new Blob([new Uint8Array(buffer, 4 + n)], { type: "image/jpeg" }));
  ctx.drawImage(bitmap, 0, 0, view.width, view.height);
  bitmap.close();
  send({ type: "ack" });
  const now = performance.now();
  showStatus("");
  stats.frames += 1; stats.lastFrame = header;
  stats.frameTimes.push(now); if (stats.frameTimes.length > 200) stats.frameTimes.shift();
  for (const [v, t] of changeTimes) {             // first frame of (or after) each change
    if (v <= header.version) { stats.latencies.push(now - t); changeTimes.delete(v); }
  }
  if (stats.latencies.length > 500) stats.latencies.splice(0, stats.latencies.length - 500);
  if (header.denoised) {        // the first denoised image (preview, then full size) after the last change
    stats.denoisedFrames += 1;
    if (header.version === version && denoisedShown.version !== version) {
      denoisedShown.version = version; denoisedShown.full = false;
      stats.denoiseLatencies.push(now - stats.lastChange);
    }
    if (header.version === version && !header.preview && !denoisedShown.full) {
      denoisedShown.full = true;
      stats.fullDenoiseLatencies.push(now - stats.lastChange);
    }
  }
  $("spp").textContent = `${header.preview ? "preview" : header.spp + " spp"}${header.denoised ? ", denoised" : ""}`;
  const recent = stats.frameTimes.filter((t) => now - t < 1000).length;
  $("stats").textContent = `${recent} frames/s · frame ${header.render_ms} ms`;
}

// ---- camera: orbit (drag), pan (shift/right drag), zoom (wheel) ---------------------
function basis() {               // camera right and up vectors (for panning)
  const a = camera.azimuth * Math.PI / 180, e = camera.elevation * Math.PI / 180;
  const u = camera.up, h = Math.abs(u[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
  const norm = (p) => { const l = Math.hypot(...p); return p.map((x) => x / l); };
  const e1 = norm(cross(h, u)), e2 = cross(u, e1);
  const d = [0, 1, 2].map((i) => Math.cos(e) * (Math.cos(a) * e1[i] + Math.sin(a) * e2[i]) + Math.sin(e) * u[i]);
  const right = norm(cross(u, d)), up = cross(d, right);
  return { right, up };
}

view.addEventListener("contextmenu", (ev) => ev.preventDefault());
view.addEventListener("pointerdown", (ev) => {
  if (!camera) return;
  view.setPointerCapture(ev.pointerId);
  dragging = { x: ev.clientX, y: ev.clientY, pan: ev.shiftKey || ev.button === 2 };
});
view.addEventListener("pointermove", (ev) => {
  if (!dragging) return;
  const dx = ev.clientX - dragging.x, dy = ev.clientY - dragging.y;
  dragging.x = ev.clientX; dragging.y = ev.clientY;
  if (dragging.pan) {
    const { right, up } = basis(), s = camera.distance / view.clientWidth;
    camera.target = camera.target.map((t, i) => t - s * (dx * right[i] - dy * up[i]));
  } else {
    camera.azimuth -= 0.4 * dx;
    camera.elevation = Math.max(-89, Math.min(89, camera.elevation + 0.4 * dy));
  }
  pendingCamera = true;
});
view.addEventListener("pointerup", () => { dragging = null; });
view.addEventListener("wheel", (ev) => {
  if (!camera) return;
  ev.preventDefault();
  camera.distance *= Math.exp(0.001 * ev.deltaY);
  pendingCamera = true;
}, { passive: false });

// ---- transfer-function editor ---------------------------------------------------------
const PAD = { l: 8, r: 8, t: 8, b: 22 };
const plotW = () => editor.width - PAD.l - PAD.r, plotH = () => editor.height - PAD.t - PAD.b;
const toX = (u) => PAD.l + u * plotW(), toY = (a) => PAD.t + (1 - a) * plotH();
const fromX = (x) => Math.min(1, Math.max(0, (x - PAD.l) / plotW()));
const fromY = (y) => Math.min(1, Math.max(0, 1 - (y - PAD.t) / plotH()));
let grabbed = -1;

function drawEditor() {
  const w = editor.width, h = editor.height;
  ectx.clearRect(0, 0, w, h);
  if (histogram && histogram.counts.length) {       // volume-weighted, sqrt scale
    const c = histogram.counts, m = Math.sqrt(Math.max(...c)) || 1, bw = plotW() / c.length;
    ectx.fillStyle = "#3a4150";
    c.forEach((v, i) => { const bh = plotH() * Math.sqrt(v) / m; ectx.fillRect(PAD.l + i * bw, PAD.t + plotH() - bh, bw + 0.5, bh); });
  }
  if (!tf) return;
  const grad = ectx.createLinearGradient(PAD.l, 0, PAD.l + plotW(), 0);   // the colour strip
  const stops = colormapStops[tf.colormap] || ["#000000", "#ffffff"];
  stops.forEach((c, i) => grad.addColorStop(i / (stops.length - 1), c));
  ectx.fillStyle = grad; ectx.fillRect(PAD.l, h - PAD.b + 6, plotW(), 10);
  ectx.strokeStyle = "#f0f0f0"; ectx.lineWidth = 1.5; ectx.beginPath();
  tf.points.forEach(([u, a], i) => (i ? ectx.lineTo(toX(u), toY(a)) : ectx.moveTo(toX(u), toY(a))));
  ectx.stroke();
  ectx.fillStyle = "#ffcc55";
  tf.points.forEach(([u, a]) => { ectx.beginPath(); ectx.arc(toX(u), toY(a), 4, 0, 2 * Math.PI); ectx.fill(); });
}


function nearestPoint(x, y) {
  let best = -1, bd = 10;
  tf.points.forEach(([u, a], i) => { const d = Math.hypot(toX(u) - x, toY(a) - y); if (d < bd) { bd = d; best = i; } });
  return best;
}

function editorXY(ev) { const r = editor.getBoundingClientRect(); return [(ev.clientX - r.left) * editor.width / r.width, (ev.clientY - r.top) * editor.height / r.height]; }

editor.addEventListener("pointerdown", (ev) => {
  if (!tf) return;
  const [x, y] = editorXY(ev);
  grabbed = nearestPoint(x, y);
  if (grabbed < 0) {                               // a new point
    const u = fromX(x), a = fromY(y);
    tf.points.push([u, a]); tf.points.sort((p, q) => p[0] - q[0]);
    grabbed = tf.points.findIndex((p) => p[0] === u && p[1] === a);
    pendingTf = true;
  }
  editor.setPointerCapture(ev.pointerId);
  drawEditor();
});
editor.addEventListener("pointermove", (ev) => {
  if (grabbed < 0) return;
  const [x, y] = editorXY(ev), p = tf.points;
  const last = p.length - 1;
  let u = fromX(x);
  if (grabbed === 0) u = 0; else if (grabbed === last) u = 1;   // the ends stay at the ends
  else u = Math.min(p[grabbed + 1][0], Math.max(p[grabbed - 1][0], u));
  p[grabbed] = [u, fromY(y)];
  pendingTf = true;
  drawEditor();
});
editor.addEventListener("pointerup", () => { grabbed = -1; });
editor.addEventListener("dblclick", (ev) => {
  const [x, y] = editorXY(ev), i = nearestPoint(x, y);
  if (i > 0 && i < tf.points.length - 1 && tf.points.length > 2) { tf.points.splice(i, 1); pendingTf = true; drawEditor(); }
});

// ---- the other controls ------------------------------------------------------------------
function syncControls() {
  $("colormap").value = tf.colormap;
  $("log").checked = tf.log;
  $("range-lo").value = +tf.range[0].toPrecision(5);
  $("range-hi").value = +tf.range[1].toPrecision(5);
  $("density").dataset.base = $("density").dataset.base || tf.density;
  $("density").value = Math.log10(tf.density / +$("density").dataset.base);
  $("density-value").textContent = tf.density.toPrecision(4);
  drawEditor();
}

$("colormap").addEventListener("change", () => { tf.colormap = $("colormap").value; pendingTf = true; drawEditor(); });
$("density").addEventListener("input", () => {
  tf.density = +$("density").dataset.base * Math.pow(10, +$("density").value);
  $("density-value").textContent = tf.density.toPrecision(4);
  pendingTf = true;
});
$("log").addEventListener("change", () => {
  const on = $("log").checked;
  if (on === tf.log) return;
  // the same values, in the other units
  const [lo, hi] = tf.range;
  tf.range = on ? [Math.log10(Math.max(lo, hi * 1e-6)), Math.log10(hi)] : [Math.pow(10, lo), Math.pow(10, hi)];
  tf.log = on;
  syncControls();
  pendingTf = true;
});
for (const id of ["range-lo", "range-hi"]) {
  $(id).addEventListener("change", () => {
    const lo = parseFloat($("range-lo").value), hi = parseFloat($("range-hi").value);
    if (!(Number.isFinite(lo) && Number.isFinite(hi) && lo < hi)) { $("message").textContent = "range: two numbers, lo < hi"; return; }
    $("message").textContent = "";
    tf.range = [lo, hi]; pendingTf = true;
  });
}
$("denoise").addEventListener("change", () => { changed(); send({ type: "denoise", on: $("denoise").checked }); });
$("snapshot").addEventListener("click", () => {
  $("snapshot-result").textContent = "writing…";
  send({ type: "snapshot", name: $("snapshot-name").value });
});

connect();
requestAnimationFrame(flush);
