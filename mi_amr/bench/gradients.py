"""What a gradient step costs (docs/performance/gradients.md):
``python -m mi_amr.bench --grad --out DIR``.

For each data set of ``--grad-data`` (``NAME:CELLS:LEVELS`` of
`mi_amr.data.datasets.make_dataset`; by default the protocol-like 20,000
cells of ``cloud`` on 4 levels and 10^6 cells on 3 levels), with the
``spiky`` TF in the benchmark's view (`mi_amr.bench.harness.bench_scene`),
``--grad-res`` x ``--grad-res`` at ``--grad-spp`` samples per pixel, rows:

* ``amr`` in ``amrvolpath``: the primal frame (not differentiable; the
  renderer a user renders pictures with);
* ``amr`` in each integrator of ``--grad-integrators`` (Mitsuba's
  ``prbvolpath`` and, when the plugin can be loaded, ``amrprbvolpath``; a
  name that does not load is skipped with its reason): the primal frame, and
  a **gradient step** with respect to ``values`` (every cell) and to
  ``tf_rgba``;
* Mitsuba's ``heterogeneous`` + ``gridvolume`` on the same field resampled
  at the finest resolution (``nearest``: the same extinction and albedo,
  `mi_amr.reference.reference_medium`) in ``prbvolpath``: the primal
  frame and a gradient step with respect to the ``sigma_t`` grid's voxels.

A gradient step is what an optimisation loop runs per iteration before its
optimiser: ``mi.render(scene, params)`` with the parameter's gradients
enabled, the L2 loss to a target image (0.8 x an amrvolpath image of the same
scene), ``dr.backward`` and the parameter's gradient evaluated. Its time is
split into the render (primal pass, ``dr.eval`` of the image) and the
backward (the integrator's adjoint pass). Beside it, ``update``: what
``params.update()`` costs after the parameter changes (x1.001; the ``amr``
medium rebuilds its structures on new values, docs/design.md section 13).

Timing follows the other benchmarks (docs/performance/protocol.md), without
``dr.freeze`` (every row traces Python, as an optimisation loop does):
passes alternate within a round, one scene alive at a time, each kind
(primal, each gradient) warmed up once (its kernels compiled), then
``--grad-steps`` steps timed after the process is idle and their median
kept, ``--repeats`` rounds; wall and process CPU seconds.

Memory, from one further step of each kind, untimed: **Dr.Jit's peak**
(``drjit.detail.malloc_watermark`` of the backend after the step, less the
bytes in use before it, with the allocation cache flushed and the statistics
cleared first: every array the step allocates, Mitsuba's and ours; not
LLVM's compiler, numpy or Python) and the **peak RSS growth** of the process
(``/proc/self/statm`` sampled every millisecond by a thread during the step,
less the RSS before it; Linux only).
"""

from __future__ import annotations

import gc
import json
import os
import statistics
import threading
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_amr
from ..data.datasets import make_dataset
from ..reference import dense_shape, reference_medium
from .harness import bench_scene, check_alone, process_cpu_seconds, wait_idle
from .protocol import SCALES

#: The medium's parameters in the benchmark scene (its shape is ``volume``).
MEDIUM = "volume.interior_medium"
#: Parameter of each gradient kind: the cells' values, the TF table, the
#: dense grid's voxels (extinction before the scale).
KEYS = {"values": f"{MEDIUM}.values", "tf_rgba": f"{MEDIUM}.tf_rgba", "voxels": f"{MEDIUM}.sigma_t.data"}
#: Integrators of the gradient rows (``--grad-integrators``).
INTEGRATORS = ("prbvolpath", "amrprbvolpath")
#: The renderer of the primal-only row (not differentiable).
PRIMAL_ONLY = "amrvolpath"
#: Mitsuba's differentiable integrator, used for the dense rows.
DENSE_INTEGRATOR = "prbvolpath"
#: The target image: this share of an amrvolpath image of the same scene.
TARGET_SHARE = 0.8
#: The change of each update (alternately times it and divided by it, down first).
UPDATE_FACTOR = 1.0 / 1.001


# ---- Scenes ----------------------------------------------------------------------
def parse_data(spec: str):
    """``NAME:CELLS:LEVELS`` (``cloud:1e6:3``) -> ``(name, cells, levels)``."""
    parts = spec.split(":")
    name = parts[0]
    cells = int(float(parts[1])) if len(parts) > 1 else 20000
    levels = int(parts[2]) if len(parts) > 2 else 4
    return name, cells, levels


