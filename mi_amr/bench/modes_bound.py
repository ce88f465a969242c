"""What bounds the emission-absorption frame of delta tracking
(docs/performance/modes.md section 1b): ``python -m mi_amr.bench
--modes-bound --out DIR``.

A frame of ``emission_absorption`` is the empty-medium frame, plus the walk
through the macrocell segments, plus one density look-up per tentative
collision (null or real). Each part is measured on its own, per case (the
cases of ``--modes``: ``--datasets`` x ``--tfs``, then ``--modes-cells``),
in Dr.Jit's kernel history (the execution time of the frame's kernel: no
Python, tracing or launch costs), one scene alive, its density scale set
in turn to 0 (the empty frame: the global majorant is 0, no walk),
``WALK_SCALE`` times the case's (the same segments, next to no tentative
collision: the walk alone) and the case's (the frame), alternated round by
round:

* ``walk_ms``: the walk alone, scaled to the frame's segments (counted: a
  two-level grid refines less at the walk's tiny scale, so the walk alone
  crosses somewhat fewer segments than the frame);
* the price of a look-up: in the frame, ``(frame - walk) / look-ups``; in a
  full SIMD packet, one kernel of ``--modes-bound-points`` look-ups at
  points drawn where tentative collisions fall (in proportion to the
  majorant), the cheapest a look-up was seen to be;
* look-ups per camera ray with the medium's majorants on a uniform grid of
  ``--modes-bound-res``^3 macrocells (counted, not timed).

Two lower bounds on the frame follow (kernel time, over the empty frame):
``perfect``, a majorant equal to the extinction everywhere (the real
collisions are the only look-ups), and ``fine``, the majorants of the fine
grid, both with the default grid's segments (a finer grid walks more) and
every look-up at the full-packet price. Neither can be built; they bound
what any grid of macrocells can do for this frame.
"""

from __future__ import annotations

import gc
import json
import statistics
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_amr
from .harness import bench_scene, check_alone

#: The walk alone: the case's density scale times this (the same non-zero
#: majorants, so the same segments, and next to no tentative collision).
WALK_SCALE = 1e-5
#: Frames timed per configuration and round (their median kept).
FRAMES = 7
MODE = "emission_absorption"


def longest_kernel_ms(work) -> float:
    """Execution time (ms) of the longest kernel that evaluating ``work()``
    launches (Dr.Jit's kernel history): the computation's own kernel, not
    the small ones around it."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    dr.eval(work())
    dr.sync_thread()
    history = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return max(k["execution_time"] for k in history if k.get("type") == dr.KernelType.JIT)


def frame_kernel_ms(scene, seed: int) -> float:
    """The kernel of one 1-spp frame (ms; the film's development and copies
    are small ones)."""
    return longest_kernel_ms(lambda: mi.render(scene, spp=1, seed=seed))


def counts_per_ray(scene_dict: dict, rays: int, scales: dict) -> dict:
    """``{name: {lookups, real, steps}}`` per camera ray of one counting
    frame, the medium's density scale set to each of ``scales``."""
    check_alone("counting")
    scene = mi.load_dict(scene_dict)
    integ, medium = scene.integrator(), mi_amr.amr_media(scene)[0]
    out = {}
    for name, s in scales.items():
        medium.set_transfer_function(medium.tf, s)
        integ.reset_counters()
        dr.eval(mi.render(scene, spp=1, seed=7))
        c = integ.counters()
        out[name] = {k: c[k] / rays for k in ("lookups", "real", "steps")}
    del scene, integ, medium
    gc.collect()
    return out


def packet_lookup_ns(medium, points: int, seed: int = 0) -> float:
    """Price of one look-up (ns) when a whole SIMD packet looks up at once:
    one kernel of ``points`` density look-ups (`value_local`) at points
    drawn as tentative collisions fall, a macrocell in proportion to its
    majorant and uniformly inside it; the median of five kernels."""
    mu = medium.majorant_grid                               # [z, y, x]
    if not mu.any():
        raise ValueError("every majorant is 0: no tentative collision to place")
    rng = np.random.default_rng(seed)
    flat = rng.choice(mu.size, size=points, p=(mu / mu.sum()).ravel())
    zyx = np.stack(np.unravel_index(flat, mu.shape), -1)[:, ::-1]            # x, y, z
    u = (zyx + rng.random((points, 3))) / np.array(mu.shape[::-1])
    ts = []
    for _ in range(5):
        p = mi.Vector3f(*[mi.Float(u[:, a].astype(np.float32)) for a in range(3)])
        dr.eval(p)
        ts.append(longest_kernel_ms(lambda: medium.value_local(p, True)))
    return 1e6 * statistics.median(ts) / points


