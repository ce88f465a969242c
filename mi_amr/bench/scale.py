"""Scale benchmark: time to the first picture, memory and frame time against the cell count.

    python -m mi_amr.bench --scale 1e7 1e8 --out DIR

For each size, data kind and source, and configuration, one fresh process
opens the data file, builds the structures of an ``amr`` medium, compiles
and renders a first frame, then renders the same frame again. Kinds:
``blocks`` (block-structured, FLASH-like 16^3 blocks over 5 levels),
``mixed`` (blocks of 8^3, 16^3 and 32^3 over 3 levels) and ``cloud``
(octree-like, up to `OCTREE_MAX` cells); sources: the ``.cells`` file
(generated once into ``--data-dir``) and the native ``.amrb`` converted
from it. Recorded: **time to the first picture** (open + build + compile
+ first frame), its parts, cells per second of open + build, resident bytes
per cell (the medium's own accounting, and the process RSS growth), peak
bytes per cell (the highest RSS, polled every 5 ms during load and build,
above the RSS before loading) and the steady frame. Writes ``scale.json``,
``scale.md`` and ``scale.png`` (log-log time and memory against cells).
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

import mi_amr
from ..data.cells import AMRCells
from ..data.datasets import ensure_dataset, make_dataset, write_block_dataset
from ..data.io import load_volume, write_exabricks
from ..native_file import save_native
from .harness import bench_scene

#: Octree-like data are generated cell by cell in memory: not above this size by default.
OCTREE_MAX = 10**7
DEFAULT_CONFIGS = ("amrvolpath/grid/hash",)
DEFAULT_KINDS = ("blocks", "mixed", "cloud")
DEFAULT_SOURCES = ("cells", "amrb")
#: Block sizes and levels of the block-structured kinds.
BLOCK_KINDS = {"blocks": (16, 5), "mixed": ((8, 16, 32), 3)}


def data_file(kind: str, n: int, data_dir: Path, source: str = "cells", layout: str = "blocks") -> Path:
    """The ``.cells`` file of ``kind`` with about ``n`` cells laid out as
    ``layout`` (`mi_amr.data.datasets.LAYOUTS`; written on first use,
    streaming for the block kinds), or its ``.amrb`` conversion."""
    data_dir = Path(data_dir)
    suffix = "" if layout == "blocks" else f"-{layout}"
    path = data_dir / f"{kind}-{n:.0e}{suffix}.cells".replace("+", "")
    if not path.exists():
        if kind in BLOCK_KINDS:
            nxb, levels = BLOCK_KINDS[kind]
            if layout == "level":                 # one physical block size: 32^3 finest, fewer cells above
                nxb = 32
            write_block_dataset(path, n, levels, nxb=nxb, layout=layout)
        elif layout == "shuffled":                 # octree-like cells in random order
            cells = make_dataset(kind, n, levels=4)
            perm = np.random.default_rng(2).permutation(len(cells))
            write_exabricks(AMRCells(cells.pos[perm], cells.level[perm], cells.values[perm], validate=False), path)
        elif layout != "blocks":
            raise ValueError(f"layout {layout!r} applies to block-structured kinds ({', '.join(BLOCK_KINDS)}); "
                             f"{kind} takes blocks or shuffled")
        else:
            ensure_dataset(path, kind, cells=n, levels=4)
    if source == "cells":
        return path
    if source != "amrb":
        raise ValueError(f"unknown source {source!r} (choose from cells, amrb)")
    native = path.with_suffix(".amrb")
    if not native.exists():
        save_native(load_volume(path), native)
    return native


def measure_one(path: str, config: str, res: int, spp: int, variant: str) -> dict:
    """Runs in its own process: load ``path`` into one medium of
    ``config`` (``integrator/traversal/sampling``), build, render."""
    mi.set_variant(variant)
    def rss():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def peak():
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

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
    first_img = np.array(mi.render(scene, spp=spp, seed=0))
    first = time.perf_counter() - t0
    steady = []
    for seed in (1, 2, 3):
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, spp=spp, seed=seed))
        steady.append(time.perf_counter() - t0)
    return {"file": path, "config": config, "cells": n, "block": med.volume.block,
            "load_build_s": load_build, "load_s": load_build - sum(build.values()), "build_s": build,
            "cells_per_s": n / load_build, "first_picture_s": load_build + first,
            "resident_B_per_cell": med.resident_bytes / n,
            "rss_growth_B_per_cell": (rss_built - base_rss) / n,
            "peak_build_B_per_cell": (high_built - base_rss) / n,
            "peak_build_maxrss_B_per_cell": max(peak_built - base_peak, 0) / n,
            "peak_render_B_per_cell": max(peak() - base_peak, 0) / n,
            "peak_process_GiB": peak() / 2**30,
            "first_frame_s": first, "steady_frame_s": statistics.median(steady),
            "image_finite": bool(np.isfinite(first_img).all() and np.isfinite(img).all()),
            "image_mean": float(img.mean()), "res": res, "spp": spp}


def run_scale(sizes, kinds, configs, out: Path, data_dir: Path, res: int, spp: int, variant: str,
              sources=DEFAULT_SOURCES, cold_kernels: bool = False, layouts=("blocks",)) -> list:
    """Every size x kind x layout x source x configuration, one fresh
    process each; ``layouts``: file layouts of the ``.cells`` data
    (`mi_amr.data.datasets.LAYOUTS`; ``blocks`` is the generator's, the
    others are read from ``.cells`` only: their ``.amrb`` is the same
    file); ``cold_kernels``: each process starts with an empty Dr.Jit
    kernel cache (a new user's first run), else the cache of this
    machine's user."""
    out.mkdir(parents=True, exist_ok=True)
    records = []
    jobs = [(n, kind, layout, source) for n in sizes for kind in kinds for layout in layouts
            for source in (sources if layout == "blocks" else [s for s in sources if s == "cells"])]
    for n, kind, layout, source in jobs:
        if kind not in BLOCK_KINDS and n > OCTREE_MAX:
            print(f"{kind} {n:.0e}: skipped (octree-like data above {OCTREE_MAX:.0e} cells "
                  "are generated in memory)", flush=True)
            continue
        if kind not in BLOCK_KINDS and layout not in ("blocks", "shuffled"):
            continue                             # octree-like data have no blocks to reorder
        t0 = time.perf_counter()
        path = data_file(kind, int(n), data_dir, source, layout)
        print(f"{kind} {n:.0e} {layout}: {path} ready ({time.perf_counter() - t0:.0f} s)", flush=True)
        for config in configs:
            rec = _run_one(path, config, res, spp, variant, cold_kernels)
            rec.update(kind=kind, target_cells=n, source=source, cold_kernels=cold_kernels, layout=layout)
            records.append(rec)
            if "error" in rec:
                print(f"  {config}: failed: {rec['error']}", flush=True)
            else:
                print(f"  {source:5s} {config:22s} {rec['cells']:>13,d} cells: first picture "
                      f"{rec['first_picture_s']:7.2f} s (open+build {rec['load_build_s']:7.2f} s, "
                      f"{rec['cells_per_s'] / 1e6:6.2f} M cells/s; first frame {rec['first_frame_s']:5.2f} s)"
                      f", steady frame {rec['steady_frame_s']:5.3f} s, resident "
                      f"{rec['resident_B_per_cell']:5.2f} B/cell, peak {rec['peak_build_B_per_cell']:6.1f}"
                      " B/cell", flush=True)
            (out / "scale.json").write_text(json.dumps(records, indent=1))
    write_scale_table(records, out)
    plot_scale(records, out)
    return records


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--scale``): the first picture,
    256x256 at 1 spp unless ``--res``/``--spp`` are given."""
    spp = 1 if args.spp == 16 else args.spp
    run_scale([int(n) for n in args.scale], args.scale_kinds or DEFAULT_KINDS,
              args.scale_configs or DEFAULT_CONFIGS, Path(args.out), Path(args.data_dir), args.res, spp,
              args.variant, args.scale_sources or DEFAULT_SOURCES, args.cold_kernels,
              tuple(args.layouts or ("blocks",)))
    print(f"wrote {args.out}/scale.json, scale.md and scale.png")
    return 0


def _run_one(path, config, res, spp, variant, cold_kernels) -> dict:
    cmd = [sys.executable, "-m", "mi_amr.bench.scale", "--one", str(path), config, str(res), str(spp), variant]
    with tempfile.TemporaryDirectory(prefix="mi-amr-kernels-") as home:
        env = dict(os.environ, HOME=home) if cold_kernels else None
        r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["no output"]
        return {"file": str(path), "config": config, "error": tail[0]}
    return json.loads(r.stdout.strip().splitlines()[-1])


def write_scale_table(records, out: Path):
    lines = ["# mi-amr scale benchmark", "",
             "| data | layout | source | cells | configuration | **first picture s** | open + build s | M cells/s | "
             "build s | first frame s | steady frame s | resident B/cell | peak B/cell |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        if "error" in r:
            lines.append(f"| {r['kind']} | {r.get('layout', 'blocks')} | {r.get('source', 'cells')} | "
                         f"{r['target_cells']:.0e} | {r['config']} | failed: {r['error']} | | | | | | | |")
            continue
        build = ", ".join(f"{k} {v:.2f}" for k, v in r["build_s"].items())
        lines.append(f"| {r['kind']} (B={r['block']}) | {r.get('layout', 'blocks')} | {r.get('source', 'cells')} | "
                     f"{r['cells']:,} | {r['config']} | "
                     f"**{r['first_picture_s']:.2f}** | {r['load_build_s']:.2f} | {r['cells_per_s'] / 1e6:.2f} | "
                     f"{build} | {r['first_frame_s']:.2f} | {r['steady_frame_s']:.3f} | "
                     f"{r['resident_B_per_cell']:.2f} | {r['peak_build_B_per_cell']:.1f} |")
    r0 = next((r for r in records if "error" not in r), None)
    if r0:
        kernels = "an empty Dr.Jit kernel cache per process" if r0.get("cold_kernels") else \
            "the machine's Dr.Jit kernel cache (warm after the first row)"
        lines += ["", f"Frames: {r0['res']}x{r0['res']}, {r0['spp']} spp, amr medium with the spiky TF, "
                  f"nearest reconstruction; each row a fresh process, with {kernels}. First picture: "
                  "open + build + compile + first frame."]
    (out / "scale.md").write_text("\n".join(lines) + "\n")


def plot_scale(records, out: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ok = [r for r in records if "error" not in r]
    if not ok:
        return
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6))
    styles = {"blocks": "-", "mixed": "-.", "cloud": "--"}
    for (kind, layout, source, config) in sorted({(r["kind"], r.get("layout", "blocks"), r.get("source", "cells"),
                                                   r["config"]) for r in ok}):
        rs = sorted((r for r in ok if r["kind"] == kind and r.get("source", "cells") == source
                     and r.get("layout", "blocks") == layout and r["config"] == config), key=lambda r: r["cells"])
        x = [r["cells"] for r in rs]
        label = f"{kind}{'' if layout == 'blocks' else ' ' + layout} .{source} {config.split('/', 1)[1]}"
        a.loglog(x, [r["first_picture_s"] for r in rs], styles.get(kind, ":"), marker="o",
                 label=f"{label} first picture")
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
