"""yt's volume renderer against ``ray_march`` and ``emission_absorption`` at
equal error (docs/performance/vs-yt.md): ``python -m mi_amr.bench --vs-yt
[DATA ...] [--field F] --out DIR``.

DATA: ``blocks`` and ``cells`` (the bench's own two-level data set, loaded
into yt with `yt.load_amr_grids`; the default), ``enzo-example`` (the
Enzo-format output of `mi_amr.data.enzo_example`, written into the output
folder) or any output yt loads (``--field``, default ``density``). Each is
loaded into yt and into mi-amr from yt (`mi_amr.from_yt`: the same cells),
both render it with one TF (plasma colours, varying opacity, 256 entries;
over log10 values on both sides where the plan of `mi_amr.plan_scene`
takes log10: yt's ``log_field`` with its bounds in log10, ours over the
medium's values after the same transform), the same plane-parallel camera
and a constant background, and every image is compared with one reference:
the exact emission-absorption integral of the nearest field,
`mi_amr.reference.emission_absorption_march` with ``steps=None`` (an exact
voxel walk) of the box-filtered pixels (``SUB`` x ``SUB`` rays each) and of
the pixel centres (yt's rays).

yt's volume-render sampler interpolates trilinearly between vertex values
it averages from the cells, which our ``nearest`` medium does not: on
``blocks`` (every yt grid holds one value) the two fields are the same, on
any other data yt renders another, smoother field, and its RMSE against the
nearest reference is the target error of ours. yt's model, read in
``yt/utilities/lib/field_interpolation_tables.pxd`` (``FIT_eval_transfer``)
and ``image_samplers.pyx`` (``VolumeRenderSampler``): ``dt`` is in the ray's
parameter ``t``, which spans ``width[2]`` from the back plane for the
plane-parallel lens, so an alpha table ``a`` absorbs ``a / width[2]`` per
unit length, and a colour table ``c`` emits ``c a / width[2]`` (the colour
tables are weighted by the alpha table); the tables hold ``width[2] *
density_scale * alpha`` (``width[2]`` in units of the domain's longest side)
and ``brightness * rgb``. Values on or outside the table's bounds get 0, so
the TF's bounds lie just outside the data's values.

Ours: ``ray_march`` (nearest: exact per ray; what is left is the pixel
footprint) with centred strata (Mitsuba's ``stratified`` sampler without
jitter: 1 spp is the pixel centre, yt's ray; ``k^2`` spp a ``k`` x ``k``
grid), and ``emission_absorption`` (Woodcock tracking, ``independent``
sampler) as before; the time to yt's RMSE is interpolated in log spp.
"""

from __future__ import annotations

import gc
import hashlib
import json
import math
import os
import statistics
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..autoscene import plan_scene
from ..data.enzo_example import write_example
from ..data.transform import apply_value_transform
from ..data.yt_import import from_yt, load_dataset, resolve_field
from ..reference import emission_absorption_march
from ..transfer.function import TransferFunction
from ..visibility import box_chords
from .harness import check_alone, process_cpu_seconds, wait_idle

#: Cells per side of one yt grid (each holds one value in ``blocks``).
BLOCK = 4
#: Reference rays per pixel side (the box filter's footprint).
SUB = 4
#: The view, in units of the domain's longest side ``L`` from its lower
#: corner (the bench's data: the unit cube): plane-parallel, looking at the
#: domain centre from ``centre + OFFSET``.
OFFSET = np.array([1.7, 1.1, 2.3])
NORTH = np.array([0.0, 0.0, 1.0])
WIDTH = 1.8                                    # yt's image width (units of L)
DEPTH = 3.0                                    # yt's width[2]: the ray length (units of L)
BACKGROUND = np.array([0.3, 0.35, 0.45])
DENSITY, BRIGHTNESS = 8.0, 1.5                 # density_scale per L
TF_ENTRIES = 256
FIELD = ("stream", "density")
#: The bench's own data sets (`block_grids`) and the Enzo-format example.
OWN = ("blocks", "cells")
ENZO_EXAMPLE = "enzo-example"
RENDERERS = ("yt", "ray_march", "emission_absorption")
#: Mitsuba samplers of the ray marcher's pixel footprint (``--vs-yt-sampler``):
#: ``centres``: stratified without jitter (1 spp: the pixel centre).
SAMPLERS = ("centres", "multijitter", "stratified", "independent")


# ---- The data and its TF ------------------------------------------------