def run_bound(name: str, tf_name: str, medium_dict: dict, cells: int, args) -> dict:
    """One case: the three kernels, the counts and the two bounds."""
    res, scale = args.res, float(medium_dict["density_scale"])
    rays = res * res
    integ = {"type": "amrvolpath", "max_depth": args.max_depth, "mode": MODE}
    scales = {"empty": 0.0, "walk": scale * WALK_SCALE, "frame": scale}
    counts = counts_per_ray(bench_scene(medium_dict, res, dict(integ, counters=True)), rays, scales)
    fine = dict(medium_dict, grid_resolution=args.modes_bound_res, grid_refinement=1)
    counts["fine"] = counts_per_ray(bench_scene(fine, res, dict(integ, counters=True)), rays,
                                    {"frame": scale})["frame"]

    check_alone(name)
    scene = mi.load_dict(bench_scene(medium_dict, res, integ))
    medium = mi_amr.amr_media(scene)[0]
    times = {k: [] for k in scales}
    for r in range(args.repeats):
        for k, s in scales.items():
            medium.set_transfer_function(medium.tf, s)
            for w in range(2):
                frame_kernel_ms(scene, 90_000 + w)
            times[k].append(statistics.median(frame_kernel_ms(scene, 1000 * r + f) for f in range(FRAMES)))
    medium.set_transfer_function(medium.tf, scale)
    packet_ns = packet_lookup_ns(medium, args.modes_bound_points)
    grid = medium.structures.grid.describe()
    del scene, medium
    gc.collect()

    empty, walk, frame = (statistics.median(times[k]) for k in scales)
    walk_segments, frame_segments = counts["walk"]["steps"], counts["frame"]["steps"]
    # the walk's cost per segment, times the frame's segments (its rays stop at a real collision)
    walk_in_frame = empty + (walk - empty) * frame_segments / max(walk_segments, 1e-12)
    lookups, real = counts["frame"]["lookups"], counts["frame"]["real"]
    per_lookup_ms = packet_ns * rays * 1e-6                   # one look-up per ray, in a full packet
    bounds = {"perfect": walk_in_frame + real * per_lookup_ms,
              "fine": walk_in_frame + counts["fine"]["lookups"] * per_lookup_ms}
    return {"dataset": name, "tf": tf_name, "cells": cells, "res": res, "grid": grid,
            "fine_res": args.modes_bound_res, "kernel_ms": times,
            "empty_ms": empty, "walk_ms": walk_in_frame, "frame_ms": frame, "frame_vs_empty": frame / empty,
            "counts_per_ray": counts,
            "lookup_ns_in_frame": 1e6 * (frame - walk_in_frame) / max(lookups * rays, 1e-12),
            "lookup_ns_packet": packet_ns,
            "bounds_ms": bounds, "bounds_vs_empty": {k: v / empty for k, v in bounds.items()},
            "fine_bound_vs_frame": bounds["fine"] / frame}


def write_table(records: list, out: Path, command: str):
    lines = ["# What bounds the emission-absorption frame", "", f"`{command}`", "",
             f"Kernel times (Dr.Jit kernel history), ms, medians of {len(records[0]['kernel_ms']['empty'])} rounds; "
             f"{records[0]['res']}x{records[0]['res']}, 1 spp; counts per camera ray.", "",
             "| data | TF | cells | grid | empty | walk | frame (x empty) | segments | look-ups (real) | "
             "look-ups, fine grid | ns a look-up: frame, packet | bound: perfect majorant (x empty) | "
             "bound: fine grid (x empty) | bound / frame |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        c, b, bx = r["counts_per_ray"], r["bounds_ms"], r["bounds_vs_empty"]
        lines.append(
            f"| {r['dataset']} | {r['tf']} | {r['cells']:,} | {r['grid']} | {r['empty_ms']:.2f} | "
            f"{r['walk_ms']:.2f} | {r['frame_ms']:.2f} (x{r['frame_vs_empty']:.2f}) | "
            f"{c['frame']['steps']:.2f} | {c['frame']['lookups']:.3f} ({c['frame']['real']:.3f}) | "
            f"{c['fine']['lookups']:.3f} ({r['fine_res']}^3) | {r['lookup_ns_in_frame']:.0f}, "
            f"{r['lookup_ns_packet']:.0f} | {b['perfect']:.2f} (x{bx['perfect']:.2f}) | "
            f"{b['fine']:.2f} (x{bx['fine']:.2f}) | {r['fine_bound_vs_frame']:.2f} |")
    lines += ["", "walk: the walk alone (density scale x1e-5), scaled to the frame's segments. Bounds: the "
              "walk plus, at the full-packet price, the real collisions only (perfect) or the look-ups of a "
              "uniform grid of the fine resolution (fine); the segments stay the default grid's."]
    (out / "modes_bound.md").write_text("\n".join(lines) + "\n")


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--modes-bound``)."""
    from .modes import cases
    mi.set_variant(args.variant)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python -m mi_amr.bench " + " ".join(getattr(args, "argv", []) or ["--modes-bound"])
    records = []
    for name, tf_name, medium, n in cases(args):
        rec = run_bound(name, tf_name, medium, n, args)
        del medium
        records.append(rec)
        print(f"{name:12s} {tf_name:6s} {n:>12,d} cells: empty {rec['empty_ms']:.2f} ms, walk "
              f"{rec['walk_ms']:.2f}, frame {rec['frame_ms']:.2f} (x{rec['frame_vs_empty']:.2f}); bounds x"
              f"{rec['bounds_vs_empty']['perfect']:.2f} (perfect), x{rec['bounds_vs_empty']['fine']:.2f} "
              f"({args.modes_bound_res}^3)", flush=True)
        (out / "modes_bound.json").write_text(json.dumps(records, indent=1, default=float))
    if records:
        write_table(records, out, command)
    print(f"wrote {out}/modes_bound.json and modes_bound.md")
    return 0
