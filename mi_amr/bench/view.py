"""How interactive ``mi-amr view`` is, measured in the page, for each lighting mode.

``python -m mi_amr.bench --view DATA [--view-field F] [--res 256] --out DIR``
serves DATA as ``mi-amr view`` does, opens the page in Debian's chromium
(Playwright) and, for each lighting mode the page can refine in (chosen in
its selector), ``--repeats`` times each, drags the camera (an orbit) and a
TF control point for ``seconds``, the pointer moving every 16 ms (a 60-Hz
pointer: the moves dispatched in the page between a real press and
release; ``driver="mouse"``: each through Playwright, whose round trips
cap the moves at about 20 a second on this machine), and lets go. While
the hand moves, frames are fast passes at ``--view-preview-scale`` of the
resolution: with the hybrid viewer (the page's toggle, on by default) the
ray marcher's (``ray_march``, noise-free, its step the engine's
``fast_step_scale``), with it off 1-spp ``emission_absorption``
(``--view-hybrid on,off`` measures both, toggled in the page); once it
rests, the mode refines. Read in the page (``window.viewerStats``): frames on screen per
second during the drag; the time from a change to the first frame after it
and to the first frame rendered from it (median and 90th percentile); the
fast passes' render time; the time from the last change to the first
picture in the chosen mode (preview or full size), to the first full-size
one, and to the first denoised full-size one. Beside them, timed here on
the loaded scene: the fast pass on the same view (in each fast mode
measured) and on an empty medium (every TF opacity 0: rays, surfaces and
the traversal only), the JPEG encoding of a fast frame, the bound of the
fast frames, and a full-size pass of each mode. The first picture: from
the start (load included) and, with the viewer loaded and warm, from
opening a page.

Writes ``DIR/view.json`` and ``DIR/view.md``.

``python -m mi_amr.bench.view DATA [N] [--cold]``: the first picture alone
(`first_pictures`), N fresh ``mi-amr view`` processes in a row, each page
opened when its URL is printed: seconds from the start to the URL, from
opening the page to its first frame, from the start to the first frame and
to the first full-size one; ``--cold``: each process with an empty Dr.Jit
kernel cache (docs/performance/view.md "The first picture").
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

from ..plugins.integrator import MODES
from .harness import write_report
from ..view.engine import FAST_MODE, FAST_STEPS, JIT_LOCK, PLAIN_FAST_MODE, ViewEngine, encode_jpeg
from ..view.server import ViewServer

#: Chromium's flags for a quiet headless run.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
#: Reset before each drag (``window.viewerStats``).
RESET = ("window.viewerStats.latencies = []; window.viewerStats.renderLatencies = [];"
         "window.viewerStats.frameTimes = []; window.viewerStats.denoiseLatencies = [];"
         "window.viewerStats.fullDenoiseLatencies = []; window.viewerStats.refinedLatencies = [];"
         "window.viewerStats.fullLatencies = []; window.viewerStats.fastRenderMs = [];"
         "window.viewerStats.fastWidths = [];")


#: The moves of a drag dispatched in the page itself, every ``moveMs`` (a
#: pointer of 60 Hz), between a real press and release.
IN_PAGE_DRAG = """([testid, x0, y0, dx, dy, tf, seconds, moveMs]) => new Promise((done) => {
    const el = document.querySelector(`[data-testid=${testid}]`);
    const t0 = performance.now();
    let k = 0;
    const timer = setInterval(() => {
        k += 1;
        const step = tf ? k % 40 : k, up = !tf || Math.floor(k / 40) % 2 === 0;
        el.dispatchEvent(new PointerEvent("pointermove", { clientX: x0 + dx * step,
            clientY: y0 + dy * (up ? step : 40 - step), pointerId: 1, pointerType: "mouse", buttons: 1,
            bubbles: true }));
        if (performance.now() - t0 >= 1000 * seconds) { clearInterval(timer); done(k); }
    }, moveMs);
})"""


def _drag(page, box, kind: str, seconds: float, move_ms: float = 16, driver: str = "page"):
    """Drag on ``box`` (the view or the TF editor) for ``seconds``, the
    pointer moving every ``move_ms``: dispatched in the page (``driver``
    "page", as a real pointer's events come), or each through Playwright's
    mouse ("mouse": a round trip to the browser per move, which bounds the
    moves per second on a busy machine)."""
    if kind == "camera":
        x0, y0, dx, dy = box["x"] + 0.3 * box["width"], box["y"] + 0.5 * box["height"], 2.5, 0.0
    else:                                 # the tallest spiky peak, dragged down and up
        x0, y0, dx, dy = box["x"] + 8 + 0.8 * (box["width"] - 16), box["y"] + 8, 0.0, 4.0
    page.mouse.move(x0, y0)
    page.mouse.down()
    t0, k = time.monotonic(), 0
    if driver == "page":
        page.evaluate(IN_PAGE_DRAG, ["view" if kind == "camera" else "tf-editor", x0, y0, dx, dy, kind == "tf",
                                     seconds, move_ms])
    else:
        while time.monotonic() - t0 < seconds:
            k += 1
            step = k % 40 if kind == "tf" else k
            sign = 1 if (k // 40) % 2 == 0 or kind == "camera" else -1
            page.mouse.move(x0 + dx * step, y0 + dy * (step if sign > 0 else 40 - step))
            page.wait_for_timeout(move_ms)
    page.mouse.up()
    return time.monotonic() - t0


def _median(xs):
    return statistics.median(xs) if xs else None


def _p90(xs):
    xs = sorted(xs)
    return xs[int(0.9 * (len(xs) - 1))] if xs else None


def _first_frame(page, url) -> tuple[float, float]:
    """When (``time.monotonic``) the page opened at ``url`` showed its first
    frame, and its first full-size one."""
    page.goto(url)
    page.wait_for_function("window.viewerStats.lastFrame", timeout=600_000, polling=10)
    first = time.monotonic()
    page.wait_for_function("window.viewerStats.lastFrame && !window.viewerStats.lastFrame.preview",
                           timeout=600_000, polling=10)
    return first, time.monotonic()


def cli_first_picture(browser, data, field=None, res: int = 256, env=None) -> dict:
    """As a new user meets it: ``mi-amr view DATA`` started as a process
    (imports included), the page opened as soon as the URL is printed;
    seconds from the start to the URL, the first frame on screen and the
    first full-size one, and the first frame after opening the page
    (``page_first_picture_s``). ``env``: the process's environment (None:
    this one's; e.g. another ``HOME`` for a cold Dr.Jit kernel cache)."""
    cmd = [sys.executable, "-m", "mi_amr.tools.cli", "view", str(data), "--no-browser", "--res", str(res),
           "--out", "/tmp"] + (["--field", field] if field else [])
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    try:
        url = None
        for line in proc.stdout:
            if line.startswith("mi-amr view: http"):
                url = line.split(": ", 1)[1].strip()
                break
        if url is None:
            raise RuntimeError(f"mi-amr view printed no URL (status {proc.wait()})")
        listening = time.monotonic() - t0
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        first, refined = _first_frame(page, url)
        page.close()
        return {"url_s": listening, "first_picture_s": first - t0, "first_refined_s": refined - t0,
                "page_first_picture_s": first - t0 - listening}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


def pass_times(engine: ViewEngine, camera, spec, size, mode, n: int = 12, tf: bool = False,
               step_scale: float | None = None, jpeg: list | None = None, centred: bool = False) -> list[float]:
    """Milliseconds of ``n`` frozen passes of ``size`` in ``mode`` (the
    camera turning a degree each, as in a drag; ``tf``: the TF's density
    changing instead, majorants recomputed each time), on the engine's
    scene; ``step_scale``: the ray marcher's step and ``centred`` its
    sensor (the hybrid's drag frames: the engine's ``fast_step_scale``,
    centred); ``jpeg``: gets the milliseconds of
    each image's JPEG encoding (as the viewer sends it)."""
    out = []
    loaded = engine.loaded
    with JIT_LOCK:
        for k in range(n + 2):
            t = time.perf_counter()
            if tf:
                loaded.apply(camera, replace(spec, density=spec.density * (1 + 0.01 * (k % 2))), size)
            else:
                loaded.apply(replace(camera, azimuth=camera.azimuth + k), spec, size)
            image = loaded.render(90_000 + k, size, mode, step_scale=step_scale, centred=centred)
            if k >= 2:                            # the first may record
                out.append(1e3 * (time.perf_counter() - t))
                if jpeg is not None:
                    t = time.perf_counter()
                    encode_jpeg(image)
                    jpeg.append(1e3 * (time.perf_counter() - t))
        loaded.render(90_000, size, mode)         # the integrator's own step again
    return out


def measure(data, field=None, res: int = 256, seconds: float = 4.0, repeats: int = 3,
            preview_scale: float = 0.5, modes=None, move_ms: float = 16, driver: str = "page",
            hybrids=(True,)) -> dict:
    """The figures of the module docstring; ``hybrids``: the page's hybrid
    toggle in each round of drags (True: ray-marched drag frames)."""
    from playwright.sync_api import sync_playwright   # lazy: a benchmark dependency
    exe = shutil.which("chromium")
    if exe is None:
        raise SystemExit("the viewer benchmark needs Debian's chromium (make setup installs it)")
    with sync_playwright() as p:                  # first, as a new user starts it (its own process)
        browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
        cli = cli_first_picture(browser, data, field, res)
        browser.close()
    t0 = time.monotonic()
    engine = ViewEngine(data, field, res=res, preview_scale=preview_scale)
    ready_at = []
    engine.on_status(lambda st: ready_at.append(time.monotonic()) if st.state == "ready" and not ready_at else None)
    engine.start()
    server = ViewServer(engine, quiet=True, out_dir="/tmp").start()
    out = {"data": str(data), "res": res, "preview_scale": preview_scale, "fast_mode": FAST_MODE, "move_ms": move_ms,
           "driver": driver, "hybrids": list(hybrids), "fast_step_scale": engine.fast_step_scale,
           "cpus": os.cpu_count(), "load_average_start": os.getloadavg(), "runs": [], "passes": {}, "cli": cli}
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
            # a page opened at the start (as mi-amr view opens the browser): the load included
            first_page = browser.new_page(viewport={"width": 1200, "height": 800})
            first, refined = _first_frame(first_page, server.url)
            out["load_s"] = ready_at[0] - t0 if ready_at else None
            out["first_picture_s"], out["first_refined_s"] = first - t0, refined - t0
            first_page.close()
            modes = [m for m in (modes or MODES) if m in engine.loaded.modes] or [engine.mode]
            # a page opened on the loaded viewer, once it recorded its passes ahead
            deadline = time.monotonic() + 300
            while (engine._warm or engine._views) and time.monotonic() < deadline:
                time.sleep(0.1)
            out["warm_s"] = time.monotonic() - t0
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            t = time.monotonic()
            first, refined = _first_frame(page, server.url)
            out["page_first_picture_s"], out["page_first_refined_s"] = first - t, refined - t
            for mode in modes:
                page.get_by_test_id("mode").select_option(mode)
                page.wait_for_function(f"""() => {{ const f = window.viewerStats.lastFrame;
                    return f && f.mode === {json.dumps(mode)} && !f.preview; }}""", timeout=600_000)
                for hybrid, r in ((h, r) for h in hybrids for r in range(repeats)):
                    if page.get_by_test_id("hybrid").is_checked() != hybrid:
                        page.get_by_test_id("hybrid").set_checked(hybrid)
                    deadline = time.monotonic() + 120
                    while any(v.hybrid != hybrid for v in list(engine._views.values())) and \
                            time.monotonic() < deadline:                     # the toggle reached the engine
                        time.sleep(0.05)
                    while engine._warm and time.monotonic() < deadline:      # its passes recorded ahead
                        time.sleep(0.1)
                    for kind, testid in (("camera", "view"), ("tf", "tf-editor")):
                        page.wait_for_timeout(1500)
                        box = page.get_by_test_id(testid).bounding_box()
                        page.evaluate(RESET)
                        modes0 = page.evaluate("({...window.viewerStats.frameModes})")
                        start, changes0 = page.evaluate("[performance.now(), window.viewerStats.changes]")
                        took = _drag(page, box, kind, seconds, move_ms, driver)
                        end, changes1 = page.evaluate("[performance.now(), window.viewerStats.changes]")
                        page.wait_for_function("window.viewerStats.fullLatencies.length > 0", timeout=120_000)
                        page.wait_for_timeout(600)
                        s = page.evaluate("window.viewerStats")
                        shown = [t for t in s["frameTimes"] if start <= t <= end]
                        fast = engine._fast_mode(next(iter(engine._views.values())))
                        out["runs"].append({
                            "mode": mode, "kind": kind, "round": r, "drag_s": took, "hybrid": hybrid,
                            "fast_mode": fast, "fast_frames": s["frameModes"].get(fast, 0) - modes0.get(fast, 0),
                            "fast_step": engine._fast_step() if fast == FAST_MODE else None,
                            "frames_per_s": len(shown) / ((end - start) / 1e3),
                            "changes_per_s": (changes1 - changes0) / ((end - start) / 1e3),
                            "latency_median_ms": _median(s["latencies"]), "latency_p90_ms": _p90(s["latencies"]),
                            "render_latency_median_ms": _median(s["renderLatencies"]),
                            "render_latency_p90_ms": _p90(s["renderLatencies"]),
                            "fast_render_median_ms": _median(s["fastRenderMs"]),
                            "fast_sizes": sorted(set(s["fastWidths"])),
                            "refined_after_ms": (s["refinedLatencies"] or [None])[0],
                            "full_after_ms": (s["fullLatencies"] or [None])[0],
                            "full_denoised_after_ms": (s["fullDenoiseLatencies"] or [None])[0]})
            page.screenshot(path=str(Path("/tmp") / "mi-amr-view-bench.png"))
            view = next(iter(engine._views.values()))
            camera, spec = view.camera, view.spec
            browser.close()
        # the passes themselves, on the loaded scene: the fast one on this view and on an empty medium
        empty = replace(spec, points=((0.0, 0.0), (1.0, 0.0)))
        fast_modes = [m for m in (FAST_MODE if h else PLAIN_FAST_MODE for h in hybrids) if m in engine.loaded.modes]
        for k, fast in enumerate(dict.fromkeys(fast_modes or [None])):
            small, full = engine._sizes(fast, SimpleNamespace(hybrid=fast == FAST_MODE))   # a view's toggle
            hybrid = {"step_scale": engine.fast_step_scale, "centred": True} if fast == FAST_MODE else {}
            name = "fast" if k == 0 else f"fast_{fast}"
            jpeg = []
            out["passes"][name] = {"size": small, "mode": fast, "step_scale": hybrid.get("step_scale"),
                                   "ms": pass_times(engine, camera, spec, small, fast, jpeg=jpeg, **hybrid)}
            out["passes"][name + "_jpeg"] = {"size": small, "ms": jpeg}
            out["passes"][name + "_tf_changing"] = {"size": small, "ms": pass_times(
                engine, camera, spec, small, fast, tf=True, **hybrid)}
            out["passes"][name + "_empty"] = {"size": small, "ms": pass_times(engine, camera, empty, small, fast,
                                                                               **hybrid)}
            for share in FAST_STEPS[1:] if hybrid else ():    # the coarser steps the budget may take
                step = engine.fast_step_scale * share
                out["passes"][f"{name}_step{step:g}"] = {"size": small, "mode": fast, "step_scale": step, "ms":
                                                         pass_times(engine, camera, spec, small, fast, step_scale=step,
                                                                    centred=True)}
        for mode in modes:
            out["passes"][f"full_{mode}"] = {"size": full, "ms": pass_times(engine, camera, spec, full, mode, 6)}
        out["load_average_end"] = os.getloadavg()
    finally:
        server.stop()
        engine.stop()
    return out


def _spread(xs, fmt="{:.0f}") -> str:
    xs = [x for x in xs if x is not None]
    if not xs:
        return "-"
    lo, mid, hi = min(xs), statistics.median(xs), max(xs)
    return f"{fmt.format(mid)} ({fmt.format(lo)}-{fmt.format(hi)})"


def report(result: dict) -> str:
    la = result.get("load_average_start", (0, 0, 0))
    fast = (f"{result['fast_mode']} (step {result['fast_step_scale']:g} finest cells, coarser to keep to the "
            "frame budget) with the hybrid on, "
            f"{PLAIN_FAST_MODE} with it off," if "fast_step_scale" in result else result["fast_mode"])
    lines = [f"`mi-amr view` on {result['data']}, {result['res']}x{result['res']}, fast passes "
             f"{fast} at preview scale {result['preview_scale']} (or smaller, to keep a "
             f"frame budget), the pointer moving every {result['move_ms']:g} ms "
             f"({'in the page' if result.get('driver', 'page') == 'page' else 'through Playwright'}); "
             "load average at the start "
             f"{la[0]:.1f} on {result.get('cpus')} CPUs.", "",
             f"First picture in the page: {result['first_picture_s']:.1f} s after the start (the load took "
             f"{result['load_s'] or 0:.1f} s), the first full-size one after {result['first_refined_s']:.1f} s; "
             f"a page opened on the loaded viewer (its passes recorded ahead after {result['warm_s']:.1f} s): "
             f"{result['page_first_picture_s']:.2f} s, refined {result['page_first_refined_s']:.2f} s. "
             f"`mi-amr view` as a process (imports included), the page opened when it printed the URL "
             f"({result['cli']['url_s']:.1f} s): first picture {result['cli']['first_picture_s']:.1f} s after the "
             f"start ({result['cli']['first_picture_s'] - result['cli']['url_s']:.2f} s after opening the page), "
             f"first full-size one {result['cli']['first_refined_s']:.1f} s after the start.", "",
             "| mode | drag | round | frames/s on screen (changes/s sent) | change -> next frame, median / p90 ms | "
             "change -> frame of it, median / p90 ms | fast pass ms (widths) | last change -> mode's first / "
             "full size / denoised full ms |",
             "|---|---|---|---|---|---|---|---|"]
    f = lambda x: "-" if x is None else f"{x:.0f}"      # noqa: E731
    # a run's mode, and its drag frames' where measured (the hybrid viewer's toggle)
    label = lambda r: r["mode"] + (f", drags {r['fast_mode']}" if r.get("fast_mode") else "")    # noqa: E731
    for r in result["runs"]:
        lines.append(f"| {label(r)} | {r['kind']} | {r['round']} | {r['frames_per_s']:.1f} "
                     f"({r['changes_per_s']:.0f}) | "
                     f"{f(r['latency_median_ms'])} / {f(r['latency_p90_ms'])} | "
                     f"{f(r['render_latency_median_ms'])} / {f(r['render_latency_p90_ms'])} | "
                     f"{f(r['fast_render_median_ms'])} ({', '.join(map(str, r['fast_sizes']))}"
                     + (f"; step {r['fast_step']:g} at the end" if r.get("fast_step") else "") + ") | "
                     f"{f(r['refined_after_ms'])} / {f(r['full_after_ms'])} / "
                     f"{f(r['full_denoised_after_ms'])} |")
    lines += ["", "Summary, median (min-max) over the rounds:", "",
              "| mode | drag | frames/s | change -> next frame median ms | last change -> mode's first ms |",
              "|---|---|---|---|---|"]
    for mode in dict.fromkeys(label(r) for r in result["runs"]):
        for kind in ("camera", "tf"):
            rs = [r for r in result["runs"] if label(r) == mode and r["kind"] == kind]
            lines.append(f"| {mode} | {kind} | {_spread([r['frames_per_s'] for r in rs], '{:.1f}')} | "
                         f"{_spread([r['latency_median_ms'] for r in rs])} | "
                         f"{_spread([r['refined_after_ms'] for r in rs])} |")
    lines += ["", "Passes timed on the loaded scene (camera turning, frozen replays), median (min-max) ms:", ""]
    for name, p in result["passes"].items():
        what = f" ({p['mode']}" + (f", step {p['step_scale']:g}" if p.get("step_scale") else "") + ")" \
            if p.get("mode") else ""
        lines.append(f"* {name}{what} at {p['size'][0]}x{p['size'][1]}: {_spread(p['ms'], '{:.1f}')}")
    for name in [n for n in result["passes"] if n.startswith("fast") and n.endswith("_empty")]:
        bound = 1e3 / statistics.median(result["passes"][name]["ms"])
        own = result["passes"][name[:-len("_empty")]]
        jpeg = result["passes"].get(name[:-len("_empty")] + "_jpeg", {}).get("ms")
        ms = statistics.median(own["ms"])
        lines.append(f"* the empty-medium {name[:-len('_empty')]} pass bounds the drag at {bound:.0f} frames/s; "
                     f"the fast pass on this view at {1e3 / ms:.0f} frames/s"
                     + (f", with its JPEG encoding ({statistics.median(jpeg):.1f} ms) at "
                        f"{1e3 / (ms + statistics.median(jpeg)):.0f}" if jpeg else ""))
    return "\n".join(lines) + "\n"


def first_pictures(data, field=None, res: int = 256, repeats: int = 3, cold_kernels: bool = False) -> dict:
    """The first picture alone, as a new user meets it (`cli_first_picture`),
    ``repeats`` times, each ``mi-amr view`` a fresh process; with
    ``cold_kernels`` each gets an empty Dr.Jit kernel cache (a fresh
    ``HOME``), else the cache as earlier runs left it. The load average
    before each run beside its figures."""
    from playwright.sync_api import sync_playwright   # lazy: a benchmark dependency
    exe = shutil.which("chromium")
    if exe is None:
        raise SystemExit("the viewer benchmark needs Debian's chromium (make setup installs it)")
    runs = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
        for _ in range(repeats):
            load = os.getloadavg()[0]
            if cold_kernels:
                with tempfile.TemporaryDirectory(prefix="mi-amr-cold-") as home:
                    r = cli_first_picture(browser, data, field, res, env=dict(os.environ, HOME=home))
            else:
                r = cli_first_picture(browser, data, field, res)
            runs.append(dict(r, load_average=load))
        browser.close()
    return {"data": str(data), "res": res, "cold_kernels": cold_kernels, "runs": runs}


def first_report(result: dict) -> str:
    """One line per run of `first_pictures`, then median (min-max)."""
    lines = [f"{result['data']}, {result['res']}x{result['res']}, kernel cache "
             f"{'cold' if result['cold_kernels'] else 'warm'}: seconds from the process start"]
    keys = ("url_s", "page_first_picture_s", "first_picture_s", "first_refined_s")
    for r in result["runs"]:
        lines.append("  URL %.2f, page open -> first picture %.2f, first picture %.2f, first full-size %.2f "
                     "(load average %.2f)" % (*(r[k] for k in keys), r["load_average"]))
    for k in keys:
        xs = [r[k] for r in result["runs"]]
        lines.append(f"  {k}: {statistics.median(xs):.2f} ({min(xs):.2f}-{max(xs):.2f})")
    return "\n".join(lines)


def run(data, field, res, out_dir, repeats=3, seconds=4.0, preview_scale=0.5, modes=None, move_ms=16,
        driver="page", hybrids=(True,)):
    result = measure(data, field, res, seconds, repeats, preview_scale, modes, move_ms, driver, hybrids)
    write_report(out_dir, "view", result, report(result))


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--view``): every lighting mode,
    or those of ``args.view_modes`` where given."""
    run(args.view, args.view_field, args.res, Path(args.out), args.repeats, preview_scale=args.view_preview_scale,
        modes=getattr(args, "view_modes", None), move_ms=getattr(args, "view_move_ms", 16.0),
        hybrids=getattr(args, "view_hybrids", (True,)))
    print(f"wrote {args.out}/view.json and view.md")
    return 0


if __name__ == "__main__":
    # ``python -m mi_amr.bench.view DATA [REPEATS] [--cold]``: the first picture alone (`first_pictures`)
    argv = [a for a in sys.argv[1:] if a != "--cold"]
    out = first_pictures(argv[0], repeats=int(argv[1]) if len(argv) > 1 else 3, cold_kernels="--cold" in sys.argv)
    print(first_report(out))
