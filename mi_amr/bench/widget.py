"""How fast the notebook widget (``sc.show()``, `mi_amr.view.widget`) is
through Jupyter's comm channel, measured in the page.

``python -m mi_amr.bench --widget DATA [--view-field F] [--res 256] --out DIR``
starts JupyterLab (`JupyterLab`: a server of its own in a temporary
folder, a token, nothing else of the user's), opens a notebook that runs
``mi_amr.scene(DATA, field=F).show(res=RES)`` in Debian's chromium
(Playwright), waits for the widget's first refined picture, then drags the
camera (an orbit) for ``--widget-seconds``, the pointer moving every 16 ms
(dispatched in the page, as `mi_amr.bench.view` does), ``--repeats`` times:
frames received per second in the page during the drag
(``window.viewerStats.frameTimes``), their sizes and lighting mode (the
hybrid viewer's ``ray_march``; ``hybrid=False``: ``emission_absorption``),
the fast passes' render time. Writes ``DIR/widget.json`` and ``DIR/widget.md``.

`JupyterLab` is also what tests/test_widget.py drives: run a cell, read
its output, the kernel's process and its listening sockets.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import psutil

from .harness import write_report

#: Chromium's flags for a quiet headless run.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]

#: The element of a ``data-testid`` in the widget's shadow root (or the document).
FIND = """(testid) => {
    for (const e of document.querySelectorAll('*')) {
        const found = e.shadowRoot && e.shadowRoot.querySelector(`[data-testid=${testid}]`);
        if (found) return found;
    }
    return document.querySelector(`[data-testid=${testid}]`);
}"""

#: The moves of an orbit dispatched in the page every ``moveMs`` (a 60-Hz
#: pointer) between a real press and release, on the widget's view.
IN_PAGE_DRAG = """([x0, y0, dx, seconds, moveMs]) => new Promise((done) => {
    const el = (%s)("view");
    const t0 = performance.now();
    let k = 0;
    const timer = setInterval(() => {
        k += 1;
        el.dispatchEvent(new PointerEvent("pointermove", { clientX: x0 + dx * k, clientY: y0, pointerId: 1,
            pointerType: "mouse", buttons: 1, bubbles: true, composed: true }));
        if (performance.now() - t0 >= 1000 * seconds) { clearInterval(timer); done(k); }
    }, moveMs);
})""" % FIND

#: The canvas's pixels in the page: [mean, share of pixels not black, 16x16 grey thumbnail].
CANVAS_PIXELS = """() => {
    const c = (%s)("view");
    const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    let sum = 0, lit = 0;
    const n = c.width * c.height, thumb = new Array(256).fill(0), count = new Array(256).fill(0);
    for (let i = 0; i < n; i++) {
        const v = (d[4 * i] + d[4 * i + 1] + d[4 * i + 2]) / 3;
        sum += v; if (v > 8) lit += 1;
        const x = Math.floor(16 * (i %% c.width) / c.width), y = Math.floor(16 * Math.floor(i / c.width) / c.height);
        thumb[16 * y + x] += v; count[16 * y + x] += 1;
    }
    return [sum / n, lit / n, thumb.map((v, k) => v / Math.max(1, count[k]))];
}""" % FIND


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def notebook_json(cells: list[str]) -> str:
    """An nbformat 4 notebook of code ``cells`` for the Python 3 kernel."""
    return json.dumps({"nbformat": 4, "nbformat_minor": 5, "metadata": {
        "kernelspec": {"name": "python3", "display_name": "Python 3 (ipykernel)", "language": "python"}},
        "cells": [{"cell_type": "code", "id": f"c{i}", "metadata": {}, "execution_count": None, "outputs": [],
                   "source": src} for i, src in enumerate(cells)]})


class JupyterLab:
    """JupyterLab serving ``folder`` on loopback with a token of its own,
    its configuration, data and runtime folders inside ``folder`` (nothing
    of the user's read or written); a context manager."""

    def __init__(self, folder, env: dict | None = None):
        self.folder = Path(folder)
        self.port, self.token = free_port(), secrets.token_hex(16)
        self.env = dict(os.environ, **(env or {}))
        home = self.folder / ".jupyter-home"
        for key, sub in (("JUPYTER_CONFIG_DIR", "config"), ("JUPYTER_RUNTIME_DIR", "runtime"),
                         ("IPYTHONDIR", "ipython")):
            self.env[key] = str(home / sub)
        self.process = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> "JupyterLab":
        log = open(self.folder / "jupyterlab.log", "w")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "jupyterlab", "--no-browser", "--ip=127.0.0.1", f"--port={self.port}",
             f"--IdentityProvider.token={self.token}", f"--ServerApp.root_dir={self.folder}",
             "--LabApp.news_url=", "--LabApp.expose_app_in_browser=True", "--ServerApp.open_browser=False"]
            + (["--allow-root"] if hasattr(os, "geteuid") and os.geteuid() == 0 else []),
            cwd=self.folder, env=self.env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"JupyterLab ended: {(self.folder / 'jupyterlab.log').read_text()[-2000:]}")
            try:
                with urllib.request.urlopen(f"{self.url}/api/status?token={self.token}", timeout=5) as r:
                    if r.status == 200:
                        return self
            except OSError:
                time.sleep(0.3)
        raise RuntimeError("JupyterLab did not answer within 120 s")

    def __exit__(self, *exc):
        if self.process is not None:
            for child in psutil.Process(self.process.pid).children(recursive=True):
                child.terminate()
            self.process.terminate()
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.process.kill()

    def open(self, browser, name: str, cells: list[str]):
        """A page of the notebook ``name`` (written with ``cells``), its kernel started."""
        (self.folder / name).write_text(notebook_json(cells))
        # its session and kernel started here: the page attaches to them (no "Select Kernel" dialog)
        body = json.dumps({"path": name, "type": "notebook", "name": name, "kernel": {"name": "python3"}}).encode()
        request = urllib.request.Request(f"{self.url}/api/sessions?token={self.token}", data=body, method="POST",
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=60) as r:
            if r.status not in (200, 201):
                raise RuntimeError(f"JupyterLab refused the session: {r.status}")
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        page.goto(f"{self.url}/lab/tree/{name}?token={self.token}")
        page.locator(".jp-Notebook .jp-Cell").first.wait_for(timeout=120_000)
        page.wait_for_function("() => window.jupyterapp && window.jupyterapp.shell.currentWidget "
                               "&& window.jupyterapp.shell.currentWidget.sessionContext", timeout=120_000)
        page.evaluate("async () => { await window.jupyterapp.shell.currentWidget.sessionContext.ready; }")
        deadline = time.monotonic() + 120
        while not page.evaluate("""() => { const s = document.querySelector('.jp-Notebook-ExecutionIndicator');
                                          return !!s && s.getAttribute('data-status') === 'idle'
                                                 && !document.querySelector('.jp-Dialog'); }"""):
            self.accept_dialog(page)                 # "Select Kernel", asked at times: the notebook's own
            if time.monotonic() > deadline:
                raise TimeoutError("the notebook's kernel did not start within 120 s")
            page.wait_for_timeout(200)
        return page

    @staticmethod
    def accept_dialog(page):
        """Accept a dialog JupyterLab shows (its default button), if any."""
        button = page.locator(".jp-Dialog .jp-mod-accept")
        if button.count():
            button.first.click()

    @staticmethod
    def run_cell(page, index: int, timeout: float = 300) -> str:
        """Run the notebook's cell ``index`` and wait for it to finish;
        returns its output's text."""
        cell = page.locator(".jp-Notebook .jp-Cell").nth(index)
        prompt = cell.locator(".jp-InputArea-prompt")
        before = prompt.inner_text()
        started = time.monotonic() + timeout
        while prompt.inner_text() == before:     # JupyterLab's own command, again until the cell starts
            if time.monotonic() > started:       # (one issued while the page still settles can go unseen)
                break
            JupyterLab.accept_dialog(page)
            page.evaluate("""(i) => { const app = window.jupyterapp, nb = app.shell.currentWidget.content;
                                      nb.activeCellIndex = i; void app.commands.execute('notebook:run-cell'); }""",
                          index)
            again = time.monotonic() + 5
            while prompt.inner_text() == before and time.monotonic() < again:
                page.wait_for_timeout(100)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            JupyterLab.accept_dialog(page)
            text = prompt.inner_text()
            if re.search(r"\[\d+\]", text) and text != before:
                break
            page.wait_for_timeout(100)
        else:
            shot = Path(tempfile.gettempdir()) / f"mi-amr-widget-cell{index}-timeout.png"
            page.screenshot(path=str(shot))
            raise TimeoutError(f"cell {index} did not finish within {timeout:g} s (the page: {shot})")
        out = cell.locator(".jp-OutputArea-output")
        return "\n".join(out.nth(i).inner_text() for i in range(out.count()))

    def kernels(self) -> list:
        """The server's kernel processes (psutil)."""
        return [p for p in psutil.Process(self.process.pid).children(recursive=True)
                if any("ipykernel" in a for a in p.cmdline())]

    @staticmethod
    def listening(process) -> set:
        """The (address, port) a process listens on (TCP)."""
        return {(c.laddr.ip, c.laddr.port) for c in process.net_connections(kind="inet")
                if c.status == psutil.CONN_LISTEN}


