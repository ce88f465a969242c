"""Scale benchmark: load, build, memory and frame time against the cell count.

    python -m mi_amr.bench --scale 1e5 1e6 1e7 1e8 --out DIR

For each size, data kind (``blocks``: block-structured, FLASH-like 16^3
blocks; ``cloud``: octree-like) and configuration, one fresh process loads
the data from a ``.cells`` file (generated once into ``--data-dir``), builds
the structures of an ``amr`` medium and renders a fixed frame. Recorded:
load seconds, build seconds per structure, cells per second, resident bytes
per cell (the medium's own accounting, and the process RSS growth), peak
bytes per cell (the highest RSS, polled every 5 ms during load and build,
above the RSS before loading), and
the first (compiling) and steady frame seconds. Writes ``scale.json``,
``scale.md`` and ``scale.png`` (log-log time and memory against cells).
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: Octree-like data are generated cell by cell in memory: not above this size by default.
OCTREE_MAX = 10**7
DEFAULT_CONFIGS = ("amrvolpath/grid/hash", "amrvolpath/kdtree/hash")


def data_file(kind: str, n: int, data_dir: Path) -> Path:
    """The ``.cells`` file of ``kind`` with about ``n`` cells, written on first use."""
    from ..data.datasets import ensure_dataset
    path = Path(data_dir) / f"{kind}-{n:.0e}.cells".replace("+", "")
    levels = 5 if kind == "blocks" else 4
    return ensure_dataset(path, kind, cells=n, levels=levels)


def measure_one(path: str, config: str, res: int, spp: int, variant: str) -> dict:
    """Runs in its own process: load ``path`` into one medium of
    ``config`` (``integrator/traversal/sampling``), build, render."""
    import os
    import resource

    from .._llvm import ensure_llvm_path
    ensure_llvm_path()
    import mitsuba as mi
    mi.set_variant(variant)
    import numpy as np

    import mi_amr
    from .bench import bench_scene
    def rss():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def peak():
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    import threading

    class RSSMonitor(threading.Thread):
        """Highest RSS seen, polled every 5 ms (the process's high-water
        mark from start-up may lie above anything the build reaches)."""

        def __init__(self):
            super().__init__(daemon=True)
            self.high, self.stop = rss(), threading.Event()

        def run(self):
            while not self.stop.wait(0.005):
                self.high = max(self.high, rss())

    integrator, traversal, sampling = config.split("/")
    base_rss, base_peak = rss(), peak()
    monitor = RSSMonitor()
    monitor.start()
    t0 = time.perf_counter()
    medium = {"type": "amr", "filename": path, "transfer_function": "spiky", "density_scale": 60.0,
              "reconstruction": "nearest", "traversal": traversal, "sampling": sampling}
    scene = mi.load_dict(bench_scene(medium, res, {"type": integrator, "max_depth": 64}))
    load_build = time.perf_counter() - t0
    med = mi_amr.amr_media(scene)[0]
    n = len(med.volume)
    build = dict(med.build_seconds)
    rss_built, peak_built = rss(), peak()
    monitor.stop.set()
    monitor.join()
    high_built = max(monitor.high, rss_built)
    t0 = time.perf_counter()
    np.array(mi.render(scene, spp=spp, seed=0))
    first = time.perf_counter() - t0
    steady = []
    for seed in (1, 2, 3):
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, spp=spp, seed=seed))
        steady.append(time.perf_counter() - t0)
    return {"file": path, "config": config, "cells": n, "block": med.volume.block,
            "load_build_s": load_build, "load_s": load_build - sum(build.values()), "build_s": build,
            "cells_per_s": n / load_build,
            "resident_B_per_cell": med.resident_bytes / n,
            "rss_growth_B_per_cell": (rss_built - base_rss) / n,
            "peak_build_B_per_cell": (high_built - base_rss) / n,
            "peak_build_maxrss_B_per_cell": max(peak_built - base_peak, 0) / n,
            "peak_render_B_per_cell": max(peak() - base_peak, 0) / n,
            "first_frame_s": first, "steady_frame_s": statistics.median(steady),
            "image_mean": float(img.mean()), "res": res, "spp": spp}


def run_scale(sizes, kinds, configs, out: Path, data_dir: Path, res: int, spp: int, variant: str) -> list:
    out.mkdir(parents=True, exist_ok=True)
    records = []
    for n in sizes:
        for kind in kinds:
            if kind != "blocks" and n > OCTREE_MAX:
                print(f"{kind} {n:.0e}: skipped (octree-like data above {OCTREE_MAX:.0e} cells "
                      "are generated in memory)", flush=True)
                continue
            t0 = time.perf_counter()
            path = data_file(kind, int(n), data_dir)
            print(f"{kind} {n:.0e}: {path} ready ({time.perf_counter() - t0:.0f} s)", flush=True)
            for config in configs:
                cmd = [sys.executable, "-m", "mi_amr.tools.scale_bench", "--one", str(path), config,
                       str(res), str(spp), variant]
                r = subprocess.run(cmd, capture_output=True, text=True)
                if r.returncode != 0:
                    tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["no output"]
                    print(f"  {config}: failed: {tail[0]}", flush=True)
                    records.append({"kind": kind, "target_cells": n, "config": config, "error": tail[0]})
                    continue
                rec = json.loads(r.stdout.strip().splitlines()[-1])
                rec.update(kind=kind, target_cells=n)
                records.append(rec)
                print(f"  {config:24s} {rec['cells']:>10d} cells: load+build {rec['load_build_s']:7.2f} s "
                      f"({rec['cells_per_s'] / 1e6:5.2f} M cells/s), resident {rec['resident_B_per_cell']:5.2f} "
                      f"B/cell, peak {rec['peak_build_B_per_cell']:6.1f} B/cell, frame "
                      f"{rec['first_frame_s']:6.2f} s first / {rec['steady_frame_s']:6.2f} s steady", flush=True)
                (out / "scale.json").write_text(json.dumps(records, indent=1))
    write_scale_table(records, out)
    plot_scale(records, out)
    return records


def write_scale_table(records, out: Path):
    lines = ["# mi-amr scale benchmark", "",
             "| data | cells | configuration | load s | build s | M cells/s | resident B/cell | "
             "peak B/cell | first frame s | steady frame s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        if "error" in r:
            lines.append(f"| {r['kind']} | {r['target_cells']:.0e} | {r['config']} | failed: {r['error']} "
                         "| | | | | | |")
            continue
        build = ", ".join(f"{k} {v:.2f}" for k, v in r["build_s"].items())
        lines.append(f"| {r['kind']} (B={r['block']}) | {r['cells']:,} | {r['config']} | {r['load_s']:.2f} | "
                     f"{build} | {r['cells_per_s'] / 1e6:.2f} | {r['resident_B_per_cell']:.2f} | "
                     f"{r['peak_build_B_per_cell']:.1f} | {r['first_frame_s']:.2f} | {r['steady_frame_s']:.2f} |")
    if records:
        r0 = next((r for r in records if "error" not in r), None)
        if r0:
            lines += ["", f"Frames: {r0['res']}x{r0['res']}, {r0['spp']} spp, amr medium with the spiky TF, "
                      "nearest reconstruction; each row a fresh process."]
    (out / "scale.md").write_text("\n".join(lines) + "\n")


def plot_scale(records, out: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ok = [r for r in records if "error" not in r]
    if not ok:
        return
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6))
    styles = {"blocks": "-", "cloud": "--"}
    for (kind, config) in sorted({(r["kind"], r["config"]) for r in ok}):
        rs = sorted((r for r in ok if r["kind"] == kind and r["config"] == config), key=lambda r: r["cells"])
        x = [r["cells"] for r in rs]
        label = f"{kind} {config.split('/', 1)[1]}"
        a.loglog(x, [r["load_build_s"] for r in rs], styles.get(kind, ":"), marker="o", label=f"{label} load+build")
        a.loglog(x, [r["steady_frame_s"] for r in rs], styles.get(kind, ":"), marker="s", label=f"{label} frame")
        b.loglog(x, [r["resident_B_per_cell"] * r["cells"] for r in rs], styles.get(kind, ":"), marker="o",
                 label=f"{label} resident")
        b.loglog(x, [max(r["peak_build_B_per_cell"], 1e-3) * r["cells"] for r in rs], styles.get(kind, ":"),
                 marker="^", label=f"{label} peak")
    a.set_xlabel("cells")
    a.set_ylabel("seconds")
    b.set_xlabel("cells")
    b.set_ylabel("bytes")
    a.legend(fontsize=6)
    b.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "scale.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    if len(sys.argv) == 7 and sys.argv[1] == "--one":
        print(json.dumps(measure_one(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), sys.argv[6])))
    else:
        sys.exit("usage: python -m mi_amr.bench --scale N [N ...] --out DIR")
