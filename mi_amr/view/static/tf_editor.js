// mi-amr view: the transfer-function editor (as ParaView's and yt's). Opacity
// points over the display value u in [0, 1] of the range (drag to move, click
// to add, double-click to remove, click to select and give it a colour), the
// volume-weighted histogram under them with the shares below and above the
// range, a value axis in the field's units (powers of ten in the log10
// display) and an opacity axis; presets, colormaps, log10 (or why not),
// range, density (slider and number), save and load as the TF JSON that
// `mi-amr render --tf` reads, and the data's fields. The TF's units and
// tables: mi_amr/view/tf_spec.py; messages: mi_amr/view/protocol.py. What else
// draws over the histogram (the iso values: iso_control.js) is the `decorate`
// function, called with the context and the plot's bottom after each drawing.

// The plot inside the canvas (tests drag points at these offsets; iso_control.js's strip shares them).
export const PAD = { l: 8, r: 8, t: 8, b: 58 };
const SUPER = { "-": "⁻", 0: "⁰", 1: "¹", 2: "²", 3: "³", 4: "⁴", 5: "⁵", 6: "⁶", 7: "⁷", 8: "⁸", 9: "⁹" };

function hexRgb(h) { return [1, 3, 5].map((i) => parseInt(h.slice(i, i + 2), 16) / 255); }
function rgbHex(c) { return "#" + c.map((x) => Math.round(255 * Math.max(0, Math.min(1, x))).toString(16).padStart(2, "0")).join(""); }

// Colour of a colormap's stops (equally spaced over u) at u.
function stopColour(stops, u) {
  const x = Math.max(0, Math.min(1, u)) * (stops.length - 1), i = Math.min(stops.length - 2, Math.floor(x)), t = x - i;
  const a = hexRgb(stops[i]), b = hexRgb(stops[i + 1]);
  return a.map((v, k) => v + t * (b[k] - v));
}

// Colour at u (tf_spec.point_colours): between neighbouring points of which one
// has its own colour, the two blended; elsewhere the colormap.
export function colourAt(points, stops, u) {
  const base = (x) => stopColour(stops, x);
  if (points.length < 2 || !points.some((p) => p.length > 2)) return base(u);
  let i = 0;
  while (i < points.length - 2 && points[i + 1][0] <= u) i += 1;
  const p = points[i], q = points[i + 1];
  if (p.length < 3 && q.length < 3) return base(u);
  const cp = p.length > 2 ? hexRgb(p[2]) : base(p[0]), cq = q.length > 2 ? hexRgb(q[2]) : base(q[0]);
  const w = q[0] - p[0], t = w > 0 ? Math.max(0, Math.min(1, (u - p[0]) / w)) : 0;
  return cp.map((v, k) => v + t * (cq[k] - v));
}

// N layers over u in [0, 1] as opacity points (tf_spec.layer_points): per layer
// a peak at (k + 1/2) / n, shoulders one deviation (width / n) off, feet at 0
// 2.5 deviations off (a Gaussian lowered to end there), opacity low^(1 - k / (n - 1)) rising to 1 (the last layer
// holds it up to u = 1), each point in its layer's colour from the colormap.
export function layerPoints(n, stops, width = 0.18, low = 0.02) {
  const sigma = width / n, foot = Math.min(2.5 * sigma, 0.5 / n - 1e-4), shoulder = Math.min(sigma, 0.8 * foot);
  const pts = [[0, 0]];
  for (let k = 0; k < n; k++) {
    const c = (k + 0.5) / n, t = n > 1 ? k / (n - 1) : 1, a = Math.pow(low, 1 - t), colour = rgbHex(stopColour(stops, t));
    const gCut = Math.exp(-0.5 * 2.5 * 2.5), s = a * (Math.exp(-0.5 * (shoulder / sigma) ** 2) - gCut) / (1 - gCut);
    pts.push([c - foot, 0, colour], [c - shoulder, s, colour], [c, a, colour]);
    if (k === n - 1) pts.push([1, a, colour]); else pts.push([c + shoulder, s, colour], [c + foot, 0, colour]);
  }
  return pts;
}

// About n round ticks over [lo, hi].
function niceTicks(lo, hi, n) {
  const raw = (hi - lo) / n, mag = Math.pow(10, Math.floor(Math.log10(raw))), f = raw / mag;
  const step = (f < 1.5 ? 1 : f < 3 ? 2 : f < 7 ? 5 : 10) * mag, out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * step; v += step) out.push(Math.abs(v) < 1e-12 * step ? 0 : v);
  return out;
}

function fmt(v) { return Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-2 && v !== 0) ? v.toExponential(1) : +v.toPrecision(3) + ""; }
function power(k) { return "10" + String(k).split("").map((c) => SUPER[c] || c).join(""); }