def drag_rate(page, seconds: float = 4.0, move_ms: float = 16) -> dict:
    """An orbit of ``seconds`` on the widget's view; the frames the page
    received per second meanwhile, their widths, the fast passes' time."""
    box = page.evaluate(f"() => {{ const el = ({FIND})('view'); el.scrollIntoView({{block: 'center'}}); "
                        "const r = el.getBoundingClientRect(); "
                        "return {x: r.x, y: r.y, width: r.width, height: r.height}; }")
    page.wait_for_timeout(300)
    x0, y0 = box["x"] + 0.3 * box["width"], box["y"] + 0.5 * box["height"]
    page.evaluate("window.viewerStats.frameTimes = []; window.viewerStats.fastRenderMs = [];"
                  "window.viewerStats.fastWidths = [];")
    modes0 = page.evaluate("({...window.viewerStats.frameModes})")
    page.mouse.move(x0, y0)
    page.mouse.down()
    start = page.evaluate("performance.now()")
    moves = page.evaluate(IN_PAGE_DRAG, [x0, y0, 1.5, seconds, move_ms])
    end = page.evaluate("performance.now()")
    page.mouse.up()
    s = page.evaluate("window.viewerStats")
    if not s["fastWidths"]:
        raise RuntimeError("the drag moved nothing: no fast frame came (was the view on screen?)")
    shown = [t for t in s["frameTimes"] if start <= t <= end]
    modes = {m: n - modes0.get(m, 0) for m, n in s["frameModes"].items() if n > modes0.get(m, 0)}
    return {"frames_per_s": len(shown) / ((end - start) / 1e3), "moves_per_s": moves / ((end - start) / 1e3),
            "fast_widths": sorted(set(s["fastWidths"])), "frame_modes": modes,
            "fast_render_median_ms": statistics.median(s["fastRenderMs"]) if s["fastRenderMs"] else None}


