"""The mi-amr benchmark: render time against error, in one process.

    python -m mi_amr.bench [--quick] --out DIR [FILE.cells ...]
    python -m mi_amr.bench --scale 1e5 1e6 1e7 1e8 --out DIR    (see mi_amr.bench.scale)
    python -m mi_amr.bench --view DATA --out DIR               (see mi_amr.bench.view)

For each data set (the synthetic ``cloud``, ``shell``, ``stadium`` and any
``.cells`` file given) x transfer function (``spiky``, ``foggy``) x
configuration (Mitsuba's ``heterogeneous`` + ``gridvolume`` reference on the
dense resampling, the ``amr`` medium in stock ``volpath`` with ``global``
and ``ray`` majorants, and ``amrvolpath`` with every traversal x sampling),
it measures build time, kernel compile time (the first frame), the median
frame time, RMSE against a high-sample reference image, efficiency
``1 / (MSE * seconds)``, density look-ups per real collision, structure
memory and the majorant recompute time of a TF change. Frame times are
taken pass by pass, alternating the configurations of a data set and TF
(A B C A B C ..., ``--repeats`` rounds), with one scene alive at a time
(`alternate_passes`).

The timing protocol (docs/performance/protocol.md): frames of real size
(256x256 by default), timed as replays of a ``dr.freeze``-recorded render
(what an interactive viewer runs; ``--no-frozen`` for plain frames), and in
the same rounds the *empty-medium frame* of the same scene (the default
medium at density scale 0: camera rays, the cube's surfaces, the emitters).
Each row reports its **share of the limit**, ``t_empty / t``: 1 would be a
medium that costs nothing, and no tracking can beat it. A medium that
scatters also pays per real collision; the *scattering floor*
(`scattering_floor`) is a frame that scatters as often as the default with
tracking that costs nothing, and each row's ``floor_share`` is ``t_floor /
t``. ``--peers eradiate`` adds rows of Eradiate's Mitsuba fork on the same
field (`mi_amr.bench.peers`). Reconstruction is
``nearest`` by default so that the dense reference renders exactly the same
field and every configuration converges to the same image.
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import time
from pathlib import Path
from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_amr
from ..autoscene import plan_scene
from ..data.blocks import BlockVolume
from ..data.datasets import make_dataset
from ..data.io import load_cells
from ..data.transform import apply_value_transform
from ..data.volume import as_method, as_volume
from ..device.grid import DeviceMacrocellGrid
from ..building import SAMPLINGS, TRAVERSALS
from ..structures.cost_model import REFINEMENTS, auto_grid
from ..structures.value_masks import ValueBins
from ..reference import dense_bytes, reference_medium, resample_dense
from ..transfer.device import DeviceTransferFunction
from .harness import FROZEN_WARMUP, bench_scene, check_alone, frame_function, wait_idle
from .peers import run_peers

SCALES = {("cloud", "spiky"): 60.0, ("cloud", "foggy"): 150.0,
          ("shell", "spiky"): 60.0, ("shell", "foggy"): 200.0,
          ("stadium", "spiky"): 300.0, ("stadium", "foggy"): 300.0,
          ("sparse", "spiky"): 60.0, ("sparse", "foggy"): 150.0}


#: amrvolpath/default with estimators turned off: name -> (residual ratio
#: tracking, decomposition tracking).
TRACKING_VARIANTS = {"no-rrt": (False, True), "no-dt": (True, False), "plain": (False, False)}


#: The limit's configuration: the empty-medium frame of a case (`config_scene`).
EMPTY = "empty"
#: The scattering floor's record (`scattering_floor`).
FLOOR = "scattering floor"


def limit_shares(times, empty_times) -> dict:
    """A row's share of the limit, ``t_empty / t``, from frames timed in the
    same rounds (`alternate_passes`): the median of the per-round ratios and
    their range (1 would be a medium that costs nothing)."""
    ratios = sorted(e / t for e, t in zip(empty_times, times))
    return {"limit_share": statistics.median(ratios), "limit_share_range": [ratios[0], ratios[-1]],
            "empty_seconds_per_frame": statistics.median(empty_times)}


def scattering_floor(mi, args, real_target: float, albedo) -> dict:
    """The *scattering floor* of a case: a frame whose tracking costs
    nothing beyond the physics, for a medium that scatters as often.

    The limit (`EMPTY`) has no scattering at all; a medium that scatters
    pays per real collision a next-event estimate, a phase sample and a new
    ray whatever its tracking. This frame renders one uniform cell (grey
    ``albedo``, the TF's alpha-weighted mean colour) with ``amrvolpath`` in
    the benchmark's view, its density scale searched (bisection in log
    scale, 1-spp frames) until its free flights make ``real_target`` real
    collisions per frame of ``args.spp``: its majorant is exact (no null
    collision) and its minorant equals it (decomposition tracking samples
    collisions without a look-up). Returns its frame time (median of
    ``args.repeats`` frames, timed like the others: frozen, after warm-up,
    process idle), the density scale and the real collisions reached."""
    one = mi_amr.dense_to_amr(np.ones((2, 2, 2), np.float32), 0.0, 1, source="scattering floor: one uniform cell")
    rgb = [float(np.clip(a, 0.0, 1.0)) for a in albedo]
    tf = mi_amr.TransferFunction([rgb + [1.0], rgb + [1.0]], (0.0, 2.0))
    scene = mi.load_dict(bench_scene({"type": "amr", "data": one, "transfer_function": tf, "density_scale": 1.0},
                                     args.res, {"type": "amrvolpath", "max_depth": args.max_depth,
                                                "counters": True}))
    integrator = scene.integrator()

    def real_per_frame(scale):
        mi_amr.set_transfer_function(scene, density_scale=scale)
        integrator.reset_counters()
        np.array(mi.render(scene, spp=1, seed=11))
        return integrator.counters()["real"] * args.spp

    lo, hi = -3.0, 5.0                                   # log10 of the density scale
    for _ in range(18):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if real_per_frame(10.0 ** mid) < real_target else (lo, mid)
    scale = 10.0 ** (0.5 * (lo + hi))
    reached = real_per_frame(scale)
    frame = frame_function(mi, args.spp, bool(getattr(args, "frozen", False)))
    for w in range(FROZEN_WARMUP):
        frame(scene, 60_000 + w)
    times = []
    for r in range(args.repeats):
        wait_idle()
        t0 = time.perf_counter()
        frame(scene, r)
        times.append(time.perf_counter() - t0)
    del scene, integrator
    return {"seconds_per_frame": statistics.median(times), "frame_seconds": times, "density_scale": scale,
            "real_target": real_target, "real_reached": reached, "albedo": rgb}


def all_configs():
    """Configuration names: ``amrvolpath/default`` is what a user gets with
    no structure options (its record names what it resolved to)."""
    out = ["reference", "dense16", "volpath/global", "volpath/ray", "amrvolpath/default"]
    out += [f"amrvolpath/default-{v}" for v in TRACKING_VARIANTS]
    out += [f"amrvolpath/{t}/{s}" for t in TRAVERSALS for s in SAMPLINGS]
    return out


_DENSE = {}


def dense_volume(cells, args):
    """The reference's resampled field (finest resolution, ``nearest``) as a
    one-level `BlockVolume` of 16^3 blocks, made once per data set."""
    method = as_method(args.reconstruction)
    if not method.dense_exact:          # a dense resampling is that field exactly
        raise ValueError("dense16 resamples the nearest field: run it with --reconstruction nearest")
    key = id(cells)
    if key not in _DENSE:
        value, found = resample_dense(cells, method, memory_limit=int(args.memory_limit * 2**30))
        _DENSE.clear()                                      # one data set at a time
        _DENSE[key] = BlockVolume.from_dense(np.where(found, value, np.nan), 16, f"{cells.source} (dense)")
    return _DENSE[key]


def config_scene(mi, config, cells, tf, scale, args, grid_resolution=None, grid_refinement=1) -> dict:
    """The benchmark scene of one configuration, as a dict (loadable again:
    its data are shared, and host structures are cached on them)."""
    kind = config.split("/")
    integ = {"type": "volpath", "max_depth": args.max_depth}
    if kind[0] == "reference":
        medium = reference_medium(cells, tf, scale, args.reconstruction,
                                  memory_limit=int(args.memory_limit * 2**30))
    elif kind[0] == EMPTY:
        # the limit: the default medium with density scale 0, so that every
        # path crosses the cube without a collision (camera rays, the cube's
        # two surfaces, the emitters: what any medium's frame costs)
        medium = {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 0.0,
                  "reconstruction": args.reconstruction}
        integ = {"type": "amrvolpath", "max_depth": args.max_depth}
    elif kind[0] == "dense16":
        # the dense-grid renderer: the reference's resampled field as one level,
        # a fixed 16^3 majorant grid walked by DDA (pbrt-v4's choice)
        medium = {"type": "amr", "data": dense_volume(cells, args), "transfer_function": tf,
                  "density_scale": scale, "reconstruction": "nearest", "grid_resolution": 16,
                  "value_masks": not args.no_value_masks}
        integ = {"type": "amrvolpath", "max_depth": args.max_depth, "counters": True}
    else:
        medium = {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": scale,
                  "reconstruction": args.reconstruction, "value_masks": not args.no_value_masks}
        if grid_resolution is not None:
            medium["grid_resolution"] = int(grid_resolution)
            medium["grid_refinement"] = int(grid_refinement)
        elif args.grid_refinement is not None:
            medium["grid_refinement"] = args.grid_refinement
        if kind[0] == "volpath":
            medium["majorant"] = kind[1]
        else:
            integ = {"type": "amrvolpath", "max_depth": args.max_depth, "counters": True}
            if kind[1].startswith("default-"):
                rrt, dt = TRACKING_VARIANTS[kind[1][len("default-"):]]
                integ.update(residual_ratio_tracking=rrt, decomposition_tracking=dt)
            elif kind[1] != "default":
                medium.update(traversal=kind[1], sampling=kind[2])
    return bench_scene(medium, args.res, integ)


def run_config(mi, config, cells, tf, scale, args, ref_image=None, grid_resolution=None, grid_refinement=1,
               timed=True, scene_dict=None):
    """Measure one configuration; returns (record, image). ``timed``: also
    time ``args.repeats`` frames in a row (else the caller times them, see
    `alternate_passes`, and one frame feeds the counters). ``scene_dict``:
    the configuration's scene, when the caller made it already."""
    check_alone(config)
    kind = config.split("/")
    t0 = time.perf_counter()
    if scene_dict is None:
        scene_dict = config_scene(mi, config, cells, tf, scale, args, grid_resolution, grid_refinement)
    scene = mi.load_dict(scene_dict)
    build_s = time.perf_counter() - t0
    integrator = scene.integrator()
    t0 = time.perf_counter()
    np.array(mi.render(scene, spp=1, seed=99_999))
    compile_s = time.perf_counter() - t0
    times, mses, img = [], [], None
    acc = None
    if hasattr(integrator, "reset_counters"):
        integrator.reset_counters()
    wait_idle()
    for r in range(args.repeats if timed else 1):
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, spp=args.spp, seed=r), dtype=np.float64)
        times.append(time.perf_counter() - t0)
        acc = img if acc is None else acc + img
        if ref_image is not None:
            mses.append(float(np.mean((img - ref_image) ** 2)))
    seconds = statistics.median(times)
    curve = []
    if ref_image is not None:
        for n in args.curve_spp:
            t0 = time.perf_counter()
            im = np.array(mi.render(scene, spp=n, seed=777 + n), dtype=np.float64)
            curve.append([n, time.perf_counter() - t0, float(np.sqrt(np.mean((im - ref_image) ** 2)))])
    rec = {"config": config, "build_s": build_s, "compile_s": compile_s, "curve": curve,
           "seconds_per_frame": seconds, "spp": args.spp,
           "seconds_per_spp": seconds / args.spp, "mean": float(img.mean())}
    if ref_image is not None:
        apply_timing(rec, times, mses)
    if hasattr(integrator, "counters"):
        c = integrator.counters()
        rec["lookups_per_collision"] = c["lookups_per_collision"]
        rec["null_per_collision"] = c["null_per_collision"]
        rec["lookups_per_shadow_ray"] = c["lookups_per_shadow_ray"]
        rec["counters"] = c
    else:
        rec["lookups_per_collision"] = None
        rec["null_per_collision"] = None
        rec["lookups_per_shadow_ray"] = None
    if kind[0] == "reference":
        rec["structure_bytes"] = dense_bytes(cells)
        rec["majorant_update_s"] = None
    else:
        med = [s for s in scene.shapes() if s.interior_medium() is not None][0].interior_medium()
        rec["structure_bytes"] = med.resident_bytes      # data + structures, as the dense reference
        dr.eval()
        t0 = time.perf_counter()
        for _ in range(5):
            med.update_majorants()
            dr.eval(med.structures.global_majorant)
            dr.sync_thread()
        rec["majorant_update_s"] = (time.perf_counter() - t0) / 5
        rec["build_detail_s"] = dict(med.build_seconds)
        grid = med.structures.device.get("grid")
        rec["resolved"] = f"{med.options.structures.traversal}/{med.options.structures.sampling}" + \
            (f", {grid.describe()}" if grid is not None else "")
    return rec, acc / len(times)


