"""yt's volume renderer as a second witness of ``emission_absorption``, and
our time to its error (docs/performance/vs-yt.md): ``python -m mi_amr.bench
--vs-yt --out DIR``.

One two-level AMR data set is loaded into yt (`yt.load_amr_grids`) and into
mi-amr from yt (`mi_amr.from_yt`): the same cells. yt's volume-render
sampler interpolates trilinearly between vertex values it averages from the
cells, which our ``nearest`` medium does not; on a data set whose grids each
hold one value (``blocks``: every yt grid is 4^3 cells of one value, on TF
nodes) the two fields are the same, and so are the TFs (yt's table nodes are
ours). What is left of yt's model against Max's integral: its first-order
step ``rgba = dt e + (1 - dt a) rgba`` over ``num_samples`` sub-steps per cell
(not ``exp``) and one ray per pixel (ours: the pixel's box filter). Both are
rendered with the same plane-parallel camera and compared with
`mi_amr.reference.emission_absorption_march` of the box-filtered
pixels (4 x 4 rays each) and of the pixel-centre rays (yt's rays).

yt's model, read in ``yt/utilities/lib/field_interpolation_tables.pxd``
(``FIT_eval_transfer``) and ``image_samplers.pyx`` (``VolumeRenderSampler``):
``dt`` is in the ray's parameter ``t``, which spans ``width[2]`` from the
back plane for the plane-parallel lens, so an alpha table ``a`` absorbs
``a / width[2]`` per unit length, and a colour table ``c`` emits ``c a /
width[2]`` (the colour tables are weighted by the alpha table); the tables
hold ``width[2] * density_scale * alpha`` and ``brightness * rgb``. Values on or outside the table's bounds get 0.
"""

from __future__ import annotations

import gc
import json
import math
import statistics
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..data.yt_import import from_yt
from ..reference import emission_absorption_march
from ..transfer.function import TransferFunction
from .harness import check_alone, wait_idle

#: Cells per side of one yt grid (each holds one value in ``blocks``).
BLOCK = 4
#: Reference rays per pixel side (the box filter's footprint).
SUB = 4
#: The view: plane-parallel along this axis, looking at the domain centre.
FOCUS = np.array([0.5, 0.5, 0.5])
POSITION = np.array([2.2, 1.6, 2.8])          # yt's camera position (code_length)
NORTH = np.array([0.0, 0.0, 1.0])
WIDTH = 1.8                                    # yt's image width (code_length)
DEPTH = 3.0                                    # yt's width[2]: the ray length
BACKGROUND = np.array([0.3, 0.35, 0.45])
DENSITY, BRIGHTNESS = 8.0, 1.5
TF_ENTRIES = 256
FIELD = ("stream", "density")


# ---- The data and its TF ------------------------------------------------


def tf_of():
    """Our TF: plasma colours, opacity that varies, over values 0..255 (its
    nodes are the integers)."""
    return TransferFunction.from_colormap("plasma", [(0.0, 0.0), (0.3, 0.1), (0.7, 0.9), (1.0, 0.4)],
                                          (0.0, TF_ENTRIES - 1.0), n=TF_ENTRIES)


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


# ---- yt's scene ---------------------------------------------------------


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


def yt_scene(ds, tf, res: int, density_scale: float = DENSITY, brightness: float = BRIGHTNESS,
             num_samples: int | None = None):
    """yt's scene: one volume source (linear field, our TF) and a
    plane-parallel camera of ``res``^2 rays."""
    from yt.visualization.volume_rendering.api import Scene, create_volume_source
    sc = Scene()
    src = create_volume_source(ds.all_data(), FIELD)
    src.log_field = False
    src.transfer_function = yt_tf(tf, density_scale, brightness)
    if num_samples:
        src.num_samples = num_samples
    sc.add_source(src)
    cam = sc.add_camera(ds, lens_type="plane-parallel")
    cam.resolution = (res, res)
    cam.set_width(ds.arr([WIDTH, WIDTH, DEPTH], "code_length"))
    cam.focus = ds.arr(FOCUS, "code_length")
    cam.set_position(ds.arr(POSITION, "code_length"), north_vector=NORTH)
    return sc


def yt_image(sc) -> tuple[np.ndarray, np.ndarray]:
    """``sc.render()`` in our image layout (rows down): rgb over
    ``BACKGROUND`` (H, W, 3) and yt's alpha, ``1 - T`` (H, W). yt's final
    image ``F[a, b]`` lies at ``-east * a - north * b`` (its raw image turned
    by 180 degrees)."""
    im = np.asarray(sc.render(), dtype=np.float64).transpose(1, 0, 2)[:, ::-1]
    return im[..., :3] + (1.0 - im[..., 3:4]) * BACKGROUND, im[..., 3]


