// mi-amr view: the slice panel beside the picture. The field on an
// axis-aligned plane (at the clip plane's position while the clip is
// axis-aligned) through the medium's own reconstruction, coloured by the
// view's TF, with the AMR level boundaries drawn (mi_amr/slicing.py, served
// as a "slice" reply); the value and the level under the cursor.

function decode(b64, Type) {
  const bytes = Uint8Array.from(atob(b64), (ch) => ch.charCodeAt(0));
  return new Type(bytes.buffer);
}

// `ctx`: { $, send, stats, getTf }.
export function createSlicePanel(ctx) {
  const { $, send } = ctx;
  const canvas = $("slice"), readout = $("slice-readout");
  const state = { reply: null, values: null, levels: null, asked: null, pending: false, box: null, tf: null,
                  exact: null };     // a position set by the clip plane (world), until the slider moves

  function position() {                       // the slider's world coordinate along the axis
    const a = "xyz".indexOf($("slice-axis").value);
    if (state.exact !== null) return state.exact;
    if (!state.box) return 0;
    const lo = state.box[0][a], hi = state.box[1][a];
    return lo + (hi - lo) * (+$("slice-position").value / 1000);
  }

  function request() {                        // at most one in flight: the newest wins
    if (!$("show-slice").checked || !state.box) return;
    if (state.pending) { state.again = true; return; }
    state.pending = true; state.again = false;
    state.asked = { axis: $("slice-axis").value, position: position() };
    $("slice-position-value").textContent = state.asked.position.toPrecision(4);
    send({ type: "slice", axis: state.asked.axis, position: state.asked.position, res: 256 });
  }

  function show(msg) {
    state.pending = false;
    state.reply = msg;
    state.values = decode(msg.values, Float32Array);
    state.levels = decode(msg.levels, Int8Array);
    const img = new Image();
    img.onload = () => {
      canvas.width = msg.width; canvas.height = msg.height;
      const scale = 256 / Math.max(msg.width, msg.height);
      canvas.style.width = `${msg.width * scale}px`; canvas.style.height = `${msg.height * scale}px`;
      canvas.getContext("2d").drawImage(img, 0, 0);
      ctx.stats.slices = (ctx.stats.slices || 0) + 1;
      ctx.stats.lastSlice = { axis: msg.axis, position: msg.position, width: msg.width, height: msg.height };
    };
    img.src = msg.png;
    $("slice-axes").textContent = `${msg.label}: ${msg.axes[0]} →, ${msg.axes[1]} ↑ at ${msg.axis} = ${msg.position.toPrecision(4)}`;
    if (state.again) request();
  }

  canvas.addEventListener("mousemove", (ev) => {
    const r = state.reply;
    if (!r) return;
    const b = canvas.getBoundingClientRect();
    const i = Math.floor((ev.clientX - b.left) / b.width * r.width), j = Math.floor((ev.clientY - b.top) / b.height * r.height);
    if (i < 0 || j < 0 || i >= r.width || j >= r.height) return;
    const v = state.values[j * r.width + i], level = state.levels[j * r.width + i];
    const [h0, h1, v0, v1] = r.window;
    const h = h0 + (i + 0.5) / r.width * (h1 - h0), vv = v1 - (j + 0.5) / r.height * (v1 - v0);
    const value = Number.isNaN(v) ? "no value" : (r.log ? `${Math.pow(10, v).toPrecision(4)} (log10 ${v.toPrecision(4)})`
      : v.toPrecision(4));
    readout.textContent = `${r.axes[0]} ${h.toPrecision(4)}, ${r.axes[1]} ${vv.toPrecision(4)}: ${value} · level ${level < 0 ? "none" : level}`;
    readout.dataset.value = String(v); readout.dataset.level = String(level);
  });

  for (const id of ["slice-axis", "slice-position"]) $(id).addEventListener("input", () => { state.exact = null; request(); });
  $("show-slice").addEventListener("change", () => {
    $("slice-panel").classList.toggle("hidden", !$("show-slice").checked);
    request();
  });

  setInterval(() => {                         // the view's TF changed and rests: its colours again
    const tf = JSON.stringify(ctx.getTf());
    if (tf !== state.tf && performance.now() - ctx.stats.lastChange > 300) {
      const first = state.tf === null;
      state.tf = tf;
      if (!first && state.reply) request();
    }
  }, 300);

  return {
    state,
    geometry(msg) { state.box = msg.box; request(); },     // once per field: its slice again
    reply: show,
    failed() { state.pending = false; },
    clip(clip) {                              // follow an axis-aligned clip plane
      if (!clip || !state.box) return;
      const n = clip.normal, a = [0, 1, 2].filter((k) => n[k] !== 0);
      if (a.length !== 1) return;
      const k = a[0], lo = state.box[0][k], hi = state.box[1][k], x = clip.offset / n[k];
      $("slice-axis").value = "xyz"[k];
      $("slice-position").value = String(Math.round(1000 * Math.min(1, Math.max(0, (x - lo) / (hi - lo)))));
      state.exact = Math.min(hi, Math.max(lo, x));
      request();
    },
  };
}