def alternate_passes(mi, scenes: dict, args, ref_image) -> dict:
    """Time configurations pass by pass (A B C A B C ...), ``args.repeats``
    rounds: each pass loads its configuration's scene, renders one untimed
    frame of ``args.spp`` (kernels, caches, buffers of the full size; with
    ``args.frozen`` the `FROZEN_WARMUP` frames of a frozen render), waits
    until the process is idle (`wait_idle`), times one more and
    frees the scene before the next is loaded, so exactly one scene is
    alive while timing and slow drifts of the machine hit every
    configuration alike. Returns ``{config: (seconds per frame, MSE per
    frame)}``."""
    frozen = bool(getattr(args, "frozen", False))
    out = {c: ([], []) for c in scenes}
    for r in range(args.repeats):
        for config, scene_dict in scenes.items():
            check_alone(config)
            scene = mi.load_dict(scene_dict)
            frame = frame_function(mi, args.spp, frozen)
            for w in range(FROZEN_WARMUP if frozen else 1):
                frame(scene, 50_000 + 10 * r + w)
            wait_idle()
            t0 = time.perf_counter()
            img = frame(scene, r)
            out[config][0].append(time.perf_counter() - t0)
            out[config][1].append(float(np.mean((img - ref_image) ** 2)))
            del scene, img
            gc.collect()
    return out


