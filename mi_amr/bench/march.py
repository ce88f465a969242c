"""The paper's comparison on this CPU: the sci-vis ray marcher against the
path tracer's convergence frames (docs/performance/march.md):
``python -m mi_amr.bench --march --out DIR``.

Beyond ExaBricks (Zellmann et al.) compares ExaBricks' ray marcher at its
maximum quality (4 frames/s on two RTX 8000) with its path tracer's 1-spp
convergence frames (16 frames/s on one RTX 4090). Here, per data set (the
block-structured generator of ``--scale`` at ``--march-cells``, 10^7 and
10^8 by default) and TF (``spiky``, ``foggy``), at ``--march-res`` (512):

* frames/s of ``ray_march`` with ``shading="gradient"`` at its finest
  quality (``step_scale`` `FINEST_STEP`) and at its default step, and of
  ``multi`` at 1 spp, timed alternately one scene alive at a time
  (`mi_amr.bench.modes.time_passes`, frozen frames);
* the time each needs to a picture within `TARGET` (2%) RMSE of its own
  converged image, relative to the image's mean. The error of an
  ``N``-spp picture is estimated from two independent ones, ``A`` and
  ``B``: ``rms(A - B) / sqrt(2)`` (their errors are independent with the
  same law), without a converged image to render; for the path tracer the
  spp to the target follow from ``1 / sqrt(spp)`` (unbiased Monte Carlo),
  measured at ``--march-multi-spp``; for the marcher (its error is the
  pixel footprint and the jitter) the spp are doubled from 1 until the
  estimate is below the target.

With ``--modes-figure PNG`` it draws the three path-traced modes beside the
marcher on the protocol's ``cloud`` data instead (`march_figure`).
"""

from __future__ import annotations

import gc
import math
import statistics
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

import mi_amr
from ..data.datasets import make_dataset
from ..data.io import load_volume
from ..images import write_png
from .harness import bench_scene, check_alone, write_report
from .modes import LARGE_SCALE, time_passes
from .protocol import SCALES as PROTOCOL_SCALES
from .scale import data_file

#: The marcher's finest quality: a quarter of the finest cell under each leaf.
FINEST_STEP = 0.25
#: The marcher's default step (`mi_amr.plugins.integrator.DEFAULT_STEP_SCALE`).
DEFAULT_STEP = 0.5
#: The picture's error target: RMSE within 2% of the image's mean.
TARGET = 0.02
#: Density scales of the two TFs on the block-structured data (inverse
#: unit-cube lengths): the modes study's for spiky, more for the thin foggy.
SCALES = {"spiky": LARGE_SCALE, "foggy": 2 * LARGE_SCALE}
#: The paper's figures (frames/s at maximum quality; GPUs).
PAPER = {"marcher": 4.0, "path tracer": 16.0}


def scenes_of(volume, tf_name: str, res: int) -> dict:
    """The three configurations' scene dictionaries on ``volume``."""
    tf = mi_amr.TransferFunction.preset(tf_name, volume.value_range)
    medium = {"type": "amr", "data": volume, "transfer_function": tf, "density_scale": SCALES[tf_name]}
    march = {"type": "amrvolpath", "mode": "ray_march", "shading": "gradient"}
    return {f"ray_march step {FINEST_STEP}": bench_scene(medium, res, dict(march, step_scale=FINEST_STEP)),
            f"ray_march step {DEFAULT_STEP}": bench_scene(medium, res, dict(march, step_scale=DEFAULT_STEP)),
            "multi 1 spp": bench_scene(medium, res, {"type": "amrvolpath", "mode": "multi", "max_depth": 64})}


def relative_error(a: np.ndarray, b: np.ndarray) -> float:
    """The RMSE of one picture against its converged image, from two
    independent pictures ``a`` and ``b`` of it: ``rms(a - b) / sqrt(2)``,
    relative to their mean."""
    mean = 0.5 * float(a.mean() + b.mean())
    return float(np.sqrt(np.mean((a - b) ** 2) / 2.0)) / max(mean, 1e-12)


def spp_to_target(scene_dict: dict, multi: bool, multi_spp: int, max_spp: int = 64) -> dict:
    """Samples per pixel to `TARGET` (see the module docstring): ``{"spp":
    ..., "error_at": {spp: error}, "extrapolated": bool}``."""
    check_alone("error")
    scene = mi.load_dict(scene_dict)
    errors = {}
    try:
        if multi:
            a = np.array(mi.render(scene, spp=multi_spp, seed=1), dtype=np.float64)
            b = np.array(mi.render(scene, spp=multi_spp, seed=2), dtype=np.float64)
            e = errors[multi_spp] = relative_error(a, b)
            return {"spp": multi_spp * (e / TARGET) ** 2, "error_at": errors, "extrapolated": True}
        spp = 1
        while True:
            a = np.array(mi.render(scene, spp=spp, seed=1), dtype=np.float64)
            b = np.array(mi.render(scene, spp=spp, seed=2), dtype=np.float64)
            e = errors[spp] = relative_error(a, b)
            if e <= TARGET or spp >= max_spp:
                return {"spp": spp, "error_at": errors, "extrapolated": e > TARGET}
            spp *= 2
    finally:
        del scene
        gc.collect()


