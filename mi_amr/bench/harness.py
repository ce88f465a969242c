"""The benchmarks' shared harness: the benchmark scene and camera, frames
timed alone and idle, frozen frames.

Every benchmark (`mi_amr.bench.protocol` and the scale, resample, view and
peer studies) renders through these, so that they time the same thing the
same way (docs/performance/protocol.md).
"""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..plugins.medium import live_media


#: The benchmark camera: position, the point it looks at (the volume is the
#: unit cube) and its field of view in degrees.
BENCH_ORIGIN, BENCH_TARGET, BENCH_FOV = (1.7, 1.25, 2.4), (0.5, 0.47, 0.5), 38.0


def zoom_camera(target, width: float):
    """``(origin, target, fov)`` of a telephoto view of ``target`` (a point
    of the unit cube) from the benchmark camera's direction and distance,
    whose field of view spans ``width`` (unit-cube lengths) at the target:
    the camera stays outside the volume."""
    o, t = np.array(BENCH_ORIGIN), np.array(BENCH_TARGET)
    dist = float(np.linalg.norm(o - t))
    target = np.asarray(target, dtype=np.float64)
    return (tuple(target + (o - t)), tuple(target),                 # the same offset as the benchmark's
            float(np.degrees(2.0 * np.arctan(0.5 * width / dist))))


def bench_scene(medium, res: int, integrator: dict, camera=None):
    """The benchmark view: the volume in the unit cube, sun and sky light.
    ``camera``: ``(origin, target, fov)`` instead of the benchmark's
    (`zoom_camera`)."""
    T = mi.ScalarTransform4f
    origin, target, fov = camera or (BENCH_ORIGIN, BENCH_TARGET, BENCH_FOV)
    return {"type": "scene", "integrator": integrator,
            "sensor": {"type": "perspective", "fov": fov,
                       "to_world": T().look_at(list(origin), list(target), [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.55, 0.65]}},
            "sun": {"type": "directional", "direction": [-0.5, -1.0, -0.35],
                    "irradiance": {"type": "rgb", "value": 2.5}},
            "volume": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                       "bsdf": {"type": "null"}, "interior": medium}}


def check_alone(config):
    """Refuse to time ``config`` while amr media of another scene are alive:
    Dr.Jit dispatches virtual calls over every live instance, so a second
    scene in memory shifts timings (docs/design.md section 7)."""
    if live_media():
        raise RuntimeError(f"benchmark: {live_media()} amr media of another scene are alive while "
                           f"timing {config}; free them first")


def process_cpu_seconds() -> float:
    """CPU seconds used so far by every thread of this process."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def wait_idle(slice_s: float = 0.02, busy_share: float = 0.25, limit_s: float = 2.0) -> float:
    """Wait until this process is idle before a timed frame: slices of
    ``slice_s`` seconds until one uses less than ``busy_share`` of a core
    (a thread left spinning, e.g. OpenBLAS's workers after a BLAS call, takes
    a core from the render and slows the timed frame:
    docs/performance/frame-cost.md section 3), at most ``limit_s``. Idle
    means two slices in a row (on a loaded machine a spinning thread can
    miss one slice for want of a core). Returns the seconds waited; warns
    when the limit is hit."""
    t_start = time.perf_counter()
    idle = 0
    while True:
        c0, t0 = process_cpu_seconds(), time.perf_counter()
        time.sleep(slice_s)
        idle = idle + 1 if process_cpu_seconds() - c0 < busy_share * (time.perf_counter() - t0) else 0
        if idle == 2:
            return time.perf_counter() - t_start
        if time.perf_counter() - t_start > limit_s:
            print(f"benchmark: the process stayed busy for {limit_s:.1f} s before a timed frame "
                  "(a spinning thread?): timings may be slow", file=sys.stderr, flush=True)
            return time.perf_counter() - t_start


#: Untimed frames of a frozen render before the timed one: the recording,
#: the second recording Mitsuba's state after a first frame asks for, and
#: one replay.
FROZEN_WARMUP = 3


def frame_function(mi, spp: int, frozen: bool):
    """``frame(scene, seed)``: one frame of ``spp`` samples per pixel as a
    float64 array, rendered by ``mi.render`` or, with ``frozen``, by a
    ``dr.freeze``-recorded ``mi.render`` (what an interactive viewer runs:
    the kernels are replayed without tracing Python and Mitsuba calls
    again; the same image for the same seed). A frozen ``frame.recorder``
    is the frozen function (its ``n_recordings``)."""
    if not frozen:
        return lambda scene, seed: np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)

    @dr.freeze
    def render(scene, seed):
        return mi.render(scene, spp=spp, seed=seed)

    def frame(scene, seed):
        return np.array(render(scene, dr.opaque(mi.UInt32, seed)), dtype=np.float64)
    frame.recorder = render
    return frame


def write_report(out_dir, name: str, result: dict, report: str) -> None:
    """A benchmark's result as ``NAME.json`` and its Markdown report as
    ``NAME.md`` in ``out_dir`` (made if missing); the report is printed."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{name}.json").write_text(json.dumps(result, indent=1, default=float))
    (out_dir / f"{name}.md").write_text(report)
    print(report)