def apply_timing(rec, times, mses):
    """Fill a record's frame time and efficiency from timed frames: the
    median frame time, and the MSE over the frames (a steadier estimate)."""
    seconds, mse = statistics.median(times), float(sum(mses) / len(mses))
    rec.update(seconds_per_frame=seconds, seconds_per_spp=seconds / rec["spp"], rmse=mse ** 0.5,
               efficiency=1.0 / (mse * seconds) if mse > 0 else float("inf"),
               frame_seconds=list(times))


#: ``--quick``: small sizes, minutes on 2 cores.
QUICK = dict(cells=4000, res=48, spp=4, ref_spp=128, repeats=3, sparse_res=32, curve_spp=[1, 2, 4],
             sweep=[8, 16, 32, 64])


def main_args(args) -> int:
    """The protocol (``python -m mi_amr.bench [--quick] --out DIR``): every
    data set x TF case, then the TF-change timing, the tables and curves."""
    if args.quick:
        vars(args).update(QUICK)
    mi.set_variant(args.variant)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data, domains = load_data(args)
    records, sweeps = [], []
    t_start = time.perf_counter()
    for name, cells in data:
        for tf_name in args.tfs:
            run_case(mi, args, name, tf_name, cells, domains, out, records, sweeps)
            (out / "results.json").write_text(json.dumps(records, indent=1, default=float))
            (out / "sweep.json").write_text(json.dumps(sweeps, indent=1, default=float))
    tf_timing = tf_change_timing(mi, args, data[0][1] if data else None)
    (out / "tf_change.json").write_text(json.dumps(tf_timing, indent=1, default=float))
    write_tables(records, sweeps, out, tf_timing)
    plot_curves(records, out)
    plot_sweeps(sweeps, out)
    print(f"wrote {out}/results.json, sweep.json, tables.md and the PNG curves "
          f"({time.perf_counter() - t_start:.0f} s)")
    return 0


