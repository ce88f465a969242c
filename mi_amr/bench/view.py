"""How interactive ``mi-amr view`` is, measured in the page.

``python -m mi_amr.bench --view DATA [--view-field F] [--res 256] --out DIR``
serves DATA as ``mi-amr view`` does, opens the page in Debian's chromium
(Playwright), waits for the first refined frame, then, ``--repeats`` times
each, drags the camera (an orbit) and a TF control point for ``seconds``
with a mouse move every 40 ms, and lets go. Read in the page
(``window.viewerStats``): frames on screen per second during the drag, the
time from a change to the first frame showing it (median and 90th
percentile), and the time from the last change to the first denoised image
(the preview's, then the first at full size).
Writes ``DIR/view.json`` and ``DIR/view.md``.
"""

from __future__ import annotations

import json
import shutil
import statistics
import time
from pathlib import Path


def _drag(page, box, kind: str, seconds: float):
    """Drag on ``box`` (the view or the TF editor) for ``seconds``."""
    if kind == "camera":
        x0, y0, dx, dy = box["x"] + 0.3 * box["width"], box["y"] + 0.5 * box["height"], 6.0, 0.0
    else:                                 # the tallest spiky peak, dragged down and up
        x0, y0, dx, dy = box["x"] + 8 + 0.8 * (box["width"] - 16), box["y"] + 8, 0.0, 4.0
    page.mouse.move(x0, y0)
    page.mouse.down()
    t0, k = time.monotonic(), 0
    while time.monotonic() - t0 < seconds:
        k += 1
        step = k % 40 if kind == "tf" else k
        sign = 1 if (k // 40) % 2 == 0 or kind == "camera" else -1
        page.mouse.move(x0 + dx * step, y0 + dy * (step if sign > 0 else 40 - step))
        page.wait_for_timeout(40)
    page.mouse.up()
    return time.monotonic() - t0


def measure(data, field=None, res: int = 256, seconds: float = 4.0, repeats: int = 3,
            preview_scale: float = 0.5) -> dict:
    from playwright.sync_api import sync_playwright

    from ..view.engine import ViewEngine
    from ..view.server import ViewServer
    exe = shutil.which("chromium")
    if exe is None:
        raise SystemExit("the viewer benchmark needs Debian's chromium (make setup installs it)")
    t0 = time.monotonic()
    engine = ViewEngine(data, field, res=res, preview_scale=preview_scale).start()
    server = ViewServer(engine, quiet=True, out_dir="/tmp").start()
    out = {"data": str(data), "res": res, "preview_scale": preview_scale, "runs": []}
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=exe, args=[
                "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run"])
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            page.goto(server.url)
            page.wait_for_function("window.viewerStats.lastFrame && !window.viewerStats.lastFrame.preview",
                                   timeout=600_000)
            out["first_picture_s"] = time.monotonic() - t0
            for r in range(repeats):
                for kind, testid in (("camera", "view"), ("tf", "tf-editor")):
                    page.wait_for_timeout(1500)
                    box = page.get_by_test_id(testid).bounding_box()
                    page.evaluate("window.viewerStats.latencies = []; window.viewerStats.frameTimes = [];"
                                  "window.viewerStats.denoiseLatencies = [];"
                                  "window.viewerStats.fullDenoiseLatencies = [];")
                    start = page.evaluate("performance.now()")
                    took = _drag(page, box, kind, seconds)
                    end = page.evaluate("performance.now()")
                    page.wait_for_function("window.viewerStats.fullDenoiseLatencies.length > 0", timeout=60_000)
                    s = page.evaluate("window.viewerStats")
                    shown = [t for t in s["frameTimes"] if start <= t <= end]
                    lat = sorted(s["latencies"])
                    out["runs"].append({
                        "kind": kind, "round": r, "drag_s": took, "frames_per_s": len(shown) / ((end - start) / 1e3),
                        "latency_median_ms": statistics.median(lat) if lat else None,
                        "latency_p90_ms": lat[int(0.9 * (len(lat) - 1))] if lat else None,
                        "denoised_after_ms": s["denoiseLatencies"][0],
                        "full_denoised_after_ms": s["fullDenoiseLatencies"][0]})
            page.screenshot(path=str(Path("/tmp") / "mi-amr-view-bench.png"))
            browser.close()
    finally:
        server.stop()
        engine.stop()
    return out


def report(result: dict) -> str:
    lines = [f"`mi-amr view` on {result['data']}, {result['res']}x{result['res']}, preview scale "
             f"{result['preview_scale']}; first refined picture in the page after "
             f"{result['first_picture_s']:.1f} s (load included)", "",
             "| drag | round | frames/s on screen | change -> frame, median / p90 ms | last change -> denoised (preview / full size) ms |",
             "|---|---|---|---|---|"]
    for r in result["runs"]:
        lines.append(f"| {r['kind']} | {r['round']} | {r['frames_per_s']:.1f} | {r['latency_median_ms']:.0f} / "
                     f"{r['latency_p90_ms']:.0f} | {r['denoised_after_ms']:.0f} / {r['full_denoised_after_ms']:.0f} |")
    return "\n".join(lines) + "\n"


def run(data, field, res, out_dir, repeats=3, seconds=4.0, preview_scale=0.5):
    result = measure(data, field, res, seconds, repeats, preview_scale)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "view.json").write_text(json.dumps(result, indent=1))
    (out_dir / "view.md").write_text(report(result))
    print(report(result))


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--view``)."""
    run(args.view, args.view_field, args.res, Path(args.out), args.repeats, preview_scale=args.view_preview_scale)
    print(f"wrote {args.out}/view.json and view.md")
    return 0