def tf_of(domain=(0.0, TF_ENTRIES - 1.0)):
    """Our TF: plasma colours, opacity that varies, over ``domain`` (the
    bench's data: values 0..255, the nodes at the integers)."""
    return TransferFunction.from_colormap("plasma", [(0.0, 0.0), (0.3, 0.1), (0.7, 0.9), (1.0, 0.4)],
                                          tuple(float(x) for x in domain), n=TF_ENTRIES)


def block_grids(n0: int = 32, seed: int = 0, kind: str = "blocks") -> list[dict]:
    """Grids of `yt.load_amr_grids` on [0, 1]^3: level 0 of ``n0``^3 cells,
    level 1 over [0.25, 0.75]^3 (``n0``^3 cells of half the size), each
    grid ``BLOCK``^3 cells. Values are integers in [1, 254] (TF nodes, never
    its bounds) from a smooth field plus noise; ``kind="blocks"``: one value
    per grid (yt's interpolation is then exact), ``"cells"``: one per cell."""
    rng = np.random.default_rng(seed)
    c = 0.5 + rng.uniform(-0.12, 0.12, 3)

    def field(x):                                          # x: (..., 3) positions
        r2 = ((x - c) ** 2).sum(-1)
        v = 250 * np.exp(-7 * r2) + 25 * rng.random(x.shape[:-1])
        return np.clip(np.round(v), 1, TF_ENTRIES - 2).astype(np.float64)

    grids = []
    for level, lo, hi in ((0, 0.0, 1.0), (1, 0.25, 0.75)):
        nb = n0 // BLOCK
        w = (hi - lo) / nb
        for ijk in np.ndindex(nb, nb, nb):
            le = lo + w * np.array(ijk)
            if kind == "blocks":
                data = np.full((BLOCK,) * 3, field(le + 0.5 * w))
            else:
                g = (np.arange(BLOCK) + 0.5) * w / BLOCK
                x = np.stack(np.meshgrid(*(le[i] + g for i in range(3)), indexing="ij"), -1)
                data = field(x)
            grids.append(dict(left_edge=le.tolist(), right_edge=(le + w).tolist(), level=level,
                              dimensions=[BLOCK] * 3, density=data))
    return grids


def load_yt(grids, n0: int):
    import yt
    yt.set_log_level(40)
    return yt.load_amr_grids(grids, [n0] * 3, bbox=np.array([[0.0, 1.0]] * 3))


@dataclass
class Case:
    """One data set on both sides: yt's ``ds`` and ``field`` (a yt field
    tuple), our ``cells`` (values after ``log``'s log10, if any), the TF
    over those values, and the domain (code units; ``L`` its longest side,
    ``ext`` its extents over ``L``)."""
    name: str
    ds: object
    field: tuple
    cells: object
    tf: TransferFunction
    log: bool
    dle: np.ndarray
    L: float
    ext: np.ndarray
    load_s: float


def own_case(kind: str, n0: int, seed: int = 0) -> Case:
    """The bench's two-level data set (`block_grids`): the linear TF `tf_of`."""
    t0 = time.perf_counter()
    ds = load_yt(block_grids(n0, seed, kind), n0)
    cells = from_yt(ds, FIELD)
    return Case(kind, ds, FIELD, cells, tf_of(), False, np.zeros(3), 1.0, np.ones(3),
                time.perf_counter() - t0)


def output_case(path, field: str, name: str | None = None) -> Case:
    """An output yt loads (`mi_amr.data.yt_import.load_dataset`), ``field``
    from yt (`from_yt`); log10 on both sides where `mi_amr.plan_scene`
    plans it, and `tf_of` over the (transformed) values' whole range,
    widened by 1e-3 of it on each side (yt gives 0 on and past its bounds,
    ours clamps: no value lies there)."""
    import yt
    yt.set_log_level(40)
    t0 = time.perf_counter()
    ds = load_dataset(path)
    key = resolve_field(ds, field)
    cells = from_yt(ds, key)
    log = plan_scene(cells).transform == "log10"
    if log:
        cells, _ = apply_value_transform(cells, "log10")
    lo, hi = cells.value_range
    pad = 1e-3 * max(hi - lo, 1e-6 * max(abs(lo), 1.0))
    dle = np.asarray(ds.domain_left_edge.to("code_length").d, np.float64)
    size = np.asarray(ds.domain_right_edge.to("code_length").d, np.float64) - dle
    L = float(size.max())
    return Case(name or Path(path).name, ds, key, cells, tf_of((lo - pad, hi + pad)), log, dle, L, size / L,
                time.perf_counter() - t0)