def load_data(args):
    """``([(name, cells)], {name: TF domain})``: the synthetic data sets (or
    ``--data`` alone, on the value scale `mi-amr render` chooses, its density
    scale entered in `SCALES`), then the extra ``.cells`` files."""
    domains = {}                                  # TF domain per data set (default: the value range)
    if args.data:
        # a user's data set alone (any format `mi-amr render` reads), on its value scale
        plan = plan_scene(args.data, args.field)
        cells = plan.data.to_cells() if hasattr(plan.data, "to_cells") else plan.data
        if plan.transform == "log10":
            cells, _ = apply_value_transform(cells, "log10")
        name = Path(args.data).name + (f"-{args.field}" if args.field else "")
        data = [(name, cells)]
        SCALES.update({(name, t): plan.density_scale for t in args.tfs})
        domains[name] = plan.tf_range
        print(f"{name}: {len(cells)} cells, {plan.transform} values, density_scale {plan.density_scale:.3g} "
              f"(as mi-amr render would choose)", flush=True)
    else:
        data = [(n, make_dataset(n, cells=args.sparse_res ** 3 if n == "sparse" else args.cells,
                                 levels=7 if n == "stadium" else 4)) for n in args.datasets]
    data += [(Path(f).stem, load_cells(f)) for f in args.files]
    return data, domains


def run_case(mi, args, name, tf_name, cells, domains, out, records, sweeps):
    """One data set x TF case: its reference image, every configuration
    measured, frame times in alternating passes, the limit and the floor;
    its records go to ``records`` (printed), its grid sweep to ``sweeps``."""
    tf = mi_amr.TransferFunction.preset(tf_name, domains.get(name, cells.value_range))
    scale = SCALES.get((name, tf_name), 100.0)
    # High-sample reference image: the default amrvolpath configuration.
    ref_args = argparse.Namespace(**{**vars(args), "spp": args.ref_spp, "repeats": 1})
    _, ref_img = run_config(mi, "amrvolpath/grid/hash", cells, tf, scale, ref_args)
    measured, scenes = measure_configs(mi, args, name, tf_name, cells, tf, scale, ref_img)
    if args.limit and scenes:
        scenes[EMPTY] = config_scene(mi, EMPTY, cells, tf, scale, args)
    # the frame times, alternating configurations pass by pass
    timing = alternate_passes(mi, scenes, args, ref_img)
    del scenes
    ref_rec = None
    for rec in measured:
        if "skipped" not in rec:
            apply_timing(rec, *timing[rec["config"]])
            ref_rec = rec if rec["config"] == "reference" else ref_rec
    if EMPTY in timing:
        measured += limit_rows(mi, args, name, tf_name, cells, tf, measured, timing[EMPTY][0])
    for rec in measured:
        records.append(rec)
        if "skipped" not in rec:
            print_row(rec, ref_rec)
    records += run_peers(args.peers, name, tf_name, cells, tf, scale, args, ref_img, measured, out)
    if args.sweep:
        sweeps.append(grid_sweep(mi, name, tf_name, cells, tf, scale, args, ref_img))


def measure_configs(mi, args, name, tf_name, cells, tf, scale, ref_img):
    """``(records, scenes)``: everything but the frame times, configuration
    by configuration, and the scene of each (a dense reference that does not
    fit is a skipped record and no scene)."""
    measured, scenes = [], {}
    for config in args.configs or all_configs():
        try:
            scenes[config] = config_scene(mi, config, cells, tf, scale, args)
            rec, _ = run_config(mi, config, cells, tf, scale, args, ref_img, timed=False,
                                scene_dict=scenes[config])
        except MemoryError as e:          # the dense reference does not fit
            print(f"{name:8s} {tf_name:6s} {config:24s} skipped: {e}", flush=True)
            scenes.pop(config, None)
            measured.append({"dataset": name, "tf": tf_name, "config": config, "cells": len(cells),
                             "skipped": str(e)})
            continue
        rec.update(dataset=name, tf=tf_name, cells=len(cells), density_scale=scale, frozen=args.frozen)
        measured.append(rec)
    return measured, scenes


def limit_rows(mi, args, name, tf_name, cells, tf, measured, empty_times) -> list:
    """The limit's row (the empty-medium frame) and, where the default
    scatters, the scattering floor's; each measured row gets its shares."""
    for rec in measured:
        if "skipped" not in rec:
            rec.update(limit_shares(rec["frame_seconds"], empty_times))
    rows = [{"dataset": name, "tf": tf_name, "config": EMPTY, "cells": len(cells),
             "density_scale": 0.0, "frozen": args.frozen, "spp": args.spp,
             "seconds_per_frame": statistics.median(empty_times),
             "seconds_per_spp": statistics.median(empty_times) / args.spp,
             "frame_seconds": list(empty_times), **limit_shares(empty_times, empty_times)}]
    default = next((r for r in measured if r["config"] == "amrvolpath/default" and "counters" in r), None)
    if default is not None and default["counters"]["real"] > 0:
        weights = tf.rgba[:, 3] + 1e-6                   # the TF's mean colour where it is opaque
        floor = scattering_floor(mi, args, default["counters"]["real"],
                                 (tf.rgba[:, :3] * weights[:, None]).sum(0) / weights.sum())
        for rec in measured + rows:
            if "skipped" not in rec:
                rec["floor_share"] = floor["seconds_per_frame"] / rec["seconds_per_frame"]
        rows.append({"dataset": name, "tf": tf_name, "config": FLOOR, "cells": 1, "spp": args.spp,
                     "frozen": args.frozen, "seconds_per_spp": floor["seconds_per_frame"] / args.spp,
                     "limit_share": statistics.median(empty_times) / floor["seconds_per_frame"],
                     "floor_share": 1.0, **floor})
    return rows


