// mi-amr view: annotations over the picture (the domain's outline, axes in
// physical units, the boxes of each AMR level, the TF's legend) and the
// clip-plane control. The geometry comes from the server in world units
// (an "annotations" reply, mi_amr/view/view_annotations.py, once per field); it is projected
// here with the view's own camera exactly as Mitsuba's perspective sensor
// does (mi_amr/annotations.py PinholeCamera.project: look-at camera, fov
// along x, pixel (0, 0) the film's upper left corner).

import { basis } from "./camera.js";
import { colourAt, valueTicks } from "./tf_editor.js";

const DEG = Math.PI / 180;
const EDGES = [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]];

// World points [[x, y, z], ...] -> [[px, py, depth], ...] for an orbit camera
// ({target, up, azimuth, elevation, distance, fov}) and a film [width, height].
export function project(camera, size, points) {
  const { right, up, back } = basis(camera);
  const o = camera.target.map((t, i) => t + camera.distance * back[i]);
  const tx = Math.tan(0.5 * camera.fov * DEG), ty = tx / (size[0] / size[1]);
  return points.map((p) => {
    const d = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
    const z = -(d[0] * back[0] + d[1] * back[1] + d[2] * back[2]);
    const x = d[0] * right[0] + d[1] * right[1] + d[2] * right[2];
    const y = d[0] * up[0] + d[1] * up[1] + d[2] * up[2];
    return [0.5 * size[0] * (1 + x / (z * tx)), 0.5 * size[1] * (1 - y / (z * ty)), z];
  });
}

// A world segment [a, b] as a pixel segment, clipped to the part in front of the camera (or null).
function segment(camera, size, a, b, near = 1e-6) {
  const [pa, pb] = project(camera, size, [a, b]);
  if (pa[2] < near && pb[2] < near) return null;
  if (pa[2] < near || pb[2] < near) {
    const t = (near - pa[2]) / (pb[2] - pa[2]);
    const m = a.map((x, i) => x + t * (b[i] - x));
    const [pm] = project(camera, size, [m]);
    return pa[2] < near ? [pm, pb] : [pa, pm];
  }
  return [pa, pb];
}

function boxCorners(lo, hi) {
  return [0, 1, 2, 3, 4, 5, 6, 7].map((c) => [c & 1 ? hi[0] : lo[0], c & 2 ? hi[1] : lo[1], c & 4 ? hi[2] : lo[2]]);
}