# ---- The view -----------------------------------------------------------
# Our scene lives in units of L from the domain's lower corner (the
# domain: [0, ext]); yt's camera is the same in code units.


def focus_of(case: Case) -> np.ndarray:
    return 0.5 * case.ext


def position_of(case: Case) -> np.ndarray:
    return focus_of(case) + OFFSET


def yt_tf(tf, density_scale: float, brightness: float):
    """yt's `ColorTransferFunction` of Max's model for ``tf``: tables at our
    nodes, alpha ``DEPTH * density_scale * alpha`` (per unit ``t``; one ``t``
    is ``DEPTH`` long), rgb ``brightness * rgb`` (yt weights each colour
    table by the alpha table: emission ``r(v) a(v)``, as ours); grey
    opacity."""
    from yt.visualization.volume_rendering.api import ColorTransferFunction
    ytf = ColorTransferFunction(tf.domain, nbins=len(tf), grey_opacity=True)
    a = DEPTH * density_scale * tf.rgba[:, 3].astype(np.float64)
    for k, ch in enumerate((ytf.red, ytf.green, ytf.blue)):
        ch.y[:] = brightness * tf.rgba[:, k].astype(np.float64)
    ytf.alpha.y[:] = a
    return ytf


def yt_scene(case: Case, res: int, density_scale: float = DENSITY, brightness: float = BRIGHTNESS,
             num_samples: int | None = None):
    """yt's scene: one volume source (``case.field``, log10 where the case
    is, our TF) and a plane-parallel camera of ``res``^2 rays."""
    from yt.visualization.volume_rendering.api import Scene, create_volume_source
    ds = case.ds
    sc = Scene()
    src = create_volume_source(ds.all_data(), case.field)
    src.log_field = case.log
    src.transfer_function = yt_tf(case.tf, density_scale, brightness)
    if num_samples:
        src.num_samples = num_samples
    sc.add_source(src)
    cam = sc.add_camera(ds, lens_type="plane-parallel")
    cam.resolution = (res, res)
    cam.set_width(ds.arr([WIDTH * case.L, WIDTH * case.L, DEPTH * case.L], "code_length"))
    cam.focus = ds.arr(case.dle + case.L * focus_of(case), "code_length")
    cam.set_position(ds.arr(case.dle + case.L * position_of(case), "code_length"), north_vector=NORTH)
    return sc


def yt_image(sc, background=BACKGROUND) -> tuple[np.ndarray, np.ndarray]:
    """``sc.render()`` in our image layout (rows down): rgb over
    ``background`` (H, W, 3) and yt's alpha, ``1 - T`` (H, W). yt's final
    image ``F[a, b]`` lies at ``-east * a - north * b`` (its raw image turned
    by 180 degrees)."""
    im = np.asarray(sc.render(), dtype=np.float64).transpose(1, 0, 2)[:, ::-1]
    return im[..., :3] + (1.0 - im[..., 3:4]) * background, im[..., 3]


