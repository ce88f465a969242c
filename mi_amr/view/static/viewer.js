// mi-amr view: the page. One connection to the server: JSON messages out
// (camera, tf, iso, denoise, mode, hybrid, snapshot, ack), JSON and frames (a header and a
// JPEG image) in. Every control change is sent at most once per animation
// frame; the server renders the newest state and drops what went stale. The
// TF editor: tf_editor.js; the iso values over its histogram: iso_control.js;
// the orbit camera's arithmetic: camera.js.
//
// Where the page lives and how it talks (its host: { root, transport }): as
// the viewer's own page, the document and a websocket to mi_amr/view/server.py
// (`websocketHost`); in a notebook, a widget's shadow root and Jupyter's comm
// channel (widget.js; mi_amr/view/widget.py bundles this file into a function
// of `widgetHost`). A transport: send(msg), and connect({ onJson, onFrame(header,
// jpegBytes), onClose }).

import { createTfEditor } from "./tf_editor.js";
import { basis, clampElevation, drawAxes } from "./camera.js";
import { createAnnotations } from "./annotations.js";
import { createSlicePanel } from "./slice.js";
import { createIsoControl } from "./iso_control.js";

// eslint-disable-next-line no-undef
const host = typeof widgetHost !== "undefined" ? widgetHost : websocketHost();
const $ = (id) => host.root.getElementById(id);
const view = $("view"), ctx = view.getContext("2d");

let camera = null;
let cameraLimits = { home: null, max_elevation: 85, floor_margin: 0.01 };   // from the server's hello
let version = 0;                 // change messages sent (the server's view version)
const changeTimes = new Map();   // version -> time it was sent (until a frame came after it)
const renderTimes = new Map();   // version -> time it was sent (until a frame rendered from it came)
let dragging = null;             // camera drag state
let pendingCamera = false;
const denoisedShown = { version: -1, full: false };   // of the newest version
const refinedShown = { version: -1, full: false };    // the newest version in the chosen mode

// Figures read by people (the stats line) and by tests and the benchmark
// (window.viewerStats): latencies from a change to the first frame after it
// (latencies) and to the first frame rendered from it (renderLatencies); from
// the last change to the first picture of the chosen mode, at preview or full
// size (refinedLatencies) and at full size (fullLatencies), and to the first
// denoised one (denoiseLatencies, fullDenoiseLatencies).
const stats = window.viewerStats = {
  frames: 0, denoisedFrames: 0, lastFrame: null, frameTimes: [], latencies: [], renderLatencies: [],
  denoiseLatencies: [], fullDenoiseLatencies: [], refinedLatencies: [], fullLatencies: [],
  lastChange: 0, errors: [], snapshots: [], ready: false, fatal: null, mode: null, frameModes: {},
  fastRenderMs: [], fastWidths: [], changes: 0,
};

function send(msg) { host.transport.send(msg); }

function changed() {             // a change message is about to go out
  version += 1;
  const now = performance.now();
  changeTimes.set(version, now);
  renderTimes.set(version, now);
  stats.lastChange = now;
  stats.changes += 1;
  if (changeTimes.size > 500) changeTimes.delete(changeTimes.keys().next().value);
  if (renderTimes.size > 500) renderTimes.delete(renderTimes.keys().next().value);
}

function flush() {               // once per animation frame: the newest camera and TF
  if (pendingCamera) { pendingCamera = false; changed(); send({ type: "camera", ...cameraMessage() }); }
  if (tfEditor.pending) { tfEditor.pending = false; changed(); send({ type: "tf", ...tfEditor.tf }); }
  if (isoControl.pending) { isoControl.pending = false; changed(); send({ type: "iso", values: isoControl.values, only: isoControl.only }); }
  if (!host.closed) requestAnimationFrame(flush);
}

function cameraMessage() {
  return { azimuth: camera.azimuth, elevation: camera.elevation, distance: camera.distance, target: camera.target };
}

// ---- connection ----------------------------------------------------------------
// The viewer's own page: the document, and a websocket to the server; the token
// comes with the page itself (no cookie: other local servers never see it).
// Binary messages: a 4-byte big-endian header length, the header's JSON, the JPEG.
function websocketHost() {
  const token = document.querySelector('meta[name="mi-amr-token"]')?.content
    || new URLSearchParams(location.search).get("token") || "";
  let ws = null;
  const transport = {
    send(msg) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg)); },
    connect({ onJson, onFrame, onClose }) {
      const proto = location.protocol === "https:" ? "wss:" : "ws:";
      ws = new WebSocket(`${proto}//${location.host}/ws?token=${encodeURIComponent(token)}`);
      ws.binaryType = "arraybuffer";
      ws.onmessage = (ev) => {
        if (typeof ev.data === "string") { onJson(JSON.parse(ev.data)); return; }
        const n = new DataView(ev.data).getUint32(0);
        onFrame(JSON.parse(new TextDecoder().decode(new Uint8Array(ev.data, 4, n))), new Uint8Array(ev.data, 4 + n));
      };
      ws.onclose = onClose;
    },
  };
  return { root: document, transport, closed: false };
}

