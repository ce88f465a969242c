#!/usr/bin/env python
"""Paired A/B of the tracking code: the estimators as consumers of one
segment walk (`mi_amr.device.tracking.walk_segments`, the work tree) against
the single 13-parameter ``track_segments`` they replaced (issue 29), in one
process.

    DRJIT_LIBLLVM_PATH="$(tools/find-llvm19)" .venv/bin/python tools/ab_tracking.py \\
        [--cases cloud/spiky cloud/foggy blocks/foggy sparse/foggy] [--rounds 9] [--frames 3]

"old" (A) is ``mi_amr/device/tracking.py`` of ``--rev`` (default: commit
f28a95a, the last with ``track_segments``), taken with ``git show`` and
loaded as a module of its own; the ``amr`` medium's ``free_flight``,
``transmittance`` and ``intersect_aabb`` are swapped (on the class) for
adapters that call it exactly as that commit's medium did and hand back the
new typed results, so the integrator is the same on both sides. "new" (B)
is the work tree's code.

A case is ``DATA/TF``, ``DATA/TF/minorants`` or ``DATA/TF/volpath``: the
20k-cell synthetic data set ``DATA`` of `mi_amr.data.datasets.make_dataset`
(``sparse``: the 128^3 field, ``cells=128**3``) with the benchmark's view,
TF and density scale (`mi_amr.bench.protocol`), rendered by ``amrvolpath``
with its default estimators (plain ones on these data); with
``/minorants``, with residual ratio and decomposition tracking forced on;
with ``/volpath``, by Mitsuba's stock ``volpath`` with the ray-wise
majorant (the span-majorant walk of ``intersect_aabb``).

Per case, one scene is loaded and kept (one scene alive: Dr.Jit dispatches
over every live medium), each side gets a ``dr.freeze``-recorded render of
its own (recorded while its code is active, then warmed up; ``--plain``:
plain ``mi.render`` frames, traced anew every frame), and the timed
frames alternate A B, B A, ... (``--rounds`` rounds of ``--frames`` frames
per side, each side after `wait_idle`). Every round renders the same seeds
on both sides and checks that the images are bit-identical; before timing,
one plain render per side also checks the integrator's counters (look-ups,
null and real collisions, steps, capped; ``amrvolpath`` only).

Printed per case: the median over rounds of the frame-time ratio new / old
(below 1: the new code is faster) with its range and interquartile range,
and the median frame times. The machine is shared (2 cores): other
processes add noise to single rounds, which the paired ratio and the median
damp but do not remove. Exit status 1 if any image or counter differs.
About 10-15 s per case at the defaults (25 rounds: about 15-25 s).
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: The last commit whose tracking.py has the 13-parameter ``track_segments``.
OLD_REV = "f28a95ae4ab308199b0af3b4805876e5fc6f2b35"


def load_old_tracking(rev: str):
    """``mi_amr/device/tracking.py`` at ``rev`` as the module
    ``mi_amr.device._tracking_ab_old`` (from a file: ``@dr.syntax`` reads
    the source)."""
    src = subprocess.run(["git", "show", f"{rev}:mi_amr/device/tracking.py"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    if "def track_segments" not in src:
        raise SystemExit(f"ab_tracking: {rev}:mi_amr/device/tracking.py has no track_segments")
    path = Path(tempfile.mkdtemp(prefix="ab_tracking_")) / "tracking_old.py"
    path.write_text(src)
    name = "mi_amr.device._tracking_ab_old"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "mi_amr.device"
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def old_methods(old):
    """``free_flight``, ``transmittance`` (returning the new typed
    results) and ``intersect_aabb`` as the old medium had them."""
    import drjit as dr
    import mitsuba as mi

    from mi_amr.device.ray import intersect_unit_cube, safe_rcp
    from mi_amr.device.tracking import FreeFlight, TrackingCounts, Transmittance

    def track(med, ray, t_max, sampler, active, ratio, control):
        o, d, s = med.local_ray(ray)
        hit, t0, t1 = intersect_unit_cube(o, safe_rcp(d))
        t_lo = dr.maximum(t0, 0.0)
        t_hi = dr.minimum(t1, t_max * s)
        active = mi.Bool(active) & hit & (s > 0.0) & (t_lo < t_hi) & (med.structures.global_majorant > 0.0)
        collided, t, albedo, result, c = old.track_segments(
            med.structures.segments(), (med.value_local, med.albedo_of), o, d, t_lo, t_hi, sampler,
            active, ratio, med._max_iterations, s, control, med.tf_device.rgb_constant)
        counts = TrackingCounts(c.lookups, c.null, c.real, c.steps, c.capped)
        return collided, t * dr.rcp(dr.select(s > 0.0, s, 1.0)), albedo, result, counts

    def free_flight(self, ray, t_max, sampler, active, control=False):
        collided, t, albedo, sigma_t, counts = track(self, ray, t_max, sampler, active, False, control)
        return FreeFlight(collided=collided, t=t, albedo=albedo, sigma_t=sigma_t, counts=counts)

    def transmittance(self, ray, t_max, sampler, active, control=False):
        _, _, _, T, counts = track(self, ray, t_max, sampler, active, True, control)
        return Transmittance(T=T, counts=counts)

    def intersect_aabb(self, ray):
        key = self._ray_majorant.key_of(ray)
        o, d, s = self.local_ray(ray)
        inv_s = dr.rcp(dr.select(s > 0.0, s, 1.0))
        hit, t0, t1 = intersect_unit_cube(o, safe_rcp(d))
        hit &= s > 0.0
        global_mu = self.structures.global_majorant
        if self.majorant_mode == "global":
            return hit & (global_mu > 0.0), t0 * inv_s, t1 * inv_s
        t_start = dr.maximum(t0, 0.0)
        t_end = dr.minimum(t1, ray.maxt * s)
        segments = self.structures.segments()
        found, t_first, t_last, mu, _ = old.span_majorant(segments, o, d, t_start, t_end, hit,
                                                          segments.max_steps(), global_mu)
        self._ray_majorant.store(key, mu)
        return found, t_first * inv_s, t_last * inv_s

    return {"free_flight": free_flight, "transmittance": transmittance, "intersect_aabb": intersect_aabb}


@contextmanager
def side(cls, methods):
    """The medium class with ``methods`` in place (none: as it is)."""
    saved = {k: cls.__dict__.get(k) for k in methods}
    for k, f in methods.items():
        setattr(cls, k, f)
    try:
        yield
    finally:
        for k, f in saved.items():
            if f is None:
                delattr(cls, k)
            else:
                setattr(cls, k, f)


def case_scene(mi, spec: str, res: int):
    """The benchmark scene of a case ``DATA/TF[/minorants|/volpath]``."""
    import argparse as ap

    import mi_amr
    from mi_amr.data.datasets import make_dataset
    from mi_amr.bench.protocol import SCALES, config_scene
    parts = spec.split("/")
    name, tf_name, option = parts[0], parts[1], (parts[2:] or [None])[0]
    if option not in (None, "minorants", "volpath"):
        raise SystemExit(f"ab_tracking: unknown case option {option!r} in {spec!r}")
    cells = make_dataset(name, cells=128 ** 3) if name == "sparse" else make_dataset(name, cells=20000)
    tf = mi_amr.TransferFunction.preset(tf_name, cells.value_range)
    args = ap.Namespace(max_depth=64, reconstruction="nearest", no_value_masks=False, grid_refinement=None,
                        res=res, memory_limit=4.0)
    config = "volpath/ray" if option == "volpath" else "amrvolpath/default"
    scene = config_scene(mi, config, cells, tf, SCALES.get((name, tf_name), 100.0), args)
    if option == "minorants":
        scene["integrator"].update(residual_ratio_tracking=True, decomposition_tracking=True)
    return scene


def run_case(mi, spec, old, args):
    import drjit as dr
    import numpy as np

    from mi_amr.plugins.medium import AMRMedium
    from mi_amr.bench.harness import FROZEN_WARMUP, wait_idle
    cls = AMRMedium.variant_class()
    scene = mi.load_dict(case_scene(mi, spec, args.res))
    integrator = scene.integrator()
    sides = {"old": old, "new": {}}

    # ---- same numerics: counters and image of one plain render per side ----
    counters, images = {}, {}
    for label, methods in sides.items():
        with side(cls, methods):
            if hasattr(integrator, "reset_counters"):       # amrvolpath; volpath has none
                integrator.reset_counters()
            images[label] = np.array(mi.render(scene, spp=args.spp, seed=1))
            counters[label] = ({k: v for k, v in integrator.counters().items() if isinstance(v, int)}
                               if hasattr(integrator, "counters") else {})
    same_counters = counters["old"] == counters["new"]
    same = bool(np.array_equal(images["old"], images["new"])) and same_counters

    # ---- one frozen render per side, recorded while its code is active ----
    def render(scene, seed):
        return mi.render(scene, spp=args.spp, seed=seed)
    frames = {}
    for label, methods in sides.items():
        frames[label] = render if args.plain else dr.freeze(render)
        with side(cls, methods):
            for w in range(1 if args.plain else FROZEN_WARMUP):
                np.array(frames[label](scene, dr.opaque(mi.UInt32, 90_000 + w)))

    times = {"old": [], "new": []}
    for r in range(args.rounds):
        out = {}
        for label in (("old", "new") if r % 2 == 0 else ("new", "old")):
            with side(cls, sides[label]):
                wait_idle()
                t0 = time.perf_counter()
                for f in range(args.frames):
                    img = np.array(frames[label](scene, dr.opaque(mi.UInt32, 1000 * r + f)))
                times[label].append((time.perf_counter() - t0) / args.frames)
                out[label] = img
        same &= bool(np.array_equal(out["old"], out["new"]))
    del scene, integrator, frames
    gc.collect()
    ratios = sorted(n / o for n, o in zip(times["new"], times["old"]))
    q = statistics.quantiles(ratios, n=4) if len(ratios) >= 4 else (ratios[0], None, ratios[-1])
    res = {"case": spec, "ratio": statistics.median(ratios), "min": ratios[0], "max": ratios[-1],
           "q1": q[0], "q3": q[-1], "old_ms": 1e3 * statistics.median(times["old"]),
           "new_ms": 1e3 * statistics.median(times["new"]), "same": same, "counters": counters["new"]}
    print(f"{spec:24s} new/old {res['ratio']:.3f} (range {res['min']:.3f}-{res['max']:.3f}, "
          f"IQR {res['q1']:.3f}-{res['q3']:.3f}), frames old {res['old_ms']:.1f} ms, new {res['new_ms']:.1f} ms, "
          f"same images and counters: {same}", flush=True)
    if not same_counters:
        print(f"  counters differ: old {counters['old']}, new {counters['new']}", flush=True)
    return res


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=["cloud/spiky", "cloud/foggy", "blocks/foggy", "sparse/foggy"],
                   help="DATA/TF or DATA/TF/minorants")
    p.add_argument("--rev", default=OLD_REV, help="git revision of the old tracking.py (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=9)
    p.add_argument("--frames", type=int, default=3, help="frames per side per round")
    p.add_argument("--res", type=int, default=96)
    p.add_argument("--spp", type=int, default=8)
    p.add_argument("--plain", action="store_true",
                   help="time plain frames (traced anew each frame) instead of frozen ones")
    args = p.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from mi_amr._llvm import ensure_llvm_path
    ensure_llvm_path()
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    old = old_methods(load_old_tracking(args.rev))
    t0 = time.perf_counter()
    results = [run_case(mi, spec, old, args) for spec in args.cases]
    ratios = [r["ratio"] for r in results]
    print(f"median over cases of the median ratio new/old: {statistics.median(ratios):.3f} "
          f"(cases {min(ratios):.3f}-{max(ratios):.3f}); all identical: {all(r['same'] for r in results)} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0 if all(r["same"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