def measure(data, field=None, res: int = 256, seconds: float = 4.0, repeats: int = 3, hybrid: bool = True) -> dict:
    from playwright.sync_api import sync_playwright   # lazy: a benchmark dependency
    exe = shutil.which("chromium")
    if exe is None:
        raise SystemExit("the widget benchmark needs Debian's chromium (make setup installs it)")
    out = {"data": str(data), "field": field, "res": res, "seconds": seconds, "cpus": os.cpu_count(),
           "hybrid": bool(hybrid), "load_average_start": os.getloadavg(), "runs": []}
    cells = ["import mitsuba as mi\nmi.set_variant('llvm_ad_rgb')\nimport mi_amr",
             f"sc = mi_amr.scene({str(data)!r}, field={field!r})\n"
             f"w = sc.show(res={int(res)}, hybrid={bool(hybrid)})\nw",
             "w.wait(recorded=True);"]
    with tempfile.TemporaryDirectory(prefix="mi-amr-widget-bench-") as tmp, JupyterLab(tmp) as lab, \
            sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
        page = lab.open(browser, "bench.ipynb", cells)
        lab.run_cell(page, 0)
        t0 = time.monotonic()
        lab.run_cell(page, 1, timeout=3600)
        page.wait_for_function("window.viewerStats && window.viewerStats.lastFrame && "
                               "!window.viewerStats.lastFrame.preview", timeout=3_600_000)
        out["first_refined_s"] = time.monotonic() - t0
        lab.run_cell(page, 2, timeout=3600)              # the passes a drag needs, recorded ahead
        page.wait_for_timeout(1000)
        for r in range(repeats):
            run = drag_rate(page, seconds)
            out["runs"].append(run)
            page.wait_for_timeout(1500)
        browser.close()
    out["load_average_end"] = os.getloadavg()
    return out


def report(result: dict) -> str:
    fps = [r["frames_per_s"] for r in result["runs"]]
    modes = sorted({m for r in result["runs"] for m in r.get("frame_modes", {})})
    lines = [f"widget through the comm channel: {result['data']} at {result['res']}x{result['res']}, "
             f"{result['cpus']} CPUs (load {result['load_average_start'][0]:.1f})"
             + (f", hybrid {'on' if result['hybrid'] else 'off'}" if "hybrid" in result else ""),
             f"  first refined picture after show(): {result['first_refined_s']:.1f} s",
             f"  frames/s in the page while dragging: median {statistics.median(fps):.1f} "
             f"({min(fps):.1f}-{max(fps):.1f}) over {len(fps)} drags",
             f"  pointer moves/s: {statistics.median(r['moves_per_s'] for r in result['runs']):.0f}; "
             f"fast frame widths {sorted({w for r in result['runs'] for w in r['fast_widths']})}; "
             f"fast pass median {statistics.median(r['fast_render_median_ms'] or 0 for r in result['runs']):.1f} ms"
             + (f"; frames in {', '.join(modes)}" if modes else "")]
    return "\n".join(lines)


def run(data, field, res, out_dir, repeats=3, seconds=4.0, hybrid=True):
    result = measure(data, field, res, seconds, repeats, hybrid)
    write_report(out_dir, "widget", result, report(result))


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--widget``)."""
    run(args.widget, args.view_field, args.res, Path(args.out), args.repeats, args.widget_seconds)
    print(f"wrote {args.out}/widget.json and widget.md")
    return 0