function connect() {
  host.transport.connect({ onJson, onFrame, onClose: () => {
    if (!stats.fatal) showStatus("disconnected from the server (reload to reconnect)");
  } });
}

function showStatus(text) { const s = $("status"); s.textContent = text; s.classList.toggle("hidden", !text); }

function showFatal(text) {       // the viewer cannot go on (the load failed): stays on screen
  stats.fatal = text;
  showStatus("");
  $("fatal").textContent = text;
  $("fatal").classList.remove("hidden");
}

function onJson(msg) {
  if (msg.type === "status") {
    if (msg.state === "error") showFatal(`mi-amr view could not load the data:\n${msg.desc}`);
    else if (msg.state !== "ready") {
      const pct = msg.total ? ` ${Math.round(100 * msg.done / msg.total)}%` : "";
      showStatus(`loading: ${msg.desc}${pct}`);
    }
  } else if (msg.type === "hello") {
    camera = msg.camera;
    Object.assign(cameraLimits, msg.editor || {});
    drawAxes($("axes"), camera);
    view.width = msg.size[0]; view.height = msg.size[1];
    view.style.height = `${512 * msg.size[1] / msg.size[0]}px`;
    $("data").textContent = msg.data;
    if (msg.out_dir) $("snapshot-folder").textContent = `snapshots go to ${msg.out_dir}`;
    tfEditor.hello(msg);
    isoControl.hello(msg);
    $("denoise").checked = msg.denoise;
    $("denoise").disabled = !msg.denoiser;
    $("denoise-note").textContent = msg.denoiser ? "" : `denoiser missing: ${msg.denoiser_missing}`;
    showModes(msg);
    annotations.hello(msg);
    showStatus("rendering…");
    stats.ready = true;
  } else if (msg.type === "annotations") {
    annotations.reply(msg); slicePanel.geometry(msg);
  } else if (msg.type === "slice") {
    slicePanel.reply(msg);
  } else if (msg.type === "histogram") {
    tfEditor.histogram(msg);
  } else if (msg.type === "tf_file") {
    stats.tfFiles = (stats.tfFiles || 0) + 1;
    tfEditor.file(msg);
  } else if (msg.type === "snapshot") {
    stats.snapshots.push(msg);
    const names = msg.files.map((f) => f.split("/").pop()).join(", ");
    $("snapshot-result").textContent = `wrote ${names} (${msg.spp} spp)${(msg.notes || []).map((n) => `; ${n}`).join("")}`;
  } else if (msg.type === "error") {
    stats.errors.push(msg);
    $("message").textContent = `server: ${msg.message}`;
    if (msg.about === "field") tfEditor.error();
    if (msg.about === "snapshot") $("snapshot-result").textContent = msg.message;
    if (msg.about === "slice") slicePanel.failed();
    if (msg.camera) { camera = msg.camera; drawAxes($("axes"), camera); }   // a change that could not render, undone
    if (msg.tf) { tfEditor.setTf(msg.tf); send({ type: "histogram" }); }
    if (msg.iso) isoControl.set(msg.iso);                                  // a refused iso change: where they stay
  }
}

async function onFrame(header, jpeg) {
  const bitmap = await createImageBitmap(new Blob([jpeg], { type: "image/jpeg" }));
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
  const rendered = header.rendered ?? header.version;
  for (const [v, t] of renderTimes) {             // first frame rendered from each change (or a later one)
    if (v <= rendered) { stats.renderLatencies.push(now - t); renderTimes.delete(v); }
  }
  for (const key of ["latencies", "renderLatencies"]) {
    if (stats[key].length > 500) stats[key].splice(0, stats[key].length - 500);
  }
  const mode = header.mode ?? "scene";
  stats.frameModes[mode] = (stats.frameModes[mode] || 0) + 1;
  if (header.fast) {
    stats.fastRenderMs.push(header.render_ms); stats.fastWidths.push(header.width);
    if (stats.fastRenderMs.length > 500) { stats.fastRenderMs.shift(); stats.fastWidths.shift(); }
  }
  if (rendered === version && !header.fast && (header.mode ?? null) === stats.mode) {   // the chosen mode
    if (refinedShown.version !== version) {
      refinedShown.version = version; refinedShown.full = false;
      stats.refinedLatencies.push(now - stats.lastChange);
    }
    if (!header.preview && !refinedShown.full) {
      refinedShown.full = true;
      stats.fullLatencies.push(now - stats.lastChange);
    }
  }
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
  $("spp").textContent = sppText(header);
  const recent = stats.frameTimes.filter((t) => now - t < 1000).length;
  $("stats").textContent = `${recent} frames/s · frame ${header.render_ms} ms`;
}

