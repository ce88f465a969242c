"""What each lighting mode costs, and a collision against the homogeneous
floor (docs/performance/modes.md): ``python -m mi_amr.bench --modes --out DIR``.

Two tables (docs/performance/modes.md):

* **Frames/s per mode.** For each case (the protocol's synthetic data x TF,
  then the large data sets of ``--modes-cells``: octree-like ``cloud`` up to
  10^7 cells, block-structured ``blocks`` above, generated once into
  ``--data-dir`` as the scale benchmark does), ``amrvolpath`` in each mode
  (``emission_absorption``, ``single``, ``multi``: docs/design.md section
  6d) beside the *empty-medium frame* of the same scene (the protocol's
  limit: density scale 0, so camera rays, the cube's surfaces and the
  emitters only), ``--res`` x ``--res`` at 1 spp unless ``--spp`` is given.
  Each mode's share of the limit is ``t_empty / t`` (median of per-round
  ratios); its *cost per real collision* is ``(t - t_empty)`` over the real
  collisions of a frame (counted once, untimed).
* **The floor: a uniform field against Mitsuba's homogeneous medium.** A
  field of one level and one value is the cheapest AMR there is; per mode it
  is timed in ``amrvolpath`` beside Mitsuba's ``homogeneous`` medium with the
  same extinction and albedo (128x128, 16 spp, sigma_t 8, albedo 0.9;
  ``multi`` also in Mitsuba's own C++ ``volpath``), with each frame's
  per-pixel variance: ``efficiency = 1 / (time x variance)`` is the judge,
  and ``t / t_homogeneous`` the cost ratio. Its cost per real collision is
  the floor every mode's cost above stands against.

Frames are timed as the protocol times them (docs/performance/protocol.md):
``dr.freeze``-recorded renders, configurations alternating pass by pass
(each pass loads its scene, renders the warm-up frames, waits until the
process is idle, times one frame and frees the scene), one scene alive at a
time, ``--repeats`` rounds; wall and process CPU seconds are both kept (on
a shared machine the CPU time swings less).
"""

from __future__ import annotations

import gc
import json
import statistics
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

import mi_amr
from ..data.cells import AMRCells
from ..data.datasets import make_dataset
from ..data.io import load_volume
from ..images import write_png
from ..plugins.integrator import MODES as _ALL_MODES

#: The paper's three lighting modes, each reaching its real collisions by
#: tracking (the ray marcher has its own study: ``--vs-yt``, ``--march``)
MODES = tuple(m for m in _ALL_MODES if m != "ray_march")
from .harness import FROZEN_WARMUP, bench_scene, check_alone, frame_function, process_cpu_seconds, wait_idle
from .protocol import SCALES
from .scale import data_file

#: The empty-medium frame of a case (the limit).
EMPTY = "empty"
#: The floor's medium: extinction and albedo, frame size
#: and samples per pixel.
FLOOR_SIGMA_T, FLOOR_ALBEDO, FLOOR_RES, FLOOR_SPP = 8.0, 0.9, 128, 16
#: Cells per axis of the floor's uniform field (one level, one value).
FLOOR_CELLS = 16
#: Density scale of the large data sets (as the scale benchmark).
LARGE_SCALE = 60.0
#: Octree-like data above this size are not generated: block-structured instead.
OCTREE_MAX = 10**7


# ---- Scenes ----------------------------------------------------------------------
def amr_medium(data, tf, scale: float, reconstruction: str = "nearest") -> dict:
    return {"type": "amr", "data": data, "transfer_function": tf, "density_scale": float(scale),
            "reconstruction": reconstruction}


def mode_scenes(medium: dict, res: int, max_depth: int, counters: bool = False) -> dict:
    """``{config: scene dict}``: the empty-medium frame and each mode."""
    scenes = {EMPTY: bench_scene(dict(medium, density_scale=0.0), res,
                                 {"type": "amrvolpath", "max_depth": max_depth})}
    for mode in MODES:
        scenes[mode] = bench_scene(medium, res, {"type": "amrvolpath", "max_depth": max_depth, "mode": mode,
                                                 "counters": counters})
    return scenes