// The value axis: [position u, label] pairs for the display range.
export function valueTicks(range, log) {
  const [lo, hi] = range;
  if (log) {
    const ints = [];
    for (let k = Math.ceil(lo); k <= Math.floor(hi); k++) ints.push(k);
    const step = Math.max(1, Math.ceil(ints.length / 6));
    if (ints.length >= 2) return ints.filter((k) => (k - ints[0]) % step === 0).map((k) => [(k - lo) / (hi - lo), power(k)]);
    return niceTicks(lo, hi, 4).map((x) => [(x - lo) / (hi - lo), fmt(Math.pow(10, x))]);
  }
  return niceTicks(lo, hi, 5).map((x) => [(x - lo) / (hi - lo), fmt(x)]);
}

// `$`: the element of an id in the viewer's own root (the page's document, or a
// notebook widget's shadow root: widget.py).
export function createTfEditor({ send, changed, message, $ = (id) => document.getElementById(id), decorate = null }) {
  const canvas = $("tf-editor"), c = canvas.getContext("2d");
  let tf = null, histogram = null, stops = {}, extras = {}, grabbed = -1, selected = -1;
  const plotW = () => canvas.width - PAD.l - PAD.r, plotH = () => canvas.height - PAD.t - PAD.b;
  const toX = (u) => PAD.l + u * plotW(), toY = (a) => PAD.t + (1 - a) * plotH();
  const fromX = (x) => Math.min(1, Math.max(0, (x - PAD.l) / plotW()));
  const fromY = (y) => Math.min(1, Math.max(0, 1 - (y - PAD.t) / plotH()));
  const editor = { pending: false, get tf() { return tf; }, decorate, redraw: () => draw() };

  function edited() { editor.pending = true; draw(); }

  function draw() {
    const w = canvas.width, h = canvas.height, bottom = PAD.t + plotH();
    c.clearRect(0, 0, w, h);
    if (histogram && histogram.counts.length) {       // volume-weighted, sqrt scale
      const n = histogram.counts, m = Math.sqrt(Math.max(...n)) || 1, bw = plotW() / n.length;
      c.fillStyle = "#3a4150";
      n.forEach((v, i) => { const bh = plotH() * Math.sqrt(v) / m; c.fillRect(PAD.l + i * bw, bottom - bh, bw + 0.5, bh); });
    }
    c.font = "10px system-ui, sans-serif"; c.fillStyle = "#8a93a3"; c.strokeStyle = "#2c313b"; c.lineWidth = 1;
    c.textAlign = "left"; c.textBaseline = "middle";
    for (const a of [0, 0.25, 0.5, 0.75, 1]) {           // the opacity axis, inside the plot
      c.beginPath(); c.moveTo(PAD.l, toY(a)); c.lineTo(PAD.l + plotW(), toY(a)); c.stroke();
      c.fillText(a === 0 ? "" : String(a), PAD.l + 2, toY(a) + (a === 1 ? 6 : 0));
    }
    c.save(); c.translate(w - 3, PAD.t + plotH() / 2); c.rotate(-Math.PI / 2); c.textAlign = "center";
    c.textBaseline = "bottom"; c.fillText("opacity", 0, 0); c.restore();
    if (!tf) return;
    const cm = stops[tf.colormap] || ["#000000", "#ffffff"];
    for (let x = 0; x < plotW(); x++) {                  // the colour strip: colormap and point colours
      c.fillStyle = rgbHex(colourAt(tf.points, cm, x / (plotW() - 1)));
      c.fillRect(PAD.l + x, bottom + 3, 1.5, 9);
    }
    c.fillStyle = "#c8cdd6"; c.strokeStyle = "#c8cdd6"; c.textAlign = "center"; c.textBaseline = "top";
    for (const [u, label] of valueTicks(tf.range, tf.log)) {   // the value axis
      c.beginPath(); c.moveTo(toX(u), bottom + 13); c.lineTo(toX(u), bottom + 17); c.stroke();
      c.textAlign = u < 0.05 ? "left" : u > 0.95 ? "right" : "center";
      c.fillText(label, toX(u), bottom + 19);
    }
    c.textAlign = "center"; c.fillStyle = "#8a93a3";
    canvas.dataset.axis = axisLabel();
    c.fillText(canvas.dataset.axis, PAD.l + plotW() / 2, bottom + 33);
    c.strokeStyle = "#f0f0f0"; c.lineWidth = 1.5; c.beginPath();
    tf.points.forEach(([u, a], i) => (i ? c.lineTo(toX(u), toY(a)) : c.moveTo(toX(u), toY(a))));
    c.stroke();
    tf.points.forEach((p, i) => {
      c.fillStyle = p.length > 2 ? p[2] : "#ffcc55"; c.beginPath(); c.arc(toX(p[0]), toY(p[1]), 4, 0, 2 * Math.PI); c.fill();
      if (i === selected) { c.strokeStyle = "#ffffff"; c.lineWidth = 1.5; c.beginPath(); c.arc(toX(p[0]), toY(p[1]), 7, 0, 2 * Math.PI); c.stroke(); }
    });
    if (editor.decorate) editor.decorate(c, bottom);
  }

  function axisLabel() {
    const name = extras.field ? extras.field.split(",").pop() : "value";
    const units = extras.units ? ` (${extras.units})` : "";
    return `${name}${units}${tf.log ? ", log scale" : ""}`;
  }

  function showShares() {
    const s = $("tf-shares");
    if (!histogram || histogram.below === undefined) { s.textContent = ""; return; }
    const pct = (x) => `${(100 * x).toFixed(2)}%`;
    s.textContent = `volume below the range: ${pct(histogram.below)} · above: ${pct(histogram.above)}`;
    s.dataset.below = histogram.below; s.dataset.above = histogram.above;
  }

  function selectPoint(i) {
    selected = i;
    const input = $("point-colour");
    input.disabled = i < 0; $("point-colour-clear").disabled = i < 0 || tf.points[i].length < 3;
    if (i >= 0) input.value = tf.points[i].length > 2 ? tf.points[i][2] : rgbHex(colourAt(tf.points, stops[tf.colormap] || ["#000000", "#ffffff"], tf.points[i][0]));
  }

  function sync() {                                  // the controls from tf
    $("colormap").value = tf.colormap;
    $("log").checked = tf.log;
    $("range-lo").value = +tf.range[0].toPrecision(5);
    $("range-hi").value = +tf.range[1].toPrecision(5);
    const slider = $("density");
    slider.dataset.base = slider.dataset.base || tf.density;
    slider.value = Math.max(-2, Math.min(2, Math.log10(tf.density / +slider.dataset.base)));
    $("density-number").value = +tf.density.toPrecision(6);
    selectPoint(selected < tf.points.length ? selected : -1);
    draw();
  }

  function nearestPoint(x, y) {
    let best = -1, bd = 10;
    tf.points.forEach(([u, a], i) => { const d = Math.hypot(toX(u) - x, toY(a) - y); if (d < bd) { bd = d; best = i; } });
    return best;
  }
  function canvasXY(ev) { const r = canvas.getBoundingClientRect(); return [(ev.clientX - r.left) * canvas.width / r.width, (ev.clientY - r.top) * canvas.height / r.height]; }

  canvas.addEventListener("pointerdown", (ev) => {
    if (!tf) return;
    const [x, y] = canvasXY(ev);
    grabbed = nearestPoint(x, y);
    if (grabbed < 0) {                               // a new point
      const p = [fromX(x), fromY(y)];
      tf.points.push(p); tf.points.sort((a, b) => a[0] - b[0]);
      grabbed = tf.points.indexOf(p);
      editor.pending = true;
    }
    selectPoint(grabbed);
    canvas.setPointerCapture(ev.pointerId);
    draw();
  });
  canvas.addEventListener("pointermove", (ev) => {
    if (grabbed < 0) return;
    const [x, y] = canvasXY(ev), p = tf.points, last = p.length - 1;
    let u = fromX(x);
    if (grabbed === 0) u = 0; else if (grabbed === last) u = 1;   // the ends stay at the ends
    else u = Math.min(p[grabbed + 1][0], Math.max(p[grabbed - 1][0], u));
    p[grabbed] = [u, fromY(y), ...p[grabbed].slice(2)];
    edited();
  });
  canvas.addEventListener("pointerup", () => { grabbed = -1; });
  canvas.addEventListener("dblclick", (ev) => {
    const [x, y] = canvasXY(ev), i = nearestPoint(x, y);
    if (i > 0 && i < tf.points.length - 1 && tf.points.length > 2) { tf.points.splice(i, 1); selectPoint(-1); edited(); }
  });

  $("point-colour").addEventListener("input", () => {
    if (selected < 0 || !tf) return;
    const p = tf.points[selected];
    tf.points[selected] = [p[0], p[1], $("point-colour").value.toLowerCase()];
    $("point-colour-clear").disabled = false;
    edited();
  });
  $("point-colour-clear").addEventListener("click", () => {
    if (selected < 0 || !tf) return;
    tf.points[selected] = tf.points[selected].slice(0, 2);
    selectPoint(selected); edited();
  });
  $("preset").addEventListener("change", () => {
    const p = (extras.presets || {})[$("preset").value];
    $("preset").value = "";
    if (!p || !tf) return;
    if ([...$("colormap").options].some((o) => o.value === p.colormap)) tf.colormap = p.colormap;
    tf.points = p.points.map((q) => q.slice(0, 2));
    selectPoint(-1); sync(); editor.pending = true;
  });
  $("add-layers").addEventListener("click", () => {
    const n = Math.round(+$("layers-n").value);
    if (!tf || !(n >= 1 && n <= 32)) { message("layers: a whole number from 1 to 32"); return; }
    message("");
    tf.points = layerPoints(n, stops[tf.colormap] || stops.viridis || ["#000000", "#ffffff"]);
    selectPoint(-1); edited();
  });
  $("colormap").addEventListener("change", () => { tf.colormap = $("colormap").value; selectPoint(selected); edited(); });
  $("density").addEventListener("input", () => {
    tf.density = +$("density").dataset.base * Math.pow(10, +$("density").value);
    $("density-number").value = +tf.density.toPrecision(6);
    editor.pending = true;
  });
  $("density-number").addEventListener("change", () => {
    const d = parseFloat($("density-number").value);
    if (!(Number.isFinite(d) && d > 0)) { message("density: a number above 0"); return; }
    message("");
    tf.density = d; sync(); editor.pending = true;
  });
  $("log").addEventListener("change", () => {
    const on = $("log").checked;
    if (on === tf.log) return;
    const [lo, hi] = tf.range;                       // the same values, in the other units
    tf.range = on ? [Math.log10(Math.max(lo, hi * 1e-6)), Math.log10(hi)] : [Math.pow(10, lo), Math.pow(10, hi)];
    tf.log = on;
    sync(); editor.pending = true;
  });
  for (const id of ["range-lo", "range-hi"]) {
    $(id).addEventListener("change", () => {
      const lo = parseFloat($("range-lo").value), hi = parseFloat($("range-hi").value);
      if (!(Number.isFinite(lo) && Number.isFinite(hi) && lo < hi)) { message("range: two numbers, lo < hi"); return; }
      message("");
      tf.range = [lo, hi]; editor.pending = true; draw();
    });
  }
  $("tf-save").addEventListener("click", () => send({ type: "tf_save" }));
  $("tf-load-button").addEventListener("click", () => $("tf-load").click());
  $("tf-load").addEventListener("change", async () => {
    const file = $("tf-load").files[0];
    $("tf-load").value = "";
    if (!file) return;
    const text = await file.text();
    if (text.length > 60000) { message(`${file.name}: too large for the editor (over 60 kB)`); return; }
    message(""); changed(); send({ type: "tf_load", text });
  });
  $("field").addEventListener("change", () => {
    message(`loading field ${$("field").value}…`);
    send({ type: "field", name: $("field").value });
  });

  // A new Hello: the scene's colormaps and fields, the view's TF.
  editor.hello = (msg) => {
    extras = msg.editor || {};
    stops = msg.colormap_stops;
    $("colormap").innerHTML = msg.colormaps.map((n) => `<option>${n}</option>`).join("");
    $("preset").innerHTML = `<option value="">preset…</option>` +
      Object.keys(extras.presets || {}).map((n) => `<option>${n}</option>`).join("");
    $("log").disabled = !msg.log_available;
    $("log-note").textContent = msg.log_available ? "" : (extras.log_note || "log10 is off for these data");
    const fields = extras.fields || [];
    const sel = $("field");
    sel.innerHTML = (fields.length ? fields : [extras.field || "value"]).map((n) => `<option>${n}</option>`).join("");
    sel.value = extras.field || sel.options[0].value;
    sel.disabled = fields.length < 2;
    $("field-note").textContent = fields.length < 2 ? (extras.field_note || "one field only") : "";
    if ($("message").textContent.startsWith("loading field")) message("");
    $("density").dataset.base = "";
    editor.setTf(msg.tf);
    send({ type: "histogram" });
  };
  editor.setTf = (spec) => { tf = spec; editor.pending = false; sync(); };
  editor.histogram = (msg) => {
    histogram = msg;
    if (msg.density !== undefined && msg.density !== null && tf && msg.log === tf.log) {
      tf.range = [...msg.range]; tf.density = msg.density;       // planned again by the server (log10 toggle)
      sync();
    }
    showShares(); draw();
  };
  editor.error = () => { if (extras.field) $("field").value = extras.field; };
  // The server's TF file: offered as a download.
  editor.file = (msg) => {
    const a = document.createElement("a");
    a.href = URL.createObjectURL(new Blob([msg.text], { type: "application/json" }));
    a.download = "transfer-function.json";
    document.body.appendChild(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 10000);
  };
  return editor;
}