def run_case(volume, tf_name: str, args) -> dict:
    scenes = scenes_of(volume, tf_name, args.march_res)
    timing = time_passes(scenes, 1, args.repeats, frozen=args.frozen)
    rec = {"cells": len(volume), "tf": tf_name, "res": args.march_res, "configs": {}}
    for config, t in timing.items():
        frame_s = statistics.median(t["wall"])
        target = spp_to_target(scenes[config], config.startswith("multi"), args.march_multi_spp)
        rec["configs"][config] = {"frame_s": frame_s, "fps": 1.0 / frame_s, "wall": t["wall"], "cpu": t["cpu"],
                                  "spp_to_target": target["spp"], "error_at": target["error_at"],
                                  "extrapolated": target["extrapolated"],
                                  "seconds_to_target": target["spp"] * frame_s}
        print(f"  {config}: {1e3 * frame_s:.0f} ms a frame, {target['spp']:.3g} spp to {100 * TARGET:.0f}%"
              f"{' (extrapolated)' if target['extrapolated'] else ''}", flush=True)
    return rec


def report(records: list, command: str) -> str:
    lines = ["# The ray marcher against the path tracer's convergence frames", "", f"`{command}`", "",
             f"The paper (GPUs): the marcher {PAPER['marcher']:g} frames/s at maximum quality on two RTX 8000, "
             f"the path tracer {PAPER['path tracer']:g} 1-spp convergence frames/s on one RTX 4090.", "",
             "| cells | TF | config | frame ms (range) | frames/s | spp to 2% | s to 2% | error at spp |",
             "|---|---|---|---|---|---|---|---|"]
    for r in records:
        for config, c in r["configs"].items():
            errs = ", ".join(f"{100 * e:.2f}% at {s}" for s, e in c["error_at"].items())
            star = "*" if c["extrapolated"] else ""
            lines.append(f"| {r['cells']:,} | {r['tf']} | {config} | {1e3 * c['frame_s']:.0f} "
                         f"({1e3 * min(c['wall']):.0f}-{1e3 * max(c['wall']):.0f}) | {c['fps']:.2f} | "
                         f"{c['spp_to_target']:.3g}{star} | {c['seconds_to_target']:.3g}{star} | {errs} |")
    lines += ["", f"Error: RMSE against the converged image relative to its mean, from two independent pictures "
              f"(`rms(A - B) / sqrt(2)`); `*`: the path tracer's spp to {100 * TARGET:.0f}% from "
              "`1 / sqrt(spp)` at the measured spp (or the marcher's cap reached)."]
    return "\n".join(lines) + "\n"


def march_figure(path: Path, args, spp: int = 64, march_spp: int = 4) -> dict:
    """The three path-traced modes beside the marcher (flat and gradient
    shading) on the protocol's ``cloud`` data with the ``spiky`` TF in the
    benchmark's view, ``args.modes_figure_res`` square: the path-traced
    ones at ``spp``, the marcher at ``march_spp``; one PNG, left to right
    emission_absorption, single, multi, ray_march flat, ray_march gradient.
    Returns each panel's render seconds."""
    res = args.modes_figure_res
    cells = make_dataset("cloud", cells=args.cells, levels=4)
    tf = mi_amr.TransferFunction.preset("spiky", cells.value_range)
    medium = {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": PROTOCOL_SCALES[("cloud", "spiky")]}
    panels, seconds = [], {}
    configs = [(m, {"type": "amrvolpath", "mode": m, "max_depth": 64}, spp) for m in ("emission_absorption", "single",
                                                                                       "multi")]
    configs += [(f"ray_march {sh}", {"type": "amrvolpath", "mode": "ray_march", "shading": sh}, march_spp)
                for sh in ("flat", "gradient")]
    for name, integrator, n in configs:
        check_alone(name)
        scene = mi.load_dict(bench_scene(medium, res, integrator))
        mi.render(scene, spp=1)                                   # compiled before the clock starts
        t0 = time.perf_counter()
        panels.append(np.array(mi.render(scene, spp=n, seed=1)))
        seconds[name] = {"seconds": time.perf_counter() - t0, "spp": n}
        del scene
        gc.collect()
    write_png(path, np.concatenate(panels, axis=1))
    return seconds


def main_args(args) -> int:
    mi.set_variant(args.variant)
    if args.modes_figure:
        seconds = march_figure(Path(args.modes_figure), args)
        print("\n".join(f"{k}: {v['seconds']:.2f} s at {v['spp']} spp" for k, v in seconds.items()))
        return 0
    out = Path(args.out or "out/bench-march")
    records = []
    t0 = time.perf_counter()
    for n in args.march_cells:
        path = data_file("blocks", int(n), Path(args.data_dir))
        volume = load_volume(path)
        print(f"{path.name}: {len(volume):,} cells", flush=True)
        for tf_name in args.tfs:
            records.append(run_case(volume, tf_name, args))
        del volume
        gc.collect()
    command = "python -m mi_amr.bench --march --march-cells " + " ".join(f"{n:g}" for n in args.march_cells) + \
        f" --march-res {args.march_res}"
    write_report(out, "march", {"records": records, "paper": PAPER, "seconds": time.perf_counter() - t0},
                 report(records, command))
    return 0 if all(math.isfinite(c["frame_s"]) for r in records for c in r["configs"].values()) else 1