def uniform_cells(n: int = FLOOR_CELLS, value: float = 0.5) -> AMRCells:
    """``n^3`` cells of one level filling their box, all of ``value``."""
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return AMRCells(g, np.zeros(len(g), np.int32), np.full(len(g), value), source="uniform field")


def floor_scenes(max_depth: int, res: int = FLOOR_RES, sigma_t: float = FLOOR_SIGMA_T,
                 albedo: float = FLOOR_ALBEDO) -> dict:
    """``{config: scene dict}`` of the floor: per mode, Mitsuba's
    ``homogeneous`` medium and the uniform ``amr`` field in ``amrvolpath``,
    and ``homogeneous`` in Mitsuba's C++ ``volpath`` (multiple scattering)."""
    homogeneous = {"type": "homogeneous", "sigma_t": float(sigma_t), "albedo": float(albedo)}
    tf = mi_amr.TransferFunction(np.tile([albedo, albedo, albedo, 1.0], (2, 1)), (0.0, 1.0))
    uniform = amr_medium(uniform_cells(), tf, sigma_t)
    scenes = {}
    for mode in MODES:
        integ = {"type": "amrvolpath", "max_depth": max_depth, "mode": mode}
        scenes[f"homogeneous/{mode}"] = bench_scene(homogeneous, res, integ)
        scenes[f"uniform amr/{mode}"] = bench_scene(uniform, res, integ)
    scenes["homogeneous/volpath"] = bench_scene(homogeneous, res, {"type": "volpath", "max_depth": max_depth})
    return scenes


# ---- Timing ----------------------------------------------------------------------
def time_passes(scenes: dict, spp: int, repeats: int, frozen: bool = True, keep_images: bool = False,
                frames: int = 1) -> dict:
    """Frames of each scene pass by pass (A B C A B C ..., ``repeats``
    rounds), one scene alive at a time (docs/design.md section 7); a pass
    times ``frames`` frames in a row (each after the process is idle) and
    keeps their median, so that short frames are not one sample of a noisy
    machine. Returns ``{config: {"wall": [s], "cpu": [s], "images": [...]}}``,
    one entry per round (``images``: each round's first timed frame)."""
    out = {c: {"wall": [], "cpu": [], "images": []} for c in scenes}
    for r in range(repeats):
        for config, scene_dict in scenes.items():
            check_alone(config)
            scene = mi.load_dict(scene_dict)
            frame = frame_function(mi, spp, frozen)
            for w in range(FROZEN_WARMUP if frozen else 1):
                frame(scene, 50_000 + 10 * r + w)
            wall, cpu = [], []
            for k in range(frames):
                wait_idle()
                c0, t0 = process_cpu_seconds(), time.perf_counter()
                img = frame(scene, 1000 * k + r)
                wall.append(time.perf_counter() - t0)
                cpu.append(process_cpu_seconds() - c0)
                if keep_images and k == 0:
                    out[config]["images"].append(img)
            out[config]["wall"].append(statistics.median(wall))
            out[config]["cpu"].append(statistics.median(cpu))
            del scene, frame, img
            gc.collect()
    return out


def real_collisions(scene_dict: dict, spp: int) -> float:
    """Real collisions in media per frame of ``spp`` (one untimed counting
    render of ``amrvolpath`` with ``counters``)."""
    check_alone("counting")
    scene = mi.load_dict(scene_dict)
    integ = scene.integrator()
    np.array(mi.render(scene, spp=spp, seed=7))
    real = float(integ.counters()["real"])
    del scene, integ
    gc.collect()
    return real


def ratio_stats(times, base) -> dict:
    """Median and range of the per-round ratios ``t / t_base``."""
    r = sorted(t / b for t, b in zip(times, base))
    return {"median": statistics.median(r), "range": [r[0], r[-1]]}


def per_collision_ns(times, empty, real: float):
    """Cost of one real collision: the frame's time above the empty frame of
    the same round over the real collisions per frame (median of rounds)."""
    if not real:
        return None
    return 1e9 * statistics.median(t - e for t, e in zip(times, empty)) / real