def print_row(rec, ref_rec):
    """Print one measured row (and set its efficiency against the reference)."""
    name, tf_name, config = rec["dataset"], rec["tf"], rec["config"]
    if config in (EMPTY, FLOOR):
        print(f"{name:8s} {tf_name:6s} {config:24s} {rec['seconds_per_spp'] * 1e3:8.2f} ms/spp", flush=True)
        return
    rec["efficiency_vs_reference"] = (rec["efficiency"] / ref_rec["efficiency"]
                                      if ref_rec and ref_rec.get("efficiency") else None)
    lpc = rec["lookups_per_collision"]
    share = f" limit {rec['limit_share']:.2f}" if "limit_share" in rec else ""
    print(f"{name:8s} {tf_name:6s} {config:24s} {rec['seconds_per_spp'] * 1e3:8.2f} ms/spp{share} "
          f"rmse {rec['rmse']:.4f} eff x{rec['efficiency_vs_reference'] or float('nan'):6.2f} "
          f"lookups/coll {lpc if lpc is not None else float('nan'):6.2f} "
          f"build {rec['build_s']:6.2f}s", flush=True)


#: The leaf counts whose majorant recompute `tf_change_timing` times.
RECOMPUTE_LEAVES = (10**5, 10**6, 10**7)


def tf_change_timing(mi, args, cells):
    """Majorant recompute time for `RECOMPUTE_LEAVES` (10^5, 10^6 and 10^7)
    leaves (one Dr.Jit kernel over the leaves' value ranges), and the first
    frame after a TF change against the steady-state frame time."""
    rng = np.random.default_rng(0)
    tf = DeviceTransferFunction(mi_amr.TransferFunction.preset("spiky", (0.0, 1.0)))
    scale = mi.Float(50.0)
    dr.make_opaque(scale)
    out = {"recompute": []}
    for n in RECOMPUTE_LEAVES:
        a = rng.random(n, dtype=np.float32)
        b = a + rng.random(n, dtype=np.float32) * 0.2
        vmin, vmax = mi.Float(a), mi.Float(b)
        dr.eval(vmin, vmax)
        # the same ranges as a macrocell grid with value masks (nearest)
        bins = ValueBins(0.0, 1.2)
        grid = DeviceMacrocellGrid(SimpleNamespace(res=np.array([n, 1, 1]), vmin=a, vmax=b,
                                                   level_bits=np.ones(n, np.uint32), masks=bins.bits(a, b),
                                                   bins=bins))
        row = {"leaves": n}
        for key, run in (("ms", lambda: scale * tf.range_max_alpha(vmin, vmax)),
                         ("ms_masked", lambda: (grid.update_majorants(tf, scale), grid.majorant)[1])):
            times = []
            for i in range(6):
                t0 = time.perf_counter()
                dr.eval(run())
                dr.sync_thread()
                times.append(time.perf_counter() - t0)
            row[key] = 1e3 * statistics.median(times[1:])          # the first includes compilation
        row["ms_per_million"] = row["ms"] / (n / 1e6)
        row["ms_masked_per_million"] = row["ms_masked"] / (n / 1e6)
        out["recompute"].append(row)
        print(f"majorant recompute: {n:>9d} leaves {row['ms']:8.2f} ms ({row['ms_per_million']:.2f} ms per 10^6); "
              f"with value masks {row['ms_masked']:8.2f} ms ({row['ms_masked_per_million']:.2f} ms per 10^6)",
              flush=True)
    if cells is not None:
        scene = mi.load_dict(bench_scene({"type": "amr", "data": cells, "transfer_function": "foggy",
                                          "density_scale": 150.0}, args.res,
                                         {"type": "amrvolpath", "max_depth": args.max_depth}))
        np.array(mi.render(scene, spp=args.spp, seed=0))        # compile
        new_tf = mi_amr.TransferFunction.from_colormap("magma", [(0, 0), (0.4, 0.2), (1, 0.1)],
                                                       cells.value_range, n=128)
        t0 = time.perf_counter()
        mi_amr.set_transfer_function(scene, new_tf, density_scale=120.0)
        update_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        np.array(mi.render(scene, spp=args.spp, seed=7))
        first = time.perf_counter() - t0
        steady = []                                    # the same TF, frames after the first
        for r in range(3):
            t0 = time.perf_counter()
            np.array(mi.render(scene, spp=args.spp, seed=r))
            steady.append(time.perf_counter() - t0)
        out["frame"] = {"steady_s": statistics.median(steady), "first_after_change_s": first,
                        "ratio": first / statistics.median(steady), "set_transfer_function_s": update_s}
        print(f"first frame after a TF change: {first:.3f} s vs steady {statistics.median(steady):.3f} s "
              f"({out['frame']['ratio']:.2f}x); set_transfer_function {1e3 * update_s:.1f} ms", flush=True)
        # a slider move: another TF of the same table size
        moved_tf = mi_amr.TransferFunction.from_colormap("viridis", [(0, 0.1), (0.6, 0.5), (1, 0)],
                                                         cells.value_range, n=128)
        out["frozen"] = frozen_frame_timing(
            mi, scene, args.spp, change=lambda: mi_amr.set_transfer_function(scene, moved_tf, density_scale=150.0))
    return out