# ---- Our scene ----------------------------------------------------------


def our_view(res: int):
    """Our orthographic sensor on yt's rays: yt composites along its
    ``normal = focus - position`` with the far end on top, which is the view
    from the mirrored position ``2 focus - position``; yt's rays span
    ``WIDTH`` edge to edge (spacing ``WIDTH / (res - 1)``), our pixel
    centres ``WIDTH * res / (res - 1)``."""
    T = mi.ScalarTransform4f
    w = WIDTH * res / (res - 1)
    origin = 2 * FOCUS - POSITION
    return {"type": "orthographic",
            "to_world": T().look_at(origin.tolist(), FOCUS.tolist(), NORTH.tolist()) @ T().scale([w / 2, w / 2, 1]),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"}}


def our_scene_dict(cells, tf, res: int, density_scale: float = DENSITY, brightness: float = BRIGHTNESS):
    T = mi.ScalarTransform4f
    return {"type": "scene",
            "integrator": {"type": "amrvolpath", "mode": "emission_absorption", "brightness": brightness},
            "sensor": our_view(res),
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": BACKGROUND.tolist()}},
            "cube": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                     "bsdf": {"type": "null"},
                     "interior": {"type": "amr", "data": cells, "transfer_function": tf,
                                  "density_scale": density_scale, "reconstruction": "nearest"}}}


