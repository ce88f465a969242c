// mi-amr view: the isosurface control over the TF editor's histogram
// (docs/manual/isosurfaces.md). Up to `max` iso values, kept in the field's own
// units (the data's values, before any log10: mi_amr/view/isosurfaces.py), each
// drawn where it lies in the editor's display units (its log10 in the log10
// display): a marker on the strip under the editor and a line across the
// histogram. Click the strip (or "add iso value") to add one, drag a marker to
// move it (it stays inside the data's range), double-click it (or its × in the
// list) to remove it, or type a value in the list; "surfaces only" switches the
// gas off. The server gets { type: "iso", values, only } (at most once per
// animation frame: viewer.js); its hello (and a refusal) says where they are.

import { PAD } from "./tf_editor.js";

export function createIsoControl({ $, message, getTf, redraw }) {
  const strip = $("iso-strip"), c = strip.getContext("2d");
  let state = { values: [], only: false, max: 4, range: [0, 1], note: "", searching: true };
  let grabbed = -1, label = "value";
  const control = { pending: false, get values() { return [...state.values]; }, get only() { return state.only; } };
  const plotW = () => strip.width - PAD.l - PAD.r;
  const dataRange = () => state.range || [-Infinity, Infinity];

  // field units <-> the editor's display units <-> strip x
  const toDisplay = (v, tf) => (tf.log ? Math.log10(v) : v);
  const fromDisplay = (d, tf) => (tf.log ? Math.pow(10, d) : d);
  function xOf(v) {
    const tf = getTf(), [lo, hi] = tf.range;
    return PAD.l + (toDisplay(v, tf) - lo) / (hi - lo) * plotW();
  }
  function valueAt(x) {                           // inside the data's range
    const tf = getTf(), [lo, hi] = tf.range;
    const u = Math.min(1, Math.max(0, (x - PAD.l) / plotW()));
    const v = fromDisplay(lo + u * (hi - lo), tf);
    const [a, b] = dataRange();
    return Math.min(b, Math.max(a, v));
  }
  const fmt = (v) => (Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-2 && v !== 0) ? v.toExponential(3) : +v.toPrecision(4) + "");

  function edited() { control.pending = true; showList(false); redraw(); }

  // the strip: a triangle per value (outside the range shown: an arrow at its edge)
  function drawStrip() {
    c.clearRect(0, 0, strip.width, strip.height);
    c.fillStyle = "#15171b"; c.fillRect(PAD.l, 0, plotW(), strip.height);
    if (!getTf()) return;
    c.font = "10px system-ui, sans-serif"; c.textBaseline = "middle";
    if (!state.values.length && !state.note) {
      c.fillStyle = "#6b7280"; c.textAlign = "center";
      c.fillText("click here to add an isosurface", PAD.l + plotW() / 2, strip.height / 2);
    }
    state.values.forEach((v, i) => {
      const x = xOf(v), h = strip.height;
      c.fillStyle = i === grabbed ? "#ffffff" : "#5ad1ff";
      c.beginPath();
      if (x < PAD.l) { c.moveTo(PAD.l, h / 2); c.lineTo(PAD.l + 8, 3); c.lineTo(PAD.l + 8, h - 3); }
      else if (x > PAD.l + plotW()) { const r = PAD.l + plotW(); c.moveTo(r, h / 2); c.lineTo(r - 8, 3); c.lineTo(r - 8, h - 3); }
      else { c.moveTo(x, 2); c.lineTo(x - 6, h - 2); c.lineTo(x + 6, h - 2); }
      c.fill();
    });
  }

  // over the histogram (the TF editor calls this after it draws)
  control.decorate = (ctx, bottom) => {
    drawStrip();
    const tf = getTf();
    if (!tf) return;
    ctx.save(); ctx.strokeStyle = "#5ad1ff"; ctx.lineWidth = 1.5; ctx.setLineDash([4, 3]);
    for (const v of state.values) {
      const x = xOf(v);
      if (x < PAD.l || x > PAD.l + plotW()) continue;
      ctx.beginPath(); ctx.moveTo(x, PAD.t); ctx.lineTo(x, bottom); ctx.stroke();
    }
    ctx.restore();
  };

  // the list: each value typed or removed; add; surfaces only
  function showList(rebuild = true) {
    const list = $("iso-list");
    if (rebuild || list.children.length !== state.values.length) {
      list.replaceChildren(...state.values.map((v, i) => {
        const item = document.createElement("span"), input = document.createElement("input"), x = document.createElement("button");
        item.className = "iso-item";
        input.size = 9; input.dataset.testid = `iso-value-${i}`; input.setAttribute("data-testid", `iso-value-${i}`);
        input.setAttribute("aria-label", `iso value ${i + 1} (${label})`);
        input.addEventListener("change", () => {
          const w = parseFloat(input.value), [lo, hi] = dataRange();
          if (!(Number.isFinite(w) && w >= lo && w <= hi)) {
            message(`iso: a number from ${fmt(lo)} to ${fmt(hi)} (${label})`); input.value = fmt(state.values[i]); return;
          }
          message(""); state.values[i] = w; edited();
        });
        x.textContent = "×"; x.title = "remove this isosurface"; x.setAttribute("data-testid", `iso-remove-${i}`);
        x.addEventListener("click", () => remove(i));
        item.append(input, x);
        return item;
      }));
    }
    [...list.querySelectorAll("input")].forEach((input, i) => { if (input !== document.activeElement || grabbed >= 0) input.value = fmt(state.values[i]); });
    const off = Boolean(state.note);
    $("iso-add").disabled = off || state.values.length >= state.max;
    $("iso-only").disabled = off;
    $("iso-only").checked = state.only;
    $("iso-note").textContent = state.note || (state.values.length ? "" : `values in ${label}`);
    strip.dataset.values = JSON.stringify(state.values);
  }

  function add(v) {
    if (state.note) { message(`iso: ${state.note}`); return -1; }
    if (state.values.length >= state.max) { message(`iso: at most ${state.max} values`); return -1; }
    if (!state.searching) {                       // the first value: the passes are recorded again, once
      message("isosurfaces: recording the passes with the surface search (once; a few seconds)");
      state.searching = true;
    }
    state.values.push(v); edited(); showList();
    return state.values.length - 1;
  }
  function remove(i) { state.values.splice(i, 1); grabbed = -1; edited(); showList(); }

  function nearest(x) {
    let best = -1, bd = 8;
    state.values.forEach((v, i) => { const d = Math.abs(Math.min(Math.max(xOf(v), PAD.l), PAD.l + plotW()) - x); if (d < bd) { bd = d; best = i; } });
    return best;
  }
  function stripX(ev) { const r = strip.getBoundingClientRect(); return (ev.clientX - r.left) * strip.width / r.width; }

  strip.addEventListener("pointerdown", (ev) => {
    if (!getTf() || state.note) return;
    const x = stripX(ev);
    grabbed = nearest(x);
    if (grabbed < 0) grabbed = add(valueAt(x));
    if (grabbed >= 0) strip.setPointerCapture(ev.pointerId);
    drawStrip();
  });
  strip.addEventListener("pointermove", (ev) => {
    if (grabbed < 0) return;
    state.values[grabbed] = valueAt(stripX(ev));
    edited();
  });
  strip.addEventListener("pointerup", () => { grabbed = -1; drawStrip(); });
  strip.addEventListener("dblclick", (ev) => { const i = nearest(stripX(ev)); if (i >= 0) remove(i); });
  $("iso-add").addEventListener("click", () => {     // the middle of the range shown
    const tf = getTf();
    if (tf) add(valueAt(PAD.l + plotW() / 2));
  });
  $("iso-only").addEventListener("change", () => { state.only = $("iso-only").checked; control.pending = true; });

  // the server's state (a hello, or a refused change): where the values are
  control.set = (iso) => {
    if (!iso) return;
    state = { ...iso, values: [...iso.values] };
    grabbed = -1; control.pending = false;
    showList(); redraw();
  };
  control.hello = (msg) => {                       // the field's name and units label the values
    const extras = msg.editor || {}, name = extras.field ? extras.field.split(",").pop() : "value";
    label = `${name}${extras.units ? ` (${extras.units})` : ""}`;
    control.set(msg.iso || { values: [], only: false, max: 0, range: [0, 1], note: "this server has no isosurfaces",
      searching: false });
  };
  return control;
}