// The annotations' state, controls and overlay. `ctx`: { $, send, changed, getCamera, getSize, getTf,
// stats, onClip(clip) }.
export function createAnnotations(ctx) {
  const { $, send } = ctx;
  const overlay = $("overlay"), legend = $("legend");
  const state = { geometry: null, shown: { outline: true, axes: false, levels: false, legend: true },
                  levelFilter: null, burnIn: false, drawnKey: "", legendKey: "", stops: null, clip: null };
  const toggles = ["outline", "axes", "levels", "legend"];

  function sendAnnotate() {
    const f = state.levelFilter;
    send({ type: "annotate", ...state.shown, burn_in: state.burnIn,
           level_filter: f === null ? null : [...f].sort((a, b) => a - b) });
  }

  function draw() {
    // drawn at the picture's displayed size (CSS pixels, sharp on any screen): the
    // projection of a film of that size is the film's, scaled
    const camera = ctx.getCamera(), film = ctx.getSize(), v = $("view");
    const size = [v.clientWidth || film[0], v.clientHeight || film[1]], dpr = window.devicePixelRatio || 1;
    state.drawnKey = JSON.stringify([camera, film, size, state.shown, state.levelFilter && [...state.levelFilter]]);
    overlay.style.width = `${size[0]}px`; overlay.style.height = `${size[1]}px`;
    overlay.width = Math.round(size[0] * dpr); overlay.height = Math.round(size[1] * dpr);
    const c = overlay.getContext("2d");
    c.setTransform(dpr, 0, 0, dpr, 0, 0);
    c.clearRect(0, 0, size[0], size[1]);
    legend.classList.toggle("hidden", !state.shown.legend);
    if (!camera || !state.geometry) return;
    const g = state.geometry;
    const lines = (segs, colour, width) => {
      c.strokeStyle = colour; c.lineWidth = width; c.beginPath();
      for (const [a, b] of segs) {
        const s = segment(camera, size, a, b);
        if (s) { c.moveTo(s[0][0], s[0][1]); c.lineTo(s[1][0], s[1][1]); }
      }
      c.stroke();
    };
    if (state.shown.levels) {
      for (const lv of g.levels) {
        if (state.levelFilter && !state.levelFilter.has(lv.refinement)) continue;
        const segs = [];
        for (let k = 0; k + 6 <= lv.boxes.length; k += 6) {
          const q = boxCorners(lv.boxes.slice(k, k + 3), lv.boxes.slice(k + 3, k + 6));
          for (const [i, j] of EDGES) segs.push([q[i], q[j]]);
        }
        lines(segs, lv.colour, 0.8);
      }
    }
    if (state.shown.outline) {
      const q = [];
      for (let k = 0; k < 8; k++) q.push(g.corners.slice(3 * k, 3 * k + 3));
      lines(EDGES.map(([i, j]) => [q[i], q[j]]), "#ffffff", 1.2);
    }
    if (state.shown.axes) {
      c.font = "11px system-ui, sans-serif";
      for (const ax of g.axes) {
        const s = ax.segment;
        lines([[s.slice(0, 3), s.slice(3, 6)]], ax.colour, 1.5);
        c.fillStyle = ax.colour; c.textAlign = "center"; c.textBaseline = "bottom";
        const ticks = [];
        for (let k = 0; k + 3 <= ax.ticks.length; k += 3) ticks.push(ax.ticks.slice(k, k + 3));
        project(camera, size, ticks).forEach(([x, y, z], k) => { if (z > 0) c.fillText(ax.labels[k], x, y); });
        const [end] = project(camera, size, [s.slice(3, 6)]);
        if (end[2] > 0) { c.textAlign = "left"; c.textBaseline = "top"; c.fillText(ax.name, end[0] + 3, end[1] + 2); }
      }
    }
  }

  // The TF's legend: its colours over the display range (tf_editor.js's colours and
  // value ticks, the view's own TF), the opacity as a curve, the value axis's label.
  function drawLegend() {
    const tf = ctx.getTf(), dpr = window.devicePixelRatio || 1, w = 240, h = 54, strip = 22;
    legend.style.width = `${w}px`; legend.style.height = `${h}px`;
    legend.width = Math.round(w * dpr); legend.height = Math.round(h * dpr);
    const c = legend.getContext("2d");
    c.setTransform(dpr, 0, 0, dpr, 0, 0);
    c.clearRect(0, 0, w, h);
    if (!tf || !state.stops) return;
    const cm = state.stops[tf.colormap] || ["#000000", "#ffffff"], x0 = 6, x1 = w - 6;
    c.fillStyle = "rgba(0, 0, 0, 0.55)"; c.fillRect(0, 0, w, h);
    for (let x = x0; x < x1; x++) {
      const rgb = colourAt(tf.points, cm, (x + 0.5 - x0) / (x1 - x0));
      c.fillStyle = `rgb(${rgb.map((v) => Math.round(255 * Math.max(0, Math.min(1, v)))).join(",")})`;
      c.fillRect(x, 4, 1, strip);
    }
    c.strokeStyle = "#ffffff"; c.lineWidth = 1.2; c.beginPath();
    tf.points.forEach(([u, a], i) => { const x = x0 + u * (x1 - x0), y = 4 + strip * (1 - a); i ? c.lineTo(x, y) : c.moveTo(x, y); });
    c.stroke();
    c.fillStyle = "#e4e4e4"; c.font = "10px system-ui, sans-serif"; c.textBaseline = "top";
    for (const [u, label] of valueTicks(tf.range, tf.log)) {
      c.textAlign = u < 0.05 ? "left" : u > 0.95 ? "right" : "center";
      c.fillRect(x0 + u * (x1 - x0), 4 + strip, 1, 3);
      c.fillText(label, x0 + u * (x1 - x0), 8 + strip);
    }
    c.textAlign = "center"; c.fillStyle = "#aab";
    c.fillText($("tf-editor").dataset.axis || "", w / 2, 20 + strip);
    state.legendKey = JSON.stringify([tf, dpr]);
    ctx.stats.legends = (ctx.stats.legends || 0) + 1;
  }

  function levelFilterControls() {           // one checkbox per refinement level, in its colour
    const box = $("level-filter");
    const levels = [...state.geometry.levels].sort((a, b) => a.refinement - b.refinement);
    box.replaceChildren(...levels.map((lv) => {
      const label = document.createElement("label");
      const input = document.createElement("input");
      input.type = "checkbox"; input.checked = !state.levelFilter || state.levelFilter.has(lv.refinement);
      input.setAttribute("data-testid", `level-${lv.refinement}`);
      input.addEventListener("change", () => {
        const all = state.geometry.levels.map((l) => l.refinement);
        const on = new Set(state.levelFilter || all);
        if (input.checked) on.add(lv.refinement); else on.delete(lv.refinement);
        state.levelFilter = on.size === all.length ? null : on;
        sendAnnotate(); draw();
      });
      label.style.color = lv.colour;
      label.title = `${lv.blocks} blocks${lv.note ? ": " + lv.note : ""}`;
      label.append(input, ` ${lv.refinement}`);
      return label;
    }));
  }

  for (const name of toggles) {
    $(`show-${name}`).checked = state.shown[name];
    $(`show-${name}`).addEventListener("change", () => { state.shown[name] = $(`show-${name}`).checked; sendAnnotate(); draw(); });
  }
  $("burn-in").addEventListener("change", () => { state.burnIn = $("burn-in").checked; sendAnnotate(); });

  // ---- the clip plane: an axis (or a free normal) and an offset along it ------------------
  function clipNormal() {
    const axis = $("clip-axis").value;
    if (axis === "off") return null;
    if (axis === "free") return ["clip-nx", "clip-ny", "clip-nz"].map((id) => +$(id).value);
    const n = [0, 0, 0]; n["xyz".indexOf(axis)] = $("clip-flip").checked ? -1 : 1;
    return n;
  }
  function clipRange(n) {                    // the offsets that cut the data: n . corners
    if (!state.geometry) return [-1, 1];
    const [lo, hi] = state.geometry.box, q = boxCorners(lo, hi).map((p) => n[0] * p[0] + n[1] * p[1] + n[2] * p[2]);
    return [Math.min(...q), Math.max(...q)];
  }
  function clipChanged(fromSlider) {
    const n = clipNormal();
    $("clip-free").classList.toggle("hidden", $("clip-axis").value !== "free");
    const slider = $("clip-offset");
    slider.disabled = !n;
    if (!n) { state.clip = null; ctx.changed(); send({ type: "clip", normal: null }); ctx.onClip(null); return; }
    const [a, b] = clipRange(n);
    if (!fromSlider) { slider.min = 0; slider.max = 1000; }
    const offset = a + (b - a) * (+slider.value / 1000);
    $("clip-value").textContent = offset.toPrecision(4);
    state.clip = { normal: n, offset };
    ctx.changed();
    send({ type: "clip", normal: n, offset });
    ctx.onClip(state.clip);
  }
  for (const id of ["clip-axis", "clip-flip", "clip-nx", "clip-ny", "clip-nz"]) $(id).addEventListener("change", () => clipChanged(false));
  $("clip-offset").addEventListener("input", () => clipChanged(true));

  function tick() {                          // redraw when the camera or the film changed; a new legend after a TF change
    const v = $("view"), size = [v.clientWidth || ctx.getSize()[0], v.clientHeight || ctx.getSize()[1]];
    const key = JSON.stringify([ctx.getCamera(), ctx.getSize(), size, state.shown, state.levelFilter && [...state.levelFilter]]);
    if (key !== state.drawnKey) draw();
    if (state.shown.legend && JSON.stringify([ctx.getTf(), window.devicePixelRatio || 1]) !== state.legendKey) drawLegend();
    requestAnimationFrame(tick);
  }

  const api = {
    project,
    state,
    hello(msg) {
      state.geometry = null; state.stops = msg.colormap_stops; state.legendKey = "";
      send({ type: "annotations" }); sendAnnotate();
    },
    reply(msg) {
      const first = !state.geometry;
      state.geometry = msg;
      if (first) levelFilterControls();
      ctx.stats.annotations = (ctx.stats.annotations || 0) + 1;
      draw();
    },
    draw,
  };
  requestAnimationFrame(tick);
  return api;
}