# ---- The two studies -------------------------------------------------------------
def run_case(name: str, tf_name: str, medium: dict, cells: int, args) -> dict:
    """One data set x TF: every mode and the empty frame, timed alternately."""
    scenes = mode_scenes(medium, args.res, args.max_depth)
    counted = mode_scenes(medium, args.res, args.max_depth, counters=True)
    reals = {m: real_collisions(counted[m], args.spp) for m in MODES}
    timing = time_passes(scenes, args.spp, args.repeats, args.frozen, frames=args.modes_frames)
    empty = timing[EMPTY]
    rec = {"dataset": name, "tf": tf_name, "cells": cells, "res": args.res, "spp": args.spp,
           "empty_s": statistics.median(empty["wall"]), "empty_cpu_s": statistics.median(empty["cpu"]),
           "empty_frames": empty, "modes": {}}
    for m in MODES:
        t = timing[m]
        rec["modes"][m] = {"frame_s": statistics.median(t["wall"]), "cpu_s": statistics.median(t["cpu"]),
                           "fps": 1.0 / statistics.median(t["wall"]), "frames": t,
                           "vs_empty": ratio_stats(t["wall"], empty["wall"]),
                           "vs_empty_cpu": ratio_stats(t["cpu"], empty["cpu"]),
                           "real_per_frame": reals[m],
                           "ns_per_collision": per_collision_ns(t["cpu"], empty["cpu"], reals[m])}
    return rec


def run_floor(args, repeats: int | None = None) -> dict:
    """The uniform field against ``homogeneous``, per mode (the floor)."""
    res, spp = args.modes_floor_res, args.modes_floor_spp
    scenes = floor_scenes(args.max_depth, res)
    tf = mi_amr.TransferFunction(np.tile([FLOOR_ALBEDO] * 3 + [1.0], (2, 1)), (0.0, 1.0))
    uniform = amr_medium(uniform_cells(), tf, FLOOR_SIGMA_T)
    # each medium's own empty frame (extinction 0), to take a frame's cost per collision
    empties = {}
    for m in MODES:
        integ = {"type": "amrvolpath", "max_depth": args.max_depth, "mode": m}
        empties[f"empty amr/{m}"] = bench_scene(dict(uniform, density_scale=0.0), res, integ)
        empties[f"empty homogeneous/{m}"] = bench_scene({"type": "homogeneous", "sigma_t": 0.0}, res, integ)
    reals = {m: real_collisions(bench_scene(uniform, res, {"type": "amrvolpath", "max_depth": args.max_depth,
                                                           "mode": m, "counters": True}), spp) for m in MODES}
    scenes.update(empties)
    timing = time_passes(scenes, spp, repeats or args.repeats, args.frozen, keep_images=True,
                         frames=args.modes_frames)
    rows = {}
    for config, t in timing.items():
        imgs = np.array(t.pop("images"))
        # per-pixel variance of one frame, from the rounds' independent frames
        var = float(imgs.var(axis=0, ddof=1).mean()) if len(imgs) > 1 else float("nan")
        rows[config] = {"frame_s": statistics.median(t["wall"]), "cpu_s": statistics.median(t["cpu"]),
                        "frames": t, "variance": var, "mean": float(imgs.mean())}
    for m in MODES:
        h, a = rows[f"homogeneous/{m}"], rows[f"uniform amr/{m}"]
        a["vs_homogeneous"] = ratio_stats(a["frames"]["wall"], h["frames"]["wall"])
        a["vs_homogeneous_cpu"] = ratio_stats(a["frames"]["cpu"], h["frames"]["cpu"])
        a["efficiency_vs_homogeneous"] = (h["frame_s"] * h["variance"]) / (a["frame_s"] * a["variance"])
        for row, e in ((h, rows[f"empty homogeneous/{m}"]), (a, rows[f"empty amr/{m}"])):
            row["real_per_frame"] = reals[m]          # the same physics: the same expected count
            row["ns_per_collision"] = per_collision_ns(row["frames"]["cpu"], e["frames"]["cpu"], reals[m])
    return {"res": res, "spp": spp, "sigma_t": FLOOR_SIGMA_T, "albedo": FLOOR_ALBEDO, "rows": rows}