def frozen_frame_timing(mi, scene, spp: int, rounds: int = 5, change=None):
    """Frame time of a ``dr.freeze``-recorded render against a plain one on
    the same scene, alternating the two; medians and the per-round ratios.
    ``change()``, when given, then changes the TF: the first frozen frame
    after it against the frozen frames that follow it (the same TF), and
    whether the change made a new recording."""
    plain, frozen = frame_function(mi, spp, False), frame_function(mi, spp, True)
    for seed in (100, 101):                          # record, and the state Mitsuba adds after a frame
        frozen(scene, seed)
    plain_s, frozen_s = [], []
    for r in range(rounds):
        for frame, times in ((plain, plain_s), (frozen, frozen_s)):
            t0 = time.perf_counter()
            frame(scene, r)
            times.append(time.perf_counter() - t0)
    ratios = sorted(p / f for p, f in zip(plain_s, frozen_s))
    res = {"plain_s": statistics.median(plain_s), "frozen_s": statistics.median(frozen_s),
           "speedup_median": statistics.median(ratios), "speedup_range": [ratios[0], ratios[-1]],
           "recordings": frozen.recorder.n_recordings}
    print(f"frozen frame {res['frozen_s']:.3f} s vs plain {res['plain_s']:.3f} s: "
          f"{res['speedup_median']:.2f}x (range {ratios[0]:.2f}-{ratios[-1]:.2f}, "
          f"{res['recordings']} recordings)", flush=True)
    if change is not None:
        change()
        after = []
        for r in range(4):
            t0 = time.perf_counter()
            frozen(scene, rounds + r)
            after.append(time.perf_counter() - t0)
        res.update(first_after_change_s=after[0], steady_after_change_s=statistics.median(after[1:]),
                   recorded_on_change=frozen.recorder.n_recordings - res["recordings"])
        res["first_ratio"] = after[0] / res["steady_after_change_s"]
        print(f"first frozen frame after a TF change: {after[0]:.3f} s ({res['first_ratio']:.2f}x the "
              f"frozen frames after it; {res['recorded_on_change']} new recordings)", flush=True)
    return res


def grid_sweep(mi, name, tf_name, cells, tf, scale, args, ref_img):
    """Efficiency of amrvolpath/grid/hash over uniform grid resolutions, and
    of the grid `auto_grid` picks (uniform or two-level; Fig. 8 of the paper)."""
    rows = []
    for r in args.sweep:
        rec, _ = run_config(mi, "amrvolpath/grid/hash", cells, tf, scale, args, ref_img, grid_resolution=r)
        rows.append({"grid_resolution": r, "efficiency": rec["efficiency"],
                     "seconds_per_spp": rec["seconds_per_spp"],
                     "lookups_per_collision": rec["lookups_per_collision"]})
    refinements = (1,) + REFINEMENTS if args.grid_refinement is None else (args.grid_refinement,)
    method = as_method(args.reconstruction)
    plan, costs = auto_grid(as_volume(cells, method), tf, scale, support=method, refinements=refinements,
                            masks=method.value_masks_tighten and not args.no_value_masks)
    auto = str(plan.resolution) if plan.refinement == 1 else f"{plan.resolution}/{plan.refinement} two-level"
    rec, _ = run_config(mi, "amrvolpath/grid/hash", cells, tf, scale, args, ref_img,
                        grid_resolution=plan.resolution, grid_refinement=plan.refinement)
    best = max(rows, key=lambda x: x["efficiency"])
    out = {"dataset": name, "tf": tf_name, "rows": rows, "auto_resolution": plan.resolution,
           "auto_refinement": plan.refinement, "auto_plan": auto,
           "auto_efficiency": rec["efficiency"], "best_resolution": best["grid_resolution"],
           "best_efficiency": best["efficiency"], "auto_vs_best": rec["efficiency"] / best["efficiency"],
           "model_costs": {f"{p.resolution}/{p.refinement}": c for p, c in costs.items()}}
    print(f"{name:8s} {tf_name:6s} grid sweep: best uniform R={best['grid_resolution']}, auto {auto} "
          f"reaches {out['auto_vs_best']:.0%} of its efficiency", flush=True)
    return out


#: Plot style: one colour per traversal (stock volpath and the reference
#: apart), one line style per sampling; the reference and the default heaviest.
#: Line styles of the default's rows with estimators off (`TRACKING_VARIANTS`).
VARIANT_STYLES = {"no-rrt": (0, (1, 1)), "no-dt": (0, (3, 1, 1, 1, 1, 1)), "plain": (0, (6, 2))}
TRAVERSAL_COLOURS = {"grid": "tab:blue", "abr": "tab:orange", "brick": "tab:green", "kdtree": "tab:red",
                     "volpath/ray": "tab:purple", "volpath/global": "tab:brown", "reference": "black",
                     "dense16": "tab:gray"}
SAMPLING_STYLES = {"hash": "-", "abr": "--", "brick": ":"}