def our_view(case: Case, res: int, sampler: dict | None = None):
    """Our orthographic sensor on yt's rays: yt composites along its
    ``normal = focus - position`` with the far end on top, which is the view
    from the mirrored position ``2 focus - position``; yt's rays span
    ``WIDTH`` edge to edge (spacing ``WIDTH / (res - 1)``), our pixel
    centres ``WIDTH * res / (res - 1)``."""
    T = mi.ScalarTransform4f
    w = WIDTH * res / (res - 1)
    focus = focus_of(case)
    origin = 2 * focus - position_of(case)
    sensor = {"type": "orthographic",
              "to_world": T().look_at(origin.tolist(), focus.tolist(), NORTH.tolist()) @ T().scale([w / 2, w / 2, 1]),
              "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                       "pixel_format": "rgb"}}
    if sampler:
        sensor["sampler"] = sampler
    return sensor


def sampler_dict(name: str) -> dict:
    """Mitsuba's sampler for ``--vs-yt-sampler`` (the sample count is the
    render's ``spp``)."""
    if name == "centres":
        return {"type": "stratified", "jitter": False}
    return {"type": name}


def our_scene_dict(case: Case, res: int, density_scale: float = DENSITY, brightness: float = BRIGHTNESS):
    """The scene of ``emission_absorption`` (independent sampler): the data
    in a box ``[0, ext]`` (units of L), nearest reconstruction."""
    T = mi.ScalarTransform4f
    half = (0.5 * case.ext).tolist()
    return {"type": "scene",
            "integrator": {"type": "amrvolpath", "mode": "emission_absorption", "brightness": brightness},
            "sensor": our_view(case, res),
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": BACKGROUND.tolist()}},
            "cube": {"type": "cube", "to_world": T().translate(half) @ T().scale(half),
                     "bsdf": {"type": "null"},
                     "interior": {"type": "amr", "data": case.cells, "transfer_function": case.tf,
                                  "density_scale": density_scale, "reconstruction": "nearest"}}}


def march_integrator(brightness: float = BRIGHTNESS, counters: bool = False):
    """``amrvolpath`` in ``ray_march`` mode, flat shading (the medium's
    ``nearest``: exact per ray)."""
    return mi.load_dict({"type": "amrvolpath", "mode": "ray_march", "brightness": brightness,
                         "counters": counters})


# ---- The reference ------------------------------------------------------


def sensor_rays(scene, res: int, sub: int):
    """``sub`` x ``sub`` stratified rays per pixel from the scene's sensor
    (``sub=1``: the pixel centres), pixels row by row: (origins, dirs)."""
    n = res * sub
    idx = dr.arange(mi.UInt32, n * n)
    pos = mi.Point2f((mi.Float(idx % n) + 0.5) / n, (mi.Float(idx // n) + 0.5) / n)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    o, d = [np.stack([np.asarray(c, np.float64) for c in (v.x, v.y, v.z)], axis=1) for v in (ray.o, ray.d)]
    return o, np.broadcast_to(d, o.shape)                        # an orthographic sensor's d is one literal


def exact_march(case: Case, tf, o, d, background, brightness, density_scale=DENSITY) -> np.ndarray:
    """`emission_absorption_march` with ``steps=None`` (the exact voxel
    walk) of rays ``(o, d)`` in our scene (units of L): in the medium's unit
    cube they are ``o / ext`` and ``d / ext`` (``t`` keeps its length, in
    L). Only the rays that meet the domain are walked (the others see the
    background), in chunks of about 2^22 voxel-face crossings, two threads."""
    o_u, d_u = o / case.ext, d / case.ext
    t0, t1 = box_chords(o_u, d_u, 0.0, 1.0)
    hit = np.flatnonzero(t1 > t0)
    out = np.broadcast_to(np.asarray(background, np.float64), (len(o), 3)).copy()
    cells = case.cells
    span = (cells.pos + (1 << cells.level.astype(np.int64))[:, None]).max(0) - cells.pos.min(0)
    faces = int(span.sum()) + 3                                   # voxel-face planes a ray may cross
    chunk = max(256, (1 << 22) // faces)
    bg = np.asarray(background, np.float64)

    def walk(s):
        k = hit[s:s + chunk]
        return k, emission_absorption_march(case.cells, tf, density_scale, o_u[k], d_u[k], bg, brightness, None)

    with ThreadPoolExecutor(2) as pool:
        for k, L in pool.map(walk, range(0, len(hit), chunk)):
            out[k] = L
    return out


def references(case: Case, scene, res: int, sub: int = SUB, cache: Path | None = None):
    """The exact march of the box-filtered pixels (``sub``^2 rays each) and
    of the pixel centres, and ``1 - T`` of the centres: (H, W, 3) each;
    kept in ``cache`` (a folder) under a digest of everything they depend on."""
    key = None
    if cache is not None:
        h = hashlib.sha256()
        for part in (case.cells.pos, case.cells.level, case.cells.values, case.tf.rgba,
                     np.array(case.tf.domain), case.ext, OFFSET, np.array([res, sub, WIDTH, DENSITY, BRIGHTNESS]),
                     BACKGROUND):
            h.update(np.ascontiguousarray(part).tobytes())
        key = Path(cache) / f"ref-{case.name}-{res}-{sub}-{h.hexdigest()[:16]}.npz"
        if key.exists():
            z = np.load(key)
            return z["box"], z["centre"], z["opacity"]
    out = []
    for s in (sub, 1):
        o, d = sensor_rays(scene, res, s)
        img = exact_march(case, case.tf, o, d, BACKGROUND, BRIGHTNESS)
        out.append(img.reshape(res, s, res, s, 3).mean(axis=(1, 3)))
    o, d = sensor_rays(scene, res, 1)
    opacity = 1.0 - exact_march(case, case.tf, o, d, np.ones(3), 0.0)
    box, centre, opacity = out[0], out[1], opacity.reshape(res, res, 3)
    if key is not None:
        key.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(key, box=box, centre=centre, opacity=opacity)
    return box, centre, opacity


# ---- Errors and placement -----------------------------------------------


def rmse(img, ref) -> float:
    return float(np.sqrt(np.mean((np.asarray(img) - ref) ** 2)))


def centroid(w) -> np.ndarray:
    """Weighted centroid (row, column) in pixels of a (H, W) image."""
    r, c = np.indices(w.shape)
    return np.array([(w * r).sum(), (w * c).sum()]) / w.sum()


def corner_pixels(case: Case, res: int) -> dict:
    """Pixel (column, row) of the domain's eight corners, by yt's formula
    (the ray of final-image index ``a`` lies at ``-east * px(a)``, ``px(a) =
    WIDTH a / (res - 1) - WIDTH / 2``) and by our sensor's transform: the
    same number where the cameras agree."""
    focus = focus_of(case)
    normal = focus - position_of(case)
    normal /= np.linalg.norm(normal)
    north = NORTH - NORTH.dot(normal) * normal
    north /= np.linalg.norm(north)
    east = np.cross(north, normal)
    corners = np.array(list(np.ndindex(2, 2, 2)), dtype=np.float64) * case.ext
    rel = corners - focus
    a = (-rel @ east + WIDTH / 2) * (res - 1) / WIDTH              # yt's final index along -east
    b = (-rel @ north + WIDTH / 2) * (res - 1) / WIDTH
    yt_cr = np.stack([res - 1 - a, b], 1) + 0.5                     # in our layout (column, row), pixel units
    to_cam = mi.ScalarTransform4f(our_view(case, res)["to_world"]).inverse()
    ours = []
    for p in corners:
        q = to_cam @ mi.ScalarPoint3f(*p)                          # camera space: x left, y up, in [-1, 1]
        ours.append([(0.5 - 0.5 * q[0]) * res, (0.5 - 0.5 * q[1]) * res])
    return {"yt": yt_cr.tolist(), "ours": ours, "max_diff_px": float(np.abs(yt_cr - np.array(ours)).max())}


# ---- Time to an error ---------------------------------------------------


def log_interp(x, xs, ys) -> float:
    """``y`` at ``x`` by linear interpolation in log-log of increasing
    ``xs`` (nan outside)."""
    lx, ly = np.log(xs), np.log(ys)
    if not (lx[0] <= math.log(x) <= lx[-1]):
        return float("nan")
    return float(np.exp(np.interp(math.log(x), lx, ly)))


def time_to(err: float, spps, errs, times, extrapolate: bool = True) -> dict:
    """spp and seconds at which our error reaches ``err``: the first
    crossing, interpolated in log spp (error and time both log-linear
    between the measured points). Past the last point (the cap) it is
    extrapolated when ``extrapolate`` (RMSE ``c / sqrt(spp)`` fitted to the
    last three points, time ``t_last * spp / spp_last``; ``extrapolated``
    says so), else nan."""
    if errs[0] <= err:
        return {"spp": float(spps[0]), "s": float(times[0]), "extrapolated": False}
    for k in range(1, len(spps)):
        if errs[k] <= err <= errs[k - 1]:
            f = (math.log(errs[k - 1]) - math.log(err)) / (math.log(errs[k - 1]) - math.log(errs[k]))
            lspp = (1 - f) * math.log(spps[k - 1]) + f * math.log(spps[k])
            return {"spp": float(math.exp(lspp)), "s": log_interp(math.exp(lspp), spps, times),
                    "extrapolated": False}
    if not extrapolate:
        return {"spp": float("nan"), "s": float("nan"), "extrapolated": False}
    c = float(np.median([e * math.sqrt(n) for n, e in zip(spps[-3:], errs[-3:])]))
    spp = (c / err) ** 2
    return {"spp": spp, "s": float(times[-1]) * spp / spps[-1], "extrapolated": True}


def ea_spps(cap: int, res: int) -> list[int]:
    """``emission_absorption``'s spp: 1, 2, 4, ... up to ``cap`` at 128^2,
    the cap scaled by ``(128 / res)^2`` beyond (at least 16): its error per
    spp hardly depends on the size, its time grows with the pixels."""
    top = max(16, cap * 128 * 128 // (res * res)) if res > 128 else cap
    return [1 << k for k in range(int(math.log2(top)) + 1)]


def march_spps(cap: int) -> list[int]:
    """The ray marcher's spp: squares 1, 4, 16, ... up to ``cap`` (a
    stratified sampler's counts)."""
    out, k = [], 1
    while k * k <= cap:
        out.append(k * k)
        k *= 2
    return out


# ---- One (data, size) ---------------------------------------------------


def run_case(case: Case, res: int, ea_spp, rm_spp, rounds: int, sampler: str = "centres", sub: int = SUB,
             num_samples=None, cache: Path | None = None) -> list[dict]:
    """yt, ``ray_march`` and ``emission_absorption`` at ``res``^2:
    ``rounds`` alternated rounds (yt, then ours at each spp; each timed call
    waits until the process is idle); three records (`record`)."""
    check_alone(f"vs-yt {case.name} {res}")
    scene = mi.load_dict(our_scene_dict(case, res))
    t0 = time.perf_counter()
    ref_box, ref_centre, opacity = references(case, scene, res, sub, cache)
    ref_s = time.perf_counter() - t0
    mean = float(ref_box.mean())
    sc = yt_scene(case, res, num_samples=num_samples)
    t0 = time.perf_counter()
    yt_img, yt_alpha = yt_image(sc)                                # builds the kd-tree and vertex data
    yt_first_s = time.perf_counter() - t0
    march = march_integrator()
    march_sensor = mi.load_dict(our_view(case, res, sampler_dict(sampler)))
    runs = {"emission_absorption": (list(ea_spp), dict()),
            "ray_march": (list(rm_spp), dict(integrator=march, sensor=march_sensor))}
    for spps, kw in runs.values():                                 # compile each spp's kernels
        for spp in spps:
            mi.render(scene, spp=spp, seed=0, **kw)
    yt_s, yt_cpu, yt_err = [], [], []
    meas = {r: {s: {"s": [], "cpu": [], "err": []} for s in runs[r][0]} for r in runs}
    for r in range(rounds):
        wait_idle()
        t0, c0 = time.perf_counter(), process_cpu_seconds()
        yt_img, yt_alpha = yt_image(sc)
        yt_s.append(time.perf_counter() - t0)
        yt_cpu.append(process_cpu_seconds() - c0)
        yt_err.append(rmse(yt_img, ref_box))
        for name, (spps, kw) in runs.items():
            for spp in spps:
                wait_idle()
                t0, c0 = time.perf_counter(), process_cpu_seconds()
                img = np.array(mi.render(scene, spp=spp, seed=1000 * r + spp, **kw), dtype=np.float64)
                meas[name][spp]["s"].append(time.perf_counter() - t0)
                meas[name][spp]["cpu"].append(process_cpu_seconds() - c0)
                meas[name][spp]["err"].append(rmse(img, ref_box))
    march_img = np.array(mi.render(scene, spp=1, seed=7, integrator=march, sensor=march_sensor), np.float64)
    med = statistics.median
    common = {"data": case.name, "size": res, "ref_mean": mean, "ref_sub": sub, "ref_s": ref_s,
              "load_s": case.load_s, "cells": int(len(case.cells.level)), "log10": case.log,
              "tf_domain": [float(x) for x in case.tf.domain]}
    yt_rmse = med(yt_err)
    placement = (centroid(yt_alpha) - centroid(opacity.mean(-1))).tolist()
    recs = [dict(common, renderer="yt", seconds=med(yt_s), rmse_over_mean=yt_rmse / mean,
                 seconds_all=yt_s, cpu_seconds=med(yt_cpu), rmse_over_mean_all=[e / mean for e in yt_err],
                 first_render_s=yt_first_s,
                 num_samples=int(sc.sources["source_00"].num_samples),
                 rmse_centre_over_mean=rmse(yt_img, ref_centre) / mean,
                 centre_vs_box_over_mean=rmse(ref_centre, ref_box) / mean,
                 placement_px=placement, corners=corner_pixels(case, res))]
    for name, (spps, _) in runs.items():
        errs = [med(meas[name][s]["err"]) for s in spps]
        times = [med(meas[name][s]["s"]) for s in spps]
        to_yt = time_to(yt_rmse, spps, errs, times, extrapolate=name == "emission_absorption")
        to_1 = time_to(0.01 * mean, spps, errs, times, extrapolate=name == "emission_absorption")
        k = next((i for i, e in enumerate(errs) if e <= yt_rmse), len(spps) - 1)
        rec = dict(common, renderer=name, spp=spps[k], seconds=times[k], rmse_over_mean=errs[k] / mean,
                   seconds_to_yt_rmse=to_yt["s"], spp_to_yt_rmse=to_yt["spp"],
                   extrapolated=to_yt["extrapolated"], to_yt_over_yt=to_yt["s"] / med(yt_s),
                   seconds_to_1pct=to_1["s"], spp_to_1pct=to_1["spp"], extrapolated_1pct=to_1["extrapolated"],
                   sampler="independent" if name == "emission_absorption" else sampler,
                   curve=[{"spp": s, "seconds": t, "rmse_over_mean": e / mean,
                           "seconds_min": min(meas[name][s]["s"]), "seconds_max": max(meas[name][s]["s"]),
                           "cpu_seconds": med(meas[name][s]["cpu"]),
                           "rmse_over_mean_min": min(meas[name][s]["err"]) / mean,
                           "rmse_over_mean_max": max(meas[name][s]["err"]) / mean}
                          for s, t, e in zip(spps, times, errs)])
        if name == "ray_march":
            rec["centre_rays_over_mean"] = rmse(march_img, ref_centre) / mean if sampler == "centres" else None
        recs.append(rec)
    del scene, march, march_sensor, sc
    gc.collect()
    dr.flush_malloc_cache()
    return recs


# ---- The command --------------------------------------------------------


def fmt_s(x) -> str:
    return "-" if x is None or not np.isfinite(x) else (f"{x * 1e3:.0f} ms" if x < 1 else f"{x:.1f} s")


def spread(vals) -> str:
    return f"{fmt_s(min(vals))}-{fmt_s(max(vals))}"


def write_table(records: list, out: Path, command: str, load: str = "") -> str:
    """``vs_yt.md``: one row per (data, size); returns the table."""
    lines = ["| data | size | yt render (min-max) | yt RMSE / mean | ray_march at 1 spp (min-max), RMSE / mean "
             "| ray_march to yt's RMSE: spp, s | / yt | emission_absorption to yt's RMSE: spp, s | / yt |",
             "|---|---|---|---|---|---|---|---|---|"]
    by = {}
    for r in records:
        by.setdefault((r["data"], r["size"]), {})[r["renderer"]] = r
    for (data, size), g in by.items():
        y, m, e = g["yt"], g["ray_march"], g["emission_absorption"]
        c0 = m["curve"][0]

        def to(r):
            star = "*" if r["extrapolated"] else ""
            if not np.isfinite(r["seconds_to_yt_rmse"]):
                return f"not within {r['curve'][-1]['spp']} spp", "-"
            return (f"{r['spp_to_yt_rmse']:.0f}{star}, {fmt_s(r['seconds_to_yt_rmse'])}{star}",
                    f"{r['to_yt_over_yt']:.3g}")
        mt, mr = to(m)
        et, er = to(e)
        lines.append(f"| {data} | {size}^2 | {fmt_s(y['seconds'])} ({spread(y['seconds_all'])}) | "
                     f"{100 * y['rmse_over_mean']:.3f}% | {fmt_s(c0['seconds'])} "
                     f"({fmt_s(c0['seconds_min'])}-{fmt_s(c0['seconds_max'])}), {100 * c0['rmse_over_mean']:.3f}% "
                     f"| {mt} | {mr} | {et} | {er} |")
    table = "\n".join(lines)
    (out / "vs_yt.md").write_text(f"`{command}`\n\n{load}\n\n{table}\n\n*: extrapolated past the cap "
                                  "(RMSE c / sqrt(spp), time linear in spp).\n")
    return table


def plot(records: list, path: Path) -> None:
    """Time against error (log-log), one panel per data set: yt's renders
    (each round), the ray marcher's and ``emission_absorption``'s curves
    over spp, one colour per size."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    datas = list(dict.fromkeys(r["data"] for r in records))
    sizes = sorted({r["size"] for r in records})
    colours = dict(zip(sizes, ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")))
    fig, axes = plt.subplots(1, len(datas), figsize=(5.2 * len(datas), 4.4), squeeze=False)
    for ax, data in zip(axes[0], datas):
        for r in (r for r in records if r["data"] == data):
            c = colours[r["size"]]
            if r["renderer"] == "yt":
                ax.scatter(r["seconds_all"], [100 * r["rmse_over_mean"]] * len(r["seconds_all"]), marker="*",
                           s=90, color=c, zorder=3, label=f"yt {r['size']}^2")
                continue
            xs = [p["seconds"] for p in r["curve"]]
            ys = [100 * p["rmse_over_mean"] for p in r["curve"]]
            style = "-o" if r["renderer"] == "ray_march" else "--s"
            ax.plot(xs, ys, style, color=c, ms=3, lw=1.2,
                    label=f"{'ray_march' if r['renderer'] == 'ray_march' else 'emission_abs.'} {r['size']}^2")
            ax.annotate(f"{r['curve'][0]['spp']}", (xs[0], ys[0]), fontsize=6, color=c)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("seconds per image")
        ax.set_ylabel("RMSE / mean of the exact integral (%)")
        ax.set_title(data)
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def json_safe(x):
    """``x`` with numpy numbers as Python's and nan/inf as None (strict JSON)."""
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def load_note() -> str:
    """The machine's load averages and core count now (one line)."""
    a = os.getloadavg()
    return f"load average {a[0]:.2f} {a[1]:.2f} {a[2]:.2f} on {os.cpu_count()} cores"


def open_case(data: str, field: str | None, n0: int, out: Path) -> Case:
    """``blocks``/``cells``, ``enzo-example`` (written under ``out``) or an
    output yt loads."""
    if data in OWN:
        return own_case(data, n0)
    if data == ENZO_EXAMPLE:
        path = out / "enzo-example" / "DD0018" / "DD0018"
        if not path.exists():
            path = write_example(out / "enzo-example")
        return output_case(path, field or "density", ENZO_EXAMPLE)
    return output_case(data, field or "density")


def omp_wait_policy() -> str:
    """``OMP_WAIT_POLICY`` of yt's OpenMP renderer: passive unless the
    environment says otherwise. yt's threads spin at their barriers under
    the active policy, and on a machine whose cores other processes share,
    a spinning thread holds the core its partner needs: a 128^2 render of
    the bench's data took 22-33 s at load 12 on 2 cores, 0.17-0.23 s
    passive (docs/performance/vs-yt.md). libgomp reads it once, when yt's
    renderer loads it: too late afterwards (said so)."""
    policy = os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    maps = Path("/proc/self/maps")
    if maps.exists() and "libgomp" in maps.read_text():
        policy += " (libgomp was loaded before: its own setting holds)"
    return policy


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--vs-yt [DATA ...]``)."""
    policy = omp_wait_policy()
    mi.set_variant(args.variant)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python -m mi_amr.bench " + " ".join(getattr(args, "argv", []) or ["--vs-yt"])
    datas = args.vs_yt or list(OWN)
    cache = Path(args.vs_yt_cache) if args.vs_yt_cache else out / "reference-cache"
    records, loads = [], [load_note()]
    print(f"yt's OMP_WAIT_POLICY: {policy}", flush=True)
    for data in datas:
        case = open_case(data, args.field, args.vs_yt_n0, out)
        sizes = args.vs_yt_res if data != "cells" else args.vs_yt_res[:1]
        for res in sizes:
            recs = run_case(case, res, ea_spps(args.vs_yt_cap, res), march_spps(args.vs_yt_march_cap),
                            args.vs_yt_rounds, args.vs_yt_sampler, args.vs_yt_sub, args.vs_yt_samples, cache)
            for r in recs:
                r["omp_wait_policy"] = policy
            records += recs
            loads.append(load_note())
            y, m, e = (next(r for r in recs if r["renderer"] == n) for n in RENDERERS)
            print(f"{data:12s} {res:4d}^2: yt {fmt_s(y['seconds'])} RMSE {100 * y['rmse_over_mean']:.3f}% of mean; "
                  f"ray_march to it {fmt_s(m['seconds_to_yt_rmse'])} ({m['spp_to_yt_rmse']:.0f} spp, "
                  f"{m['to_yt_over_yt']:.2f} of yt); emission_absorption {fmt_s(e['seconds_to_yt_rmse'])} "
                  f"({e['spp_to_yt_rmse']:.0f} spp{', extrapolated' if e['extrapolated'] else ''}); "
                  f"placement {y['corners']['max_diff_px']:.1e} px; {loads[-1]}", flush=True)
            (out / "vs_yt.json").write_text(json.dumps(json_safe(records), indent=1))
        del case
        gc.collect()
    note = "Load: " + "; ".join(loads) + "."
    print(write_table(records, out, command, note))
    plot(records, out / "vs_yt.png")
    print(f"wrote {out}/vs_yt.json, vs_yt.md and vs_yt.png ({note})")
    return 0