def integrator_loads(name: str):
    """``None`` when the integrator plugin ``name`` loads, else why not (a
    plugin another module registers may not be there yet)."""
    try:
        mi.load_dict({"type": name})
        return None
    except Exception as e:                       # noqa: BLE001 (any failure: the row is skipped)
        words = str(e).strip().splitlines()[-1] if str(e).strip() else ""
        return f"{type(e).__name__}: {words.rsplit(': ', 1)[-1][:120]}"


def pass_plan(integrators) -> list:
    """``(medium, integrator, kinds)`` of each pass of a round: the primal
    of amrvolpath, the primal and the two gradients of each integrator on
    ``amr``, the primal and the voxels' gradient of the dense medium."""
    plan = [("amr", PRIMAL_ONLY, ["primal"])]
    plan += [("amr", name, ["primal", "values", "tf_rgba"]) for name in integrators]
    plan.append(("dense", DENSE_INTEGRATOR, ["primal", "voxels"]))
    return plan


def row_label(medium: str, integrator: str, kind: str) -> str:
    return f"{medium} {integrator} " + ("primal" if kind == "primal" else f"grad {kind}")


# ---- Memory ----------------------------------------------------------------------
_PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_bytes() -> int:
    """Resident set size of this process now (Linux ``/proc/self/statm``)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * _PAGE


class RSSPeak:
    """The peak RSS over a ``with`` block, sampled by a thread every
    ``interval`` seconds (Dr.Jit releases the GIL while its kernels run)."""

    def __init__(self, interval: float = 0.001):
        self.interval, self.peak, self.samples = interval, 0, 0
        self._stop = threading.Event()

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_bytes())
            self.samples += 1
            time.sleep(self.interval)

    def __enter__(self):
        self.base = rss_bytes()
        self.peak = self.base
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss_bytes())
        self.growth = self.peak - self.base


def backend():
    return dr.JitBackend.CUDA if mi.variant().startswith("cuda") else dr.JitBackend.LLVM


# ---- One step --------------------------------------------------------------------
def step(scene, params, kind: str, spp: int, target, seed: int = 0) -> dict:
    """One primal frame (``kind`` "primal") or one gradient step with respect
    to ``KEYS[kind]`` (its gradients enabled before, untimed). Returns the
    wall and CPU seconds, the render and backward parts, and (gradient) the
    gradient's Dr.Jit array."""
    if kind != "primal":
        dr.enable_grad(params[KEYS[kind]])
        params.update()
    c0, t0 = process_cpu_seconds(), time.perf_counter()
    if kind == "primal":
        img = mi.render(scene, spp=spp, seed=seed)
        dr.eval(img)
        dr.sync_thread()
        t1 = time.perf_counter()
        return {"wall": t1 - t0, "cpu": process_cpu_seconds() - c0, "render": t1 - t0, "backward": 0.0}
    img = mi.render(scene, params, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    t1 = time.perf_counter()
    loss = dr.mean(dr.square(img - target), axis=None)
    dr.backward(loss)
    grad = dr.grad(params[KEYS[kind]])
    dr.eval(grad)
    dr.sync_thread()
    t2 = time.perf_counter()
    return {"wall": t2 - t0, "cpu": process_cpu_seconds() - c0, "render": t1 - t0, "backward": t2 - t1,
            "grad": grad}


def update(params, key: str, factor: float) -> float:
    """Seconds of ``params.update()`` after the parameter is scaled by
    ``factor`` (its gradients dropped: a new, detached variable; empty
    slots of ``values`` stay NaN; the TF's entries kept in [0, 1])."""
    value = dr.detach(params[key]) * factor
    params[key] = dr.minimum(value, 1.0) if key == KEYS["tf_rgba"] else value
    dr.eval(params[key])
    dr.sync_thread()
    t0 = time.perf_counter()
    params.update()
    dr.sync_thread()
    return time.perf_counter() - t0


def memory_step(scene, params, kind: str, spp: int, target) -> dict:
    """Peak memory of one step: Dr.Jit's (its allocation cache flushed and
    statistics cleared, then the watermark less the bytes in use before)
    and the process's RSS growth (`RSSPeak`). Dr.Jit rounds an allocation
    up to a power of two, and counts it so: its peak is what the step
    reserved, up to twice what it needed. ``drjit_before_bytes`` is not the
    scene's size: arrays uploaded from numpy (the ``amr`` medium's) are not
    counted, arrays kernels compute (the dense medium's grids) are."""
    if kind != "primal":
        dr.enable_grad(params[KEYS[kind]])
        params.update()
    gc.collect()
    dr.sync_thread()
    dr.flush_malloc_cache()
    dr.detail.malloc_clear_statistics()
    base = dr.detail.malloc_watermark(backend())
    with RSSPeak() as rss:
        s = step(scene, params, kind, spp, target, seed=0)
        del s
    peak = dr.detail.malloc_watermark(backend())
    if kind != "primal":
        dr.disable_grad(params[KEYS[kind]])
        params.update()
    return {"drjit_peak_bytes": int(peak - base), "drjit_before_bytes": int(base),
            "rss_peak_growth_bytes": int(rss.growth), "rss_samples": rss.samples}


def gradient_stats(grad, present=None) -> dict:
    """Size, finiteness and how many entries are non-zero (over ``present``
    entries, e.g. the cells' slots of ``values``, when given)."""
    g = np.asarray(grad, dtype=np.float64).ravel()
    sel = g if present is None else g[present]
    return {"size": int(g.size), "bytes": int(g.size * 4), "finite": bool(np.isfinite(g).all()),
            "nonzero": int(np.count_nonzero(sel)), "entries": int(sel.size),
            "abs_sum": float(np.abs(sel[np.isfinite(sel)]).sum())}


# ---- A case ----------------------------------------------------------------------
def case_scenes(cells, tf, scale: float, res: int, max_depth: int, integrators, memory_limit: int) -> dict:
    """``{(medium, integrator): scene dict}`` of one data set (the dense
    resampling made once)."""
    amr = {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": float(scale),
           "reconstruction": "nearest"}
    scenes = {("amr", PRIMAL_ONLY): bench_scene(amr, res, {"type": PRIMAL_ONLY, "max_depth": max_depth})}
    for name in integrators:
        scenes[("amr", name)] = bench_scene(amr, res, {"type": name, "max_depth": max_depth})
    dense = reference_medium(cells, tf, scale, "nearest", memory_limit=memory_limit)
    scenes[("dense", DENSE_INTEGRATOR)] = bench_scene(dense, res, {"type": DENSE_INTEGRATOR, "max_depth": max_depth})
    return scenes


def gradient_case(cells, tf, scale: float, *, res: int = 128, spp: int = 4, steps: int = 3, repeats: int = 3,
                  integrators=INTEGRATORS, max_depth: int = 64, memory: bool = True,
                  memory_limit: int = 4 << 30, log=print) -> dict:
    """Every row of one data set (module docstring), rounds of alternating
    passes. Returns ``{"rows": {label: row}, "skipped": {label: reason},
    "params": {...}, ...}``; a row holds per round the median of its timed
    steps (``wall``, ``cpu``, ``render``, ``backward``, ``update``), its
    memory per round and, for a gradient, the last gradient's statistics."""
    skipped, usable = {}, []
    for name in integrators:
        why = integrator_loads(name)
        if why is None:
            usable.append(name)
        else:
            for kind in ("primal", "values", "tf_rgba"):
                skipped[row_label("amr", name, kind)] = f"integrator {name} does not load: {why}"
    scenes = case_scenes(cells, tf, scale, res, max_depth, usable, memory_limit)
    plan = pass_plan(usable)
    rows = {row_label(m, i, k): {"medium": m, "integrator": i, "kind": k, "wall": [], "cpu": [], "render": [],
                                 "backward": [], "update": [], "memory": []}
            for m, i, kinds in plan for k in kinds}
    info = {"cells": len(cells), "dense_shape": list(dense_shape(cells)), "res": res, "spp": spp,
            "steps": steps, "repeats": repeats, "max_depth": max_depth, "density_scale": scale}
    target = None
    for r in range(repeats):
        for medium, integ, kinds in plan:
            check_alone(f"{medium} {integ}")
            scene = mi.load_dict(scenes[(medium, integ)])
            params = mi.traverse(scene)
            if target is None:               # 0.8 x the first scene's image (amrvolpath), untimed
                target = mi.TensorXf(TARGET_SHARE * np.array(mi.render(scene, spp=spp, seed=12345)))
            if r == 0:
                info.setdefault("param_sizes", {})
                for kind in kinds[1:]:
                    info["param_sizes"][kind] = int(dr.width(params[KEYS[kind]]))
                if medium == "amr" and "values" in kinds:
                    med = mi_amr.amr_media(scene)[0]
                    present = med.value_index(cells)
                    info["value_slots"] = int(dr.width(params[KEYS["values"]]))
                    info["resident_bytes"] = int(med.resident_bytes)
                    del med
            for kind in kinds:
                row = rows[row_label(medium, integ, kind)]
                factor = UPDATE_FACTOR
                s = step(scene, params, kind, spp, target)                  # warm-up: kernels compiled
                if kind != "primal":
                    update(params, KEYS[kind], factor)
                    factor = 1.0 / factor
                del s
                times = {k: [] for k in ("wall", "cpu", "render", "backward", "update")}
                for _ in range(steps):
                    wait_idle()
                    s = step(scene, params, kind, spp, target)
                    for k in ("wall", "cpu", "render", "backward"):
                        times[k].append(s[k])
                    if kind != "primal":
                        if r == repeats - 1:
                            row["grad"] = gradient_stats(s["grad"], present if kind == "values" else None)
                        del s
                        times["update"].append(update(params, KEYS[kind], factor))
                        factor = 1.0 / factor
                    else:
                        del s
                for k, v in times.items():
                    if v:
                        row[k].append(statistics.median(v))
                if memory:
                    row["memory"].append(memory_step(scene, params, kind, spp, target))
                log(f"  round {r + 1}/{repeats} {row_label(medium, integ, kind):38s} "
                    f"{1e3 * row['wall'][-1]:9.1f} ms (render {1e3 * row['render'][-1]:8.1f}, backward "
                    f"{1e3 * row['backward'][-1]:8.1f})"
                    + (f" Dr.Jit peak {row['memory'][-1]['drjit_peak_bytes'] / 2**20:8.1f} MiB, RSS +"
                       f"{row['memory'][-1]['rss_peak_growth_bytes'] / 2**20:8.1f} MiB" if memory else ""))
            del params, scene
            gc.collect()
    for row in rows.values():
        base = rows[row_label(row["medium"], row["integrator"], "primal")]
        row["vs_primal"] = ratio_stats(row["wall"], base["wall"])
        row["vs_primal_cpu"] = ratio_stats(row["cpu"], base["cpu"])
        row["vs_amrvolpath"] = ratio_stats(row["wall"], rows[row_label("amr", PRIMAL_ONLY, "primal")]["wall"])
    dense_grad = rows[row_label("dense", DENSE_INTEGRATOR, "voxels")]
    for row in rows.values():
        if row["kind"] in ("values", "tf_rgba"):
            row["vs_dense_grad"] = ratio_stats(row["wall"], dense_grad["wall"])
            row["vs_dense_grad_cpu"] = ratio_stats(row["cpu"], dense_grad["cpu"])
    return {**info, "rows": rows, "skipped": skipped}


def ratio_stats(times, base) -> dict:
    """Median and range of the per-round ratios ``t / t_base``."""
    r = sorted(t / b for t, b in zip(times, base))
    return {"median": statistics.median(r), "range": [r[0], r[-1]]}


# ---- Tables ----------------------------------------------------------------------
def _spread(v, scale=1e3) -> str:
    """Median (min-max) of per-round values, times ``scale``."""
    v = sorted(scale * x for x in v)
    if not v:
        return "-"
    return f"{statistics.median(v):.0f} ({v[0]:.0f}-{v[-1]:.0f})" if v[-1] >= 100 else \
        f"{statistics.median(v):.1f} ({v[0]:.1f}-{v[-1]:.1f})"


def _ratio(r) -> str:
    return f"{r['median']:.2f} ({r['range'][0]:.2f}-{r['range'][1]:.2f})"


def _mib(row, key) -> str:
    v = [m[key] for m in row["memory"]]
    return f"{statistics.median(v) / 2**20:.1f}" if v else "-"


def _grad_cell(g) -> str:
    return f"{g['entries']:,} ({g['nonzero']:,})" if g else "-"


def case_table(case: dict) -> list:
    lines = [f"### {case['dataset']}: {case['cells']:,} cells, dense grid "
             f"{'x'.join(str(n) for n in case['dense_shape'][::-1])} "
             f"({int(np.prod(case['dense_shape'])):,} voxels); {case['res']}x{case['res']}, {case['spp']} spp", "",
             "| row | step ms, wall | step ms, CPU | render ms | backward ms | update ms | / primal (wall) | "
             "/ primal (CPU) | / amrvolpath primal | / dense grad (wall) | (CPU) | Dr.Jit peak MiB | RSS peak growth MiB | "
             "gradient entries (non-zero) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, row in case["rows"].items():
        g = row.get("grad")
        lines.append(
            f"| {label} | {_spread(row['wall'])} | {_spread(row['cpu'])} | {_spread(row['render'])} | "
            f"{_spread(row['backward']) if row['kind'] != 'primal' else '-'} | {_spread(row['update'])} | "
            f"{_ratio(row['vs_primal']) if row['kind'] != 'primal' else '1'} | "
            f"{_ratio(row['vs_primal_cpu']) if row['kind'] != 'primal' else '1'} | {_ratio(row['vs_amrvolpath'])} | "
            f"{_ratio(row['vs_dense_grad']) if 'vs_dense_grad' in row else '-'} | "
            f"{_ratio(row['vs_dense_grad_cpu']) if 'vs_dense_grad_cpu' in row else '-'} | "
            f"{_mib(row, 'drjit_peak_bytes')} | {_mib(row, 'rss_peak_growth_bytes')} | "
            f"{_grad_cell(g)} |")
    for label, why in case["skipped"].items():
        lines.append(f"| {label} | skipped: {why} |" + " |" * 12)
    return lines


def params_table(cases: list) -> list:
    """Parameter counts and bytes: the AMR values against the dense voxels."""
    lines = ["| data | cells | `values` entries (slots of the blocks) | `values` bytes | `tf_rgba` entries | "
             "amr resident bytes (data + structures) | dense voxels (`sigma_t.data`) | voxel bytes | "
             "dense grids' bytes (sigma_t + albedo) | voxels / values |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        p = c["param_sizes"]
        v, vox = p.get("values", 0), p["voxels"]
        lines.append(f"| {c['dataset']} | {c['cells']:,} | {v:,} | {4 * v / 2**20:.2f} MiB | "
                     f"{p.get('tf_rgba', 0):,} | {c.get('resident_bytes', 0) / 2**20:.1f} MiB | {vox:,} | "
                     f"{4 * vox / 2**20:.1f} MiB | {16 * vox / 2**20:.1f} MiB | "
                     f"{vox / v if v else float('nan'):.1f} |")
    return lines


def write_tables(cases: list, out: Path, command: str, load: list):
    lines = ["# What a gradient step costs", "", f"`{command}`", "",
             f"Load average (1 min) at the start of each case and at the end: "
             f"{', '.join(f'{x:.2f}' for x in load)}.", "", "## Parameters", ""]
    lines += params_table(cases)
    lines += ["", "## Time and memory", "",
              "Times: median (min-max) over rounds of each round's median step. Ratios: per round, the row "
              "over the primal of the same medium and integrator, over amrvolpath's primal frame and over the "
              "dense medium's gradient step; "
              "median (min-max). Memory: one untimed step per round, median over rounds (Dr.Jit peak: "
              "malloc watermark less the bytes in use before; RSS: sampled peak less the RSS before).", ""]
    for c in cases:
        lines += case_table(c) + [""]
    (out / "gradients.md").write_text("\n".join(lines) + "\n")


def load_average() -> float:
    try:
        with open("/proc/loadavg") as f:
            return float(f.read().split()[0])
    except OSError:
        return float("nan")


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--grad``)."""
    mi.set_variant(args.variant)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python -m mi_amr.bench " + " ".join(getattr(args, "argv", []) or ["--grad"])
    cases, load = [], []
    for spec in args.grad_data:
        name, n, levels = parse_data(spec)
        cells = make_dataset(name, cells=n, levels=levels)
        tf = mi_amr.TransferFunction.preset(args.grad_tf, cells.value_range)
        scale = SCALES.get((name, args.grad_tf), 100.0)
        load.append(load_average())
        print(f"{spec}: {len(cells):,} cells, dense {dense_shape(cells)[::-1]}, load {load[-1]:.2f}", flush=True)
        case = gradient_case(cells, tf, scale, res=args.grad_res, spp=args.grad_spp, steps=args.grad_steps,
                             repeats=args.repeats, integrators=args.grad_integrators, max_depth=args.max_depth,
                             memory=args.grad_memory, memory_limit=int(args.memory_limit * 2**30))
        case.update(dataset=f"{name} ({levels} levels)", spec=spec, tf=args.grad_tf)
        for label, why in case["skipped"].items():
            print(f"  skipped {label}: {why}", flush=True)
        cases.append(case)
        del cells
        gc.collect()
        (out / "gradients.json").write_text(json.dumps({"command": command, "cases": cases, "load": load},
                                                        indent=1, default=float))
    load.append(load_average())
    (out / "gradients.json").write_text(json.dumps({"command": command, "cases": cases, "load": load},
                                                    indent=1, default=float))
    write_tables(cases, out, command, load)
    print(f"wrote {out}/gradients.json and gradients.md")
    return 0