def cases(args):
    """``(name, tf name, medium dict, cells)`` of every case: the protocol's
    synthetic data x TF, then the large data sets (loaded once each, as the
    loop reaches them)."""
    for name in args.datasets:
        cells = make_dataset(name, cells=args.sparse_res ** 3 if name == "sparse" else args.cells,
                             levels=7 if name == "stadium" else 4)
        for tf_name in args.tfs:
            tf = mi_amr.TransferFunction.preset(tf_name, cells.value_range)
            yield name, tf_name, amr_medium(cells, tf, SCALES.get((name, tf_name), 100.0)), len(cells)
    for n in args.modes_cells:
        kind = "cloud" if n <= OCTREE_MAX else "blocks"
        path = data_file(kind, int(n), Path(args.data_dir))
        volume = load_volume(path, method="nearest")
        tf = mi_amr.TransferFunction.preset("spiky", volume.value_range)
        yield f"{kind} {n:.0e}", "spiky", amr_medium(volume, tf, LARGE_SCALE), len(volume)
        del volume


# ---- The README's figure ---------------------------------------------------------
def mode_figure(path: Path, args, name: str = "cloud", tf_name: str = "spiky") -> dict:
    """The three modes side by side on one data set (the paper's Fig. 4):
    the protocol's ``cloud`` data (``args.cells``) with the ``spiky`` TF in
    the benchmark's view (sun and a constant sky; emission_absorption shows
    the TF colours self-lit), each rendered at
    ``args.modes_figure_res`` with ``args.modes_figure_spp`` samples, and its
    1-spp frame at that size timed as the tables time them (`time_passes`).
    Writes one PNG of the three pictures; returns ``{mode: {"frame_s",
    "frames"}}``."""
    res, spp = args.modes_figure_res, args.modes_figure_spp
    cells = make_dataset(name, cells=args.cells, levels=4)
    tf = mi_amr.TransferFunction.preset(tf_name, cells.value_range)
    medium = amr_medium(cells, tf, SCALES.get((name, tf_name), 100.0))
    scenes = mode_scenes(medium, res, args.max_depth)
    timing = time_passes({m: scenes[m] for m in MODES}, 1, args.repeats, args.frozen, frames=args.modes_frames)
    panels = []
    for m in MODES:
        scene = mi.load_dict(scenes[m])
        panels.append(np.array(mi.render(scene, spp=spp, seed=1)))
        del scene
        gc.collect()
    write_png(path, np.concatenate(panels, axis=1))
    return {m: {"frame_s": statistics.median(t["wall"]), "frames": t["wall"], "res": res, "figure_spp": spp,
                "dataset": name, "tf": tf_name, "cells": len(cells)} for m, t in timing.items()}


# ---- Tables ----------------------------------------------------------------------
def _range(r) -> str:
    return f"{r['median']:.2f} ({r['range'][0]:.2f}-{r['range'][1]:.2f})"