def curve_style(record) -> dict:
    """Matplotlib style of a configuration's curve (see `TRAVERSAL_COLOURS`)."""
    config = record["config"]
    if config in ("reference", "dense16") or config.startswith("volpath/"):
        return {"color": TRAVERSAL_COLOURS[config], "ls": "-." if config != "reference" else "-",
                "lw": 3.0 if config == "reference" else 1.3, "label": config}
    if config.split("/")[1].startswith("default"):            # drawn as what it resolved to
        traversal, sampling = record.get("resolved", "grid/hash").split(",")[0].split("/")
        variant = config.split("/")[1][len("default-"):]
        return {"color": _colour(traversal), "ls": VARIANT_STYLES.get(variant, _line(sampling)),
                "lw": 1.6 if variant else 3.0, "label": f"{config} (= {traversal}/{sampling})"}
    _, traversal, sampling = config.split("/")
    return {"color": _colour(traversal), "ls": _line(sampling), "lw": 1.3, "label": config}


def _colour(traversal: str) -> str:
    """A traversal's colour (one registered after these were chosen: olive)."""
    return TRAVERSAL_COLOURS.get(traversal, "tab:olive")


def _line(sampling: str):
    """A sampling's line style (one registered after these were chosen: dash-dot)."""
    return SAMPLING_STYLES.get(sampling, "-.")


def plot_curves(records, out: Path):
    """RMSE against render seconds, log-log, one PNG per data set x TF
    (styles from `curve_style`; sized for a README column)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    for key in dict.fromkeys((r["dataset"], r["tf"]) for r in records):
        rows = [r for r in records if (r["dataset"], r["tf"]) == key and r.get("curve")]
        if not rows:
            continue
        fig, ax = plt.subplots(figsize=(7.5, 4.6))
        for r in sorted(rows, key=lambda r: curve_style(r)["lw"]):     # heavy lines on top
            c = [p for p in r["curve"] if p[2] > 0]
            st = curve_style(r)
            ax.loglog([p[1] for p in c], [p[2] for p in c], marker="o", ms=2.5, **st)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())   # no crowded minor labels
        ax.set_xlabel("render time [s]")
        ax.set_ylabel("RMSE vs high-spp image")
        ax.set_title(f"{key[0]} / {key[1]}: error against time (lower left is better)", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        order = sorted(range(len(labels)), key=lambda i: labels[i])
        ax.legend([handles[i] for i in order], [labels[i] for i in order], fontsize=7,
                  loc="center left", bbox_to_anchor=(1.01, 0.5), title="colour: traversal\nline: sampling",
                  title_fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"curves_{key[0]}_{key[1]}.png", dpi=100)
        plt.close(fig)


def plot_sweeps(sweeps, out: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    if not sweeps:
        return
    fig, ax = plt.subplots(figsize=(7, 5))
    for sw in sweeps:
        r = [x["grid_resolution"] for x in sw["rows"]]
        e = [x["efficiency"] / sw["best_efficiency"] for x in sw["rows"]]
        line, = ax.semilogx(r, e, marker="o", label=f"{sw['dataset']}/{sw['tf']}")
        two_level = sw.get("auto_refinement", 1) > 1
        ax.plot([sw["auto_resolution"]], [sw["auto_vs_best"]], marker="P" if two_level else "*", ms=14,
                color=line.get_color())
    ax.set_xlabel("grid resolution (macrocells along the longest axis; fine level of a two-level grid)")
    ax.set_ylabel("efficiency / best uniform grid\n(star: automatic uniform choice, plus: two-level)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "grid_sweep.png", dpi=110)
    plt.close(fig)


def peer_summary(records) -> list[str]:
    """Markdown lines: per case, ``amrvolpath/default`` against the best
    grid of a peer (its most efficient row other than its own
    ``heterogeneous``), both ways: absolute (efficiency over efficiency) and
    normalised by each side's own ``heterogeneous`` medium (ours: the
    ``reference`` row; the peer's: its ``heterogeneous`` row)."""
    peers = [r for r in records if r.get("peer") and "skipped" not in r]
    if not peers:
        return []
    lines = ["## Against a peer: Eradiate's `extremum_grid` + `eovolpath`", "",
             "Best peer grid = its most efficient `extremum_grid` row. Absolute: efficiency of "
             "`amrvolpath/default` over the peer's; normalised: each over its own `heterogeneous` medium "
             "(ours timed in this process, the peer's in its own), then the ratio.", "",
             "| data / TF | best peer grid | peer eff. vs its heterogeneous | default eff. vs ours | "
             "default / peer, absolute | default / peer, normalised |", "|---|---|---|---|---|---|"]
    for key in dict.fromkeys((r["dataset"], r["tf"]) for r in peers):
        rows = [r for r in peers if (r["dataset"], r["tf"]) == key and r["peer_config"] != "heterogeneous"]
        ours = next((r for r in records if (r["dataset"], r["tf"]) == key and r["config"] == "amrvolpath/default"
                     and "skipped" not in r), None)
        if not rows or ours is None:
            continue
        best = max(rows, key=lambda r: r["efficiency"])
        own, mine = best.get("efficiency_vs_own_heterogeneous"), ours.get("efficiency_vs_reference")
        norm = f"{mine / own:.2f}x" if own and mine else ""
        lines.append(f"| {key[0]} / {key[1]} | {best['config'].split('/', 1)[1]} | "
                     f"{own:.2f}x | {mine:.2f}x | **{ours['efficiency'] / best['efficiency']:.2f}x** | "
                     f"**{norm}** |" if own and mine else
                     f"| {key[0]} / {key[1]} | {best['config']} | | | "
                     f"{ours['efficiency'] / best['efficiency']:.2f}x | |")
    return lines + [""]