function sppText(h) {            // the real count; the denoised picture's own when older; "done" at the end
  const mode = h.mode ? ` · ${h.mode}` : "";
  if (h.fast) return `moving: preview${mode}`;
  if (h.preview) return (h.denoised ? "preview, denoised" : "preview") + mode;
  const denoised = h.denoised ? (h.shown_spp ? `, denoised at ${h.shown_spp} spp` : ", denoised") : "";
  const done = h.spp >= h.max_spp && !h.shown_spp ? ` · done: refined to ${h.spp} spp` : "";
  return `${h.spp} spp${denoised}${done}${mode}`;
}

// ---- lighting mode: what the picture refines in (drags render in the fast one) -------------
// The hybrid toggle: drags ray-marched (fastModes.on) or in fastModes.off, for this view alone.
let fastMode = null, fastModes = null;
function showModes(msg) {
  const select = $("mode");
  select.replaceChildren(...(msg.modes || []).map((m) => new Option(m, m, false, m === msg.mode)));
  select.disabled = !msg.modes;
  fastMode = msg.fast_mode ?? null;
  fastModes = msg.fast_modes ?? null;
  $("hybrid").checked = msg.hybrid === true;
  $("hybrid").disabled = msg.hybrid == null;
  modeNote(msg.mode ?? null, msg.modes ? "" : msg.mode_note || "");
}

function modeNote(mode, why) {
  stats.mode = mode;
  $("mode-note").textContent = why || (fastMode && mode && fastMode !== mode
    ? `${fastMode} while the camera or the TF moves` : "");
}

$("mode").addEventListener("change", () => {
  modeNote($("mode").value, "");
  changed();
  send({ type: "mode", mode: $("mode").value });
});
$("hybrid").addEventListener("change", () => {
  if (fastModes) fastMode = $("hybrid").checked ? fastModes.on : fastModes.off;
  modeNote(stats.mode, "");
  changed();
  send({ type: "hybrid", on: $("hybrid").checked });
});

// ---- camera: orbit (drag), pan (shift/right drag), zoom (wheel) ---------------------
// Orbit and zoom keep the elevation within the poles and the eye above the
// ground (as the server does: camera.py); a pan may take it anywhere.
const clampEl = (el) => clampElevation(camera, el, cameraLimits.max_elevation, cameraLimits.floor_margin);
function cameraMoved() { pendingCamera = true; drawAxes($("axes"), camera); }

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
    const { right, up } = basis(camera), s = camera.distance / view.clientWidth;
    camera.target = camera.target.map((t, i) => t - s * (dx * right[i] - dy * up[i]));
  } else {
    camera.azimuth -= 0.4 * dx;
    camera.elevation = clampEl(camera.elevation + 0.4 * dy);
  }
  cameraMoved();
});
view.addEventListener("pointerup", () => { dragging = null; });
view.addEventListener("wheel", (ev) => {
  if (!camera) return;
  ev.preventDefault();
  camera.distance *= Math.exp(0.001 * ev.deltaY);
  camera.elevation = clampEl(camera.elevation);
  cameraMoved();
}, { passive: false });
$("reset-camera").addEventListener("click", () => {     // the view the scene started with
  if (!camera || !cameraLimits.home) return;
  const h = cameraLimits.home;
  Object.assign(camera, { azimuth: h.azimuth, elevation: h.elevation, distance: h.distance, target: [...h.target] });
  cameraMoved();
});

// ---- transfer-function editor (tf_editor.js) and the other controls ---------------------
const tfEditor = createTfEditor({ send, changed, message: (text) => { $("message").textContent = text; }, $ });
const isoControl = createIsoControl({ $, message: (text) => { $("message").textContent = text; },
  getTf: () => tfEditor.tf, redraw: () => tfEditor.redraw() });
tfEditor.decorate = isoControl.decorate;
// annotations over the picture, the clip plane and the slice panel (annotations.js, slice.js)
const slicePanel = createSlicePanel({ $, send, stats, getTf: () => tfEditor.tf });
const annotations = window.viewerAnnotations = createAnnotations({ $, send, changed, stats, getCamera: () => camera,
  getSize: () => [view.width, view.height], getTf: () => tfEditor.tf, onClip: (clip) => slicePanel.clip(clip) });

$("denoise").addEventListener("change", () => { changed(); send({ type: "denoise", on: $("denoise").checked }); });
$("snapshot").addEventListener("click", () => {
  $("snapshot-result").textContent = "writing…";
  send({ type: "snapshot", name: $("snapshot-name").value });
});

connect();
requestAnimationFrame(flush);