def write_tables(records: list, floor: dict | None, out: Path, command: str):
    lines = ["# What each lighting mode costs", "", f"`{command}`", ""]
    if records:
        r0 = records[0]
        lines += [f"## Frames/s per mode ({r0['res']}x{r0['res']}, {r0['spp']} spp)", "",
                  "| data | TF | cells | empty frame ms (fps) | " + " | ".join(
                      f"{m} ms (fps)" for m in MODES) + " | emission_absorption / empty | single / empty | "
                  "multi / empty | ns per real collision (EA, single, multi) |",
                  "|---|---|---|---|" + "---|" * (2 * len(MODES) + 1)]
        for r in records:
            ms = [r["modes"][m] for m in MODES]
            ns = ", ".join("-" if x["ns_per_collision"] is None else f"{x['ns_per_collision']:.0f}" for x in ms)
            lines.append(f"| {r['dataset']} | {r['tf']} | {r['cells']:,} | {1e3 * r['empty_s']:.1f} "
                         f"({1 / r['empty_s']:.1f}) | "
                         + " | ".join(f"{1e3 * x['frame_s']:.1f} ({x['fps']:.1f})" for x in ms) + " | "
                         + " | ".join(_range(x["vs_empty"]) for x in ms) + f" | {ns} |")
        lines += ["", "Ratios: frame time over the empty-medium frame of the same round (median, range over "
                  "rounds; the target for emission_absorption is at most 1.5). Cost per real collision: "
                  "(CPU time of the frame - CPU time of the empty frame) / real collisions per frame.", ""]
    if floor:
        rows = floor["rows"]
        lines += [f"## The floor: a uniform field against Mitsuba's homogeneous medium ({floor['res']}x"
                  f"{floor['res']}, {floor['spp']} spp, sigma_t {floor['sigma_t']:g}, albedo {floor['albedo']:g})",
                  "",
                  "| mode | homogeneous ms | uniform amr ms | amr / homogeneous (wall) | (CPU) | variance homogeneous | "
                  "variance amr | efficiency amr / homogeneous | real collisions per frame | ns per collision "
                  "homogeneous | ns per collision amr |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for m in MODES:
            h, a = rows[f"homogeneous/{m}"], rows[f"uniform amr/{m}"]
            nh, na = h["ns_per_collision"], a["ns_per_collision"]
            lines.append(f"| {m} | {1e3 * h['frame_s']:.1f} | {1e3 * a['frame_s']:.1f} | "
                         f"{_range(a['vs_homogeneous'])} | {_range(a['vs_homogeneous_cpu'])} | "
                         f"{h['variance']:.3g} | {a['variance']:.3g} | {a['efficiency_vs_homogeneous']:.2f} | "
                         f"{a['real_per_frame']:,.0f} | {nh if nh is None else f'{nh:.0f}'} | "
                         f"{na if na is None else f'{na:.0f}'} |")
        v = rows["homogeneous/volpath"]
        lines += ["", f"Mitsuba's C++ volpath with the homogeneous medium (multi): {1e3 * v['frame_s']:.1f} ms, "
                  f"variance {v['variance']:.3g}. Variance: per pixel, of one frame, over the rounds' frames. "
                  "Cost per collision: CPU time above the same medium's empty frame (extinction 0, same "
                  "mode) over the real collisions per frame."]
    (out / "modes.md").write_text("\n".join(lines) + "\n")


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--modes``)."""
    mi.set_variant(args.variant)
    if args.spp == 16:                  # the protocol's default: this study's is 1 spp
        args.spp = 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python -m mi_amr.bench " + " ".join(getattr(args, "argv", []) or ["--modes"])
    records, floor = [], None
    for name, tf_name, medium, n in cases(args):
        rec = run_case(name, tf_name, medium, n, args)
        del medium
        records.append(rec)
        m = rec["modes"]
        print(f"{name:12s} {tf_name:6s} {n:>12,d} cells: empty {1e3 * rec['empty_s']:6.1f} ms, "
              + ", ".join(f"{k} {1e3 * m[k]['frame_s']:6.1f} ms (x{m[k]['vs_empty']['median']:.2f})" for k in MODES),
              flush=True)
        (out / "modes.json").write_text(json.dumps({"cases": records, "floor": floor}, indent=1, default=float))
    if args.modes_figure:
        fig = mode_figure(Path(args.modes_figure), args)
        print(f"wrote {args.modes_figure}: " + ", ".join(
            f"{m} {1e3 * f['frame_s']:.0f} ms a 1-spp frame" for m, f in fig.items()), flush=True)
        (out / "modes_figure.json").write_text(json.dumps(fig, indent=1))
    if args.modes_floor:
        floor = run_floor(args)
        for m in MODES:
            a = floor["rows"][f"uniform amr/{m}"]
            print(f"floor {m:20s}: homogeneous {1e3 * floor['rows'][f'homogeneous/{m}']['frame_s']:6.1f} ms, "
                  f"uniform amr {1e3 * a['frame_s']:6.1f} ms (x{a['vs_homogeneous']['median']:.2f}), "
                  f"efficiency x{a['efficiency_vs_homogeneous']:.2f}", flush=True)
    (out / "modes.json").write_text(json.dumps({"cases": records, "floor": floor}, indent=1, default=float))
    write_tables(records, floor, out, command)
    print(f"wrote {out}/modes.json and modes.md")
    return 0
