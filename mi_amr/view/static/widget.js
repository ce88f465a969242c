// mi-amr's notebook widget (mi_amr/view/widget.py, an anywidget): the viewer's
// page (viewer.js, which widget.py bundles with its imports into
// `startViewer(widgetHost)`, and the markup and style of index.html and
// viewer.css: MARKUP, STYLE) in a shadow root of the cell's output, talking to
// the kernel over Jupyter's comm channel alone: messages out as
// model.send(msg), those of BATCH_MS together as one { type: "batch",
// messages } (each comm message is a request that the kernel and JupyterLab
// handle one by one, a busy and an idle status around it); in, custom
// messages: JSON ones as they are, frames as { type: "frame", header } with
// the JPEG image as the message's one buffer.
// Nothing else is fetched or opened.

const BATCH_MS = 25;

function render({ model, el }) {
  const shadow = el.attachShadow({ mode: "open" });
  shadow.innerHTML = `<style>${STYLE}</style><div class="mi-amr-root">${MARKUP}</div>`;
  let handlers = null, queue = [], timer = null, lastSent = -1e9;
  const flush = () => {
    timer = null;
    if (host.closed || !queue.length) return;
    const q = queue;
    queue = [];
    lastSent = performance.now();
    model.send(q.length === 1 ? q[0] : { type: "batch", messages: q });
  };
  const listener = (msg, buffers) => {
    if (!handlers || !msg) return;
    if (msg.type === "frame") {
      const b = buffers[0];
      handlers.onFrame(msg.header, new Uint8Array(b.buffer, b.byteOffset, b.byteLength));
    } else {
      handlers.onJson(msg);
    }
  };
  model.on("msg:custom", listener);
  const host = {
    root: shadow,
    closed: false,
    transport: {
      send(msg) {              // at once, unless a message left less than BATCH_MS ago
        if (host.closed) return;
        queue.push(msg);
        const wait = BATCH_MS - (performance.now() - lastSent);
        if (wait <= 0) flush();
        else if (!timer) timer = setTimeout(flush, wait);
      },
      // the kernel answers a describe with the status, then (once loaded) the
      // view's hello and its newest frame: a page shown late catches up
      connect(h) { handlers = h; model.send({ type: "describe" }); },
    },
  };
  startViewer(host);     // eslint-disable-line no-undef
  return () => { host.closed = true; model.off("msg:custom", listener); };
}

export default { render };