def write_tables(records, sweeps, out: Path, tf_timing=None):
    """One Markdown table per data set, laid out like the paper's Table 2,
    and the grid-resolution sweep."""
    lines = ["# mi-amr benchmark", ""]
    if any(r.get("frozen") for r in records):
        lines += ["Frames timed as `dr.freeze` replays (the default; `--no-frozen` times plain frames): "
                  "no per-frame trace.", ""]
    if any("limit_share" in r for r in records):
        lines += ["Limit: t_empty / t, the empty-medium frame of the same scene (density scale 0) over "
                  "the row's frame, timed in the same rounds; 1 would be a medium that costs nothing.", ""]
    if any(r["config"] == FLOOR for r in records):
        lines += ["Scattering floor: a uniform medium with as many real collisions per frame as "
                  "`amrvolpath/default`, tracked without look-ups (`scattering_floor`); its row's limit "
                  "column is t_empty / t_floor, the best share any tracking could reach here.", ""]
    for name in dict.fromkeys(r["dataset"] for r in records):
        skipped = [r for r in records if r["dataset"] == name and r.get("skipped")]
        rows = [r for r in records if r["dataset"] == name and not r.get("skipped")]
        tfs = list(dict.fromkeys(r["tf"] for r in rows))
        lines += [f"## {name} ({rows[0]['cells']} cells)", "",
                  "| configuration | " + " | ".join(f"{t}: ms/spp | {t}: limit | {t}: eff. vs ref | "
                                                     f"{t}: look-ups/coll. | "
                                                     f"{t}: null/coll. | {t}: look-ups/shadow ray"
                                                     for t in tfs) + " | memory MiB |",
                  "|---|" + "---|---|---|---|---|---|" * len(tfs) + "---|"]
        for config in dict.fromkeys(r["config"] for r in rows):
            cells = []
            mem = None
            for t in tfs:
                r = next((x for x in rows if x["config"] == config and x["tf"] == t), None)
                if r is None:
                    cells += ["", "", "", "", "", ""]
                    continue
                share = r.get("limit_share")
                share = "" if share is None else f"{share:.2f}"
                if config in (EMPTY, FLOOR):
                    cells += [f"{r['seconds_per_spp'] * 1e3:.2f}", share, "", "", "", ""]
                    continue
                mem = r["structure_bytes"] / 2**20
                eff = r.get("efficiency_vs_reference")
                lpc = r.get("lookups_per_collision")
                npc = r.get("null_per_collision")
                lps = r.get("lookups_per_shadow_ray")
                cells += [f"{r['seconds_per_spp'] * 1e3:.2f}", share, f"{eff:.2f}x" if eff else "",
                          f"{lpc:.2f}" if lpc else "", f"{npc:.2f}" if npc is not None else "",
                          f"{lps:.2f}" if lps is not None and lps == lps else ""]
            resolved = next((x.get("resolved") for x in rows if x["config"] == config and x.get("resolved")), None)
            name = f"{config} ({resolved})" if config.endswith("/default") and resolved else config
            name = {EMPTY: "empty medium (the limit)", FLOOR: "scattering floor"}.get(config, name)
            lines.append(f"| {name} | " + " | ".join(cells) + (f" | {mem:.2f} |" if mem is not None else " | |"))
        for r in skipped:
            lines.append(f"\n{r['config']} ({r['tf']}) skipped: {r['skipped']}")
        lines.append("")
    lines += peer_summary(records)
    if sweeps:
        lines += ["## Grid resolution sweep (amrvolpath/grid/hash)", "",
                  "| data set | TF | best uniform R | best efficiency | auto grid | auto / best |",
                  "|---|---|---|---|---|---|"]
        for sw in sweeps:
            lines.append(f"| {sw['dataset']} | {sw['tf']} | {sw['best_resolution']} | {sw['best_efficiency']:.4g} | "
                         f"{sw.get('auto_plan', sw['auto_resolution'])} | {sw['auto_vs_best']:.0%} |")
        lines.append("")
    if tf_timing:
        lines += ["## Transfer-function change", "",
                  "| leaves | majorant recompute ms | ms per 10^6 leaves | with value masks ms | ms per 10^6 |",
                  "|---|---|---|---|---|"]
        for r in tf_timing["recompute"]:
            masked = (f"{r['ms_masked']:.2f} | {r['ms_masked_per_million']:.2f}" if "ms_masked" in r else " | ")
            lines.append(f"| {r['leaves']} | {r['ms']:.2f} | {r['ms_per_million']:.2f} | {masked} |")
        if "frame" in tf_timing:
            f = tf_timing["frame"]
            lines += ["", f"First frame after a TF change: {f['first_after_change_s']:.3f} s, steady state "
                          f"{f['steady_s']:.3f} s ({f['ratio']:.2f}x); set_transfer_function "
                          f"{1e3 * f['set_transfer_function_s']:.1f} ms."]
        z = tf_timing.get("frozen", {})
        if "first_after_change_s" in z:
            lines += ["", f"Frozen frames (`dr.freeze`): {z['frozen_s']:.3f} s against {z['plain_s']:.3f} s plain "
                          f"({z['speedup_median']:.2f}x); the first after a TF change "
                          f"{z['first_after_change_s']:.3f} s ({z['first_ratio']:.2f}x), "
                          f"{z['recorded_on_change']} new recordings."]
        lines.append("")
    (out / "tables.md").write_text("\n".join(lines))