def sensor_rays(scene, res: int, sub: int):
    """``sub`` x ``sub`` stratified rays per pixel from the scene's sensor
    (``sub=1``: the pixel centres), pixels row by row: (origins, dirs)."""
    n = res * sub
    idx = dr.arange(mi.UInt32, n * n)
    pos = mi.Point2f((mi.Float(idx % n) + 0.5) / n, (mi.Float(idx // n) + 0.5) / n)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    o, d = [np.stack([np.asarray(c, np.float64) for c in (v.x, v.y, v.z)], axis=1) for v in (ray.o, ray.d)]
    return o, np.broadcast_to(d, o.shape)                        # an orthographic sensor's d is one literal


def references(scene, cells, tf, res: int, steps: int, density_scale=DENSITY, brightness=BRIGHTNESS):
    """The dense march of the box-filtered pixels (``SUB``^2 rays each) and
    of the pixel centres, and ``1 - T`` of the centres: (H, W, 3) each."""
    out = []
    for sub in (SUB, 1):
        o, d = sensor_rays(scene, res, sub)
        img = np.concatenate([emission_absorption_march(cells, tf, density_scale, o[s:s + (1 << 18)],
                                                        d[s:s + (1 << 18)], BACKGROUND, brightness, steps)
                              for s in range(0, len(o), 1 << 18)])
        out.append(img.reshape(res, sub, res, sub, 3).mean(axis=(1, 3)))
    o, d = sensor_rays(scene, res, 1)
    opacity = 1.0 - emission_absorption_march(cells, tf, density_scale, o, d, 1.0, 0.0, steps)
    return out[0], out[1], opacity.reshape(res, res, 3)


# ---- Errors and placement -----------------------------------------------


def rmse(img, ref) -> float:
    return float(np.sqrt(np.mean((np.asarray(img) - ref) ** 2)))


def centroid(w) -> np.ndarray:
    """Weighted centroid (row, column) in pixels of a (H, W) image."""
    r, c = np.indices(w.shape)
    return np.array([(w * r).sum(), (w * c).sum()]) / w.sum()


def corner_pixels(res: int) -> dict:
    """Pixel (column, row) of the domain's eight corners, by yt's formula
    (the ray of final-image index ``a`` lies at ``-east * px(a)``, ``px(a) =
    WIDTH a / (res - 1) - WIDTH / 2``) and by our sensor's transform: the
    same number where the cameras agree."""
    normal = FOCUS - POSITION
    normal /= np.linalg.norm(normal)
    north = NORTH - NORTH.dot(normal) * normal
    north /= np.linalg.norm(north)
    east = np.cross(north, normal)
    corners = np.array(list(np.ndindex(2, 2, 2)), dtype=np.float64)
    rel = corners - FOCUS
    a = (-rel @ east + WIDTH / 2) * (res - 1) / WIDTH              # yt's final index along -east
    b = (-rel @ north + WIDTH / 2) * (res - 1) / WIDTH
    yt_cr = np.stack([res - 1 - a, b], 1) + 0.5                     # in our layout (column, row), pixel units
    to_cam = mi.ScalarTransform4f(our_view(res)["to_world"]).inverse()
    ours = []
    for p in corners:
        q = to_cam @ mi.ScalarPoint3f(*p)                          # camera space: x left, y up, in [-1, 1]
        ours.append([(0.5 - 0.5 * q[0]) * res, (0.5 - 0.5 * q[1]) * res])
    return {"yt": yt_cr.tolist(), "ours": ours, "max_diff_px": float(np.abs(yt_cr - np.array(ours)).max())}


# ---- The study ----------------------------------------------------------


def log_interp(x, xs, ys) -> float:
    """``y`` at ``x`` by linear interpolation in log-log of increasing
    ``xs`` (nan outside)."""
    lx, ly = np.log(xs), np.log(ys)
    if not (lx[0] <= math.log(x) <= lx[-1]):
        return float("nan")
    return float(np.exp(np.interp(math.log(x), lx, ly)))


def time_to(err: float, spps, errs, times) -> dict:
    """spp and seconds at which our error reaches ``err``: the first
    crossing, interpolated in log spp (error and time both log-linear
    between the measured points). Past the last point (the cap) it is
    extrapolated: RMSE ``c / sqrt(spp)`` fitted to the last three points,
    time ``t_last * spp / spp_last``; ``extrapolated`` says so."""
    if errs[0] <= err:
        return {"spp": float(spps[0]), "s": float(times[0]), "extrapolated": False}
    for k in range(1, len(spps)):
        if errs[k] <= err <= errs[k - 1]:
            f = (math.log(errs[k - 1]) - math.log(err)) / (math.log(errs[k - 1]) - math.log(errs[k]))
            lspp = (1 - f) * math.log(spps[k - 1]) + f * math.log(spps[k])
            return {"spp": float(math.exp(lspp)), "s": log_interp(math.exp(lspp), spps, times),
                    "extrapolated": False}
    c = float(np.median([e * math.sqrt(n) for n, e in zip(spps[-3:], errs[-3:])]))
    spp = (c / err) ** 2
    return {"spp": spp, "s": float(times[-1]) * spp / spps[-1], "extrapolated": True}


def run_case(res: int, n0: int, kind: str, spps, rounds: int, steps: int, num_samples=None,
             seed: int = 0) -> dict:
    """One row: yt and ours at ``res``^2, ``rounds`` alternated rounds."""
    check_alone(f"vs-yt {kind} {res}")
    tf = tf_of()
    t0 = time.perf_counter()
    ds = load_yt(block_grids(n0, seed, kind), n0)
    cells = from_yt(ds, FIELD)
    load_s = time.perf_counter() - t0
    scene = mi.load_dict(our_scene_dict(cells, tf, res))
    t0 = time.perf_counter()
    ref_box, ref_centre, opacity = references(scene, cells, tf, res, steps)
    ref_s = time.perf_counter() - t0
    mean = float(ref_box.mean())
    sc = yt_scene(ds, tf, res, num_samples=num_samples)
    t0 = time.perf_counter()
    yt_img, yt_alpha = yt_image(sc)                                # builds the kd-tree and vertex data
    yt_first_s = time.perf_counter() - t0
    for spp in spps:                                               # compile each spp's kernels
        mi.render(scene, spp=spp, seed=0)
    yt_s, yt_err, ours = [], [], {s: {"s": [], "err": []} for s in spps}
    for r in range(rounds):
        wait_idle()
        t0 = time.perf_counter()
        yt_img, yt_alpha = yt_image(sc)
        yt_s.append(time.perf_counter() - t0)
        yt_err.append(rmse(yt_img, ref_box))
        for spp in spps:
            wait_idle()
            t0 = time.perf_counter()
            img = np.array(mi.render(scene, spp=spp, seed=1000 * r + spp), dtype=np.float64)
            ours[spp]["s"].append(time.perf_counter() - t0)
            ours[spp]["err"].append(rmse(img, ref_box))
    med = statistics.median
    spp_list = list(spps)
    errs = [med(ours[s]["err"]) for s in spp_list]
    times = [med(ours[s]["s"]) for s in spp_list]
    yt_rmse = med(yt_err)
    placement = (centroid(yt_alpha) - centroid(opacity.mean(-1))).tolist()
    rec = {
        "kind": kind, "res": res, "cells": int(len(cells.level)), "grids": len(ds.index.grids),
        "load_s": load_s, "ref_s": ref_s, "ref_steps": steps, "ref_mean": mean,
        "yt_num_samples": int(sc.sources["source_00"].num_samples),
        "yt_first_s": yt_first_s, "yt_s": yt_s, "yt_s_median": med(yt_s),
        "yt_rmse": yt_rmse, "yt_rmse_rel": yt_rmse / mean,
        "yt_rmse_centre": rmse(yt_img, ref_centre), "yt_rmse_centre_rel": rmse(yt_img, ref_centre) / mean,
        "centre_vs_box_rel": rmse(ref_centre, ref_box) / mean,
        "placement_px": placement, "corners": corner_pixels(res),
        "spp": spp_list, "ours_rmse": errs, "ours_s": times,
        "ours_s_spread": [[min(ours[s]["s"]), max(ours[s]["s"])] for s in spp_list],
        "ours_rmse_spread": [[min(ours[s]["err"]), max(ours[s]["err"])] for s in spp_list],
    }
    rec["to_yt_error"] = time_to(yt_rmse, spp_list, errs, times)
    rec["to_1pct"] = time_to(0.01 * mean, spp_list, errs, times)
    rec["ours_vs_yt"] = rec["to_yt_error"]["s"] / rec["yt_s_median"]
    del scene
    gc.collect()
    dr.flush_malloc_cache()
    return rec


# ---- The command --------------------------------------------------------


def fmt_s(x: float) -> str:
    return "-" if not np.isfinite(x) else (f"{x * 1e3:.0f} ms" if x < 1 else f"{x:.1f} s")


def write_table(records: list, out: Path, command: str) -> str:
    """``vs_yt.md``: one row per case; returns the table."""
    lines = ["| data | size | yt first render | yt render (min-max) | yt RMSE / mean (box; centre rays) "
             "| ours at 1 spp | ours RMSE / mean at cap (spp) | ours to yt's RMSE: spp, s | ours / yt "
             "| ours to 1% of mean: spp, s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        def to(t):
            star = "*" if t["extrapolated"] else ""
            return f"{t['spp']:.0f}{star}, {fmt_s(t['s'])}{star}"
        lines.append(
            f"| {r['kind']} | {r['res']}^2 | {fmt_s(r['yt_first_s'])} | {fmt_s(r['yt_s_median'])} "
            f"({fmt_s(min(r['yt_s']))}-{fmt_s(max(r['yt_s']))}) | {100 * r['yt_rmse_rel']:.3f}%; "
            f"{100 * r['yt_rmse_centre_rel']:.3f}% | {fmt_s(r['ours_s'][0])} | "
            f"{100 * r['ours_rmse'][-1] / r['ref_mean']:.2f}% ({r['spp'][-1]}) | {to(r['to_yt_error'])} | "
            f"{r['ours_vs_yt']:.3g}x | {to(r['to_1pct'])} |")
    table = "\n".join(lines)
    (out / "vs_yt.md").write_text(f"`{command}`\n\n{table}\n\n*: extrapolated past the cap "
                                  "(RMSE c / sqrt(spp), time linear in spp).\n")
    return table


def main_args(args) -> int:
    """Entry from `mi_amr.bench.__main__` (``--vs-yt``)."""
    mi.set_variant(args.variant)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python -m mi_amr.bench " + " ".join(getattr(args, "argv", []) or ["--vs-yt"])
    spps = [1 << k for k in range(int(math.log2(args.vs_yt_cap)) + 1)]
    records = []
    for kind in args.vs_yt_kinds:
        for res in (args.vs_yt_res if kind == "blocks" else args.vs_yt_res[:1]):
            rec = run_case(res, args.vs_yt_n0, kind, spps, args.vs_yt_rounds, args.vs_yt_steps,
                           num_samples=args.vs_yt_samples)
            records.append(rec)
            print(f"{kind:6s} {res:4d}^2: yt {fmt_s(rec['yt_s_median'])} RMSE {100 * rec['yt_rmse_rel']:.3f}% "
                  f"of mean; ours to it {fmt_s(rec['to_yt_error']['s'])} ({rec['to_yt_error']['spp']:.0f} spp"
                  f"{', extrapolated' if rec['to_yt_error']['extrapolated'] else ''}), to 1% "
                  f"{fmt_s(rec['to_1pct']['s'])}; placement {rec['corners']['max_diff_px']:.1e} px",
                  flush=True)
            (out / "vs_yt.json").write_text(json.dumps(records, indent=1, default=float))
    print(write_table(records, out, command))
    print(f"wrote {out}/vs_yt.json and vs_yt.md")
    return 0
