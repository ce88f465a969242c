"""Time against error of AMR rendering against dense resamples of the same data.

    python -m mi_amr.bench --resample [DATA ...] --out DIR

Answers "why not resample my AMR data to a dense grid and render that?".
For each data set (``cosmo:CELLS[:LEVELS]``, the synthetic cosmic web of
`mi_amr.data.datasets` written once into ``--data-dir``; ``enzo``, the
Enzo-format example of tools/make_enzo_example.py, read by yt; or a path
`mi-amr render` reads, with ``--field``) the scene is the one ``mi-amr
render`` plans (`mi_amr.autoscene.plan_scene`: log10 values for densities
spanning decades, its TF range and density scale) in the benchmark view
(`bench_scene`: the same camera and lights for every row).

* **truth**: the ``amr`` medium (default structures, ``nearest``: the cells
  as the piecewise-constant field a finite-volume code writes) in
  ``amrvolpath`` at ``truth_spp``, in two independent halves: the truth's
  own noise (mean squared) is ``mean((h1 - h2)^2) / 4`` and is taken off
  every error below.
* **rivals**: dense resamples at ``resolutions`` (voxels along the longest
  side), by ``box`` (the volume-weighted, mass-conserving average of the
  *linear* values over each voxel, what yt's covering grid gives on data
  whose parent cells hold their children's average; then log10) and
  optionally ``nearest`` (the cell under each voxel centre), each rendered
  by Mitsuba's ``heterogeneous`` + ``gridvolume`` (``nearest`` filter, the
  TF baked into sigma_t/albedo textures) and by ``dense16`` (the ``amr``
  medium on the resampled grid, one level, a 16^3 majorant grid). A rival
  whose memory estimate exceeds ``memory_limit`` is skipped and said so.
* **floor** of a rival: the RMSE of its high-spp image against the truth,
  with both images' noise taken off (its bias); **curves**: RMSE against
  render seconds at 1, 2, 4, ... spp (frames of more than `CHUNK_SPP`
  samples are `CHUNK_SPP`-sample frames summed), timed as the benchmark
  times (`frame_function`, frozen by default, `wait_idle`, one scene alive).
* **check**: where the finest-resolution dense grid fits (``check_max``),
  the nearest resample at the finest resolution in ``heterogeneous`` must
  equal the truth within noise: its measured MSE over the expected noise
  MSE (``check_ratio``) is about 1.

Writes ``resample.json``, ``resample.md`` and ``resample.png`` to ``out``.
Errors are RMSE of linear RGB radiance over the image.
"""

from __future__ import annotations

import gc
import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import mitsuba as mi
import numpy as np

from ..autoscene import plan_scene
from ..data.blocks import BlockVolume
from ..data.datasets import write_block_dataset
from ..data.transform import log10_values, positive_floor
from ..progress import progress
from ..transfer.function import TransferFunction
from .harness import FROZEN_WARMUP, bench_scene, check_alone, frame_function, wait_idle, zoom_camera

DEFAULT_DATA = ("enzo", "cosmo:1e7", "cosmo:1e8")
DEFAULT_RESOLUTIONS = (128, 256, 512, 1024)
RENDERERS = ("heterogeneous", "dense16")
METHODS = ("box", "nearest")
#: Samples per pixel of one render call; more are several calls (bounded memory).
CHUNK_SPP = 64
#: Rivals of this many voxels or more are timed as plain frames: Dr.Jit's
#: frozen replay failed on a 1024^3 grid (see `study_one`).
FREEZE_MAX_VOXELS = 1 << 29
#: A floor is resolved where its square exceeds this many standard errors
#: of its estimate (`bias_floor`).
RESOLVED_SE = 4.0
#: Cosmo levels unless the spec gives them.
COSMO_LEVELS = 7
#: Estimated peak bytes per voxel of building each renderer, the resampled
#: float32 grid included: heterogeneous = grid 4 + sigma_t/albedo numpy 16
#: + their Dr.Jit copies 16; dense16 = grid 4 + blocks 4 + device copy 4 + 2 spare.
BYTES_PER_VOXEL = {"heterogeneous": 36, "dense16": 14}


# ---- data ----------------------------------------------------------------
def data_path(spec: str, data_dir: Path):
    """``(path, field, name)`` of a data spec, generating synthetic data on first use."""
    data_dir = Path(data_dir)
    if spec.startswith("cosmo:"):
        parts = spec.split(":")
        try:
            cells = int(float(parts[1]))
            levels = int(parts[2]) if len(parts) > 2 else COSMO_LEVELS
        except (ValueError, IndexError):
            raise ValueError(f"bad data spec {spec!r}: expected cosmo:CELLS[:LEVELS], e.g. cosmo:1e7") from None
        path = data_dir / f"cosmo-{cells:.0e}-L{levels}.cells".replace("+", "")
        if not path.exists():
            with progress(cells, f"writing {path}") as bar:
                write_block_dataset(path, cells, levels, name="cosmo", progress_bar=bar)
        return path, None, f"cosmo {cells:.0e} L{levels}"
    if spec == "enzo":
        path = data_dir / "enzo" / "DD0018" / "DD0018"
        if not path.exists():
            script = Path(__file__).resolve().parents[2] / "tools" / "make_enzo_example.py"
            if not script.exists():
                raise FileNotFoundError(f"{script}: the Enzo example's writer (a source checkout) is missing")
            subprocess.run([sys.executable, str(script), str(data_dir / "enzo")], check=True)
        return path, "density", "enzo example"
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(f"{spec}: no such data file (or use cosmo:CELLS[:LEVELS] or enzo)")
    return path, None, path.name


def resample_grid(data, resolution: int, method: str = "box", bar=None):
    """The linear values of ``data`` (`AMRCells` or `BlockVolume`) on a dense
    grid of ``resolution`` voxels along the longest side, float32 ``[z, y, x]``.
    ``box``: the volume-weighted average over each voxel (mass-conserving;
    assumes the cells cover the domain); ``nearest``: the cell under each
    voxel centre. The voxel must be a power-of-two number of finest cells
    (so that cells and voxels align)."""
    if method not in METHODS:
        raise ValueError(f"unknown resample method {method!r} (choose from {', '.join(METHODS)})")
    lo, hi = (np.asarray(b, dtype=np.int64) for b in data.bounds)
    ext = hi - lo
    v = int(ext.max()) // int(resolution)
    if v < 1 or v * int(resolution) != int(ext.max()) or v & (v - 1) or np.any(ext % v):
        raise ValueError(f"{data.source}: {resolution} voxels per side do not align with the cells "
                         f"(extent {ext.tolist()} finest cells: the voxel must be a power of two of them)")
    nx, ny, nz = (int(e) // v for e in ext)
    grid = np.zeros(nx * ny * nz, dtype=np.float32)
    for pos, level, value in data.cell_chunks(1 << 21):
        p = pos - lo
        size = np.int64(1) << level.astype(np.int64)
        fine = size <= v
        idx = p[fine] // v
        flat = (idx[:, 2] * ny + idx[:, 1]) * nx + idx[:, 0]
        if method == "box":
            u, inv = np.unique(flat, return_inverse=True)
            grid[u] += np.bincount(inv.ravel(), weights=value[fine] * (size[fine] / v) ** 3.0).astype(np.float32)
        else:
            c = idx * v + 0.5 * v
            inside = np.all((p[fine] <= c) & (c < p[fine] + size[fine, None]), axis=1)
            grid[flat[inside]] = value[fine][inside]
        for L in np.unique(level[~fine]):                 # cells larger than a voxel fill k^3 voxels
            sel = np.nonzero(level == L)[0]
            k = (1 << int(L)) // v
            o = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)
            step = max(1, (1 << 22) // len(o))
            for s in range(0, len(sel), step):
                base = p[sel[s:s + step]] // v
                q = (base[:, None, :] + o[None]).reshape(-1, 3)
                grid[(q[:, 2] * ny + q[:, 1]) * nx + q[:, 0]] = np.repeat(value[sel[s:s + step]], len(o))
        if bar is not None:
            bar.update(len(level))
    return grid.reshape(nz, ny, nx)


def _dense_blocks(values: np.ndarray, source: str):
    """A one-level `BlockVolume` of 16^3 blocks of a NaN-free grid whose sides
    are multiples of 16, with one copy (else `BlockVolume.from_dense`)."""
    nz, ny, nx = values.shape
    if nx % 16 or ny % 16 or nz % 16 or np.isnan(values).any():
        return BlockVolume.from_dense(values, 16, source)
    bz, by, bx = nz // 16, ny // 16, nx // 16
    blocks = np.ascontiguousarray(values.reshape(bz, 16, by, 16, bx, 16).transpose(0, 2, 4, 1, 3, 5)).reshape(-1)
    k = np.arange(bx * by * bz)
    coord = np.stack([k % bx, (k // bx) % by, k // (bx * by)], axis=1).astype(np.int32)
    return BlockVolume(16, np.zeros(len(k), np.uint8), coord, blocks, np.zeros(3, np.int64),
                       np.zeros(3, np.int64), np.array([nx, ny, nz], np.int64), values.size, source)


def available_bytes() -> int:
    """MemAvailable of /proc/meminfo (bytes); 8 GiB where it cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 8 << 30


# ---- scenes --------------------------------------------------------------
class Study:
    """One data set's scene plan and renders (images float64 (H, W, C))."""

    def __init__(self, mi, plan, args, camera=None):
        self.mi, self.plan, self.args, self.camera = mi, plan, args, camera
        self.tf = TransferFunction.load(plan.tf, plan.tf_range)

    def medium_common(self):
        p = self.plan
        return {"transfer_function": p.tf, "tf_min": p.tf_range[0], "tf_max": p.tf_range[1],
                "density_scale": p.density_scale, "reconstruction": "nearest"}

    def truth_scene(self):
        med = {"type": "amr", "data": self.plan.data, "value_transform": self.plan.transform, **self.medium_common()}
        return bench_scene(med, self.args.res, {"type": "amrvolpath", "max_depth": self.args.max_depth},
                           self.camera)

    def transformed(self, grid: np.ndarray) -> np.ndarray:
        """The grid on the truth's value scale (log10 in place, with the data's floor)."""
        if self.plan.transform == "log10":
            flat = grid.reshape(-1)
            log10_values(flat, self.floor, out=flat)
        return grid

    def rival_scene(self, grid: np.ndarray, renderer: str):
        """Scene of ``renderer`` on a transformed dense grid."""
        mi = self.mi
        if renderer == "dense16":
            med = {"type": "amr", "data": _dense_blocks(grid, f"{self.plan.data.source} (dense)"),
                   "grid_resolution": 16, **self.medium_common()}
            integ = {"type": "amrvolpath", "max_depth": self.args.max_depth}
        elif renderer == "heterogeneous":
            sigma = np.empty(grid.shape + (1,), np.float32)
            albedo = np.empty(grid.shape + (3,), np.float32)
            for z in range(0, grid.shape[0], 16):                  # the TF slab by slab
                rgba = self.tf(grid[z:z + 16])
                sigma[z:z + 16], albedo[z:z + 16] = rgba[..., 3:4], rgba[..., :3]

            def vol(a):
                return {"type": "gridvolume", "data": mi.TensorXf(a), "filter_type": "nearest"}
            med = {"type": "heterogeneous", "sigma_t": vol(sigma), "albedo": vol(albedo),
                   "scale": float(self.plan.density_scale)}
            del sigma, albedo
            integ = {"type": "volpath", "max_depth": self.args.max_depth}
        else:
            raise ValueError(f"unknown renderer {renderer!r} (choose from {', '.join(RENDERERS)})")
        return bench_scene(med, self.args.res, integ, self.camera)


def densest_point(data) -> np.ndarray:
    """Centre of the cell holding the largest value, in the unit cube the
    data bounds fill (a halo's core on cosmological data)."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in data.bounds)
    best, where = -np.inf, None
    for pos, level, value in data.cell_chunks():
        i = int(np.argmax(value))
        if value[i] > best:
            best, where = float(value[i]), pos[i] + 0.5 * float(1 << int(level[i]))
    return (where - lo) / (hi - lo)


def render_mean(mi, scene, spp: int, seed: int, frozen: bool = True) -> np.ndarray:
    """Mean image of ``spp`` samples per pixel, `CHUNK_SPP` per call (frozen:
    replayed, no per-call trace)."""
    frames = {}
    acc, done, k = None, 0, 0
    while done < spp:
        n = min(CHUNK_SPP, spp - done)
        if n not in frames:
            frames[n] = frame_function(mi, n, frozen)
        img = frames[n](scene, seed + k) * n
        acc = img if acc is None else acc + img
        done, k = done + n, k + 1
    return acc / spp


def halves(mi, scene, spp: int, seed: int, frozen: bool = True):
    """``(mean image, its noise MSE, its noise map)`` from two independent
    halves of ``spp``: the map ``(h1 - h2)^2 / 4`` estimates, per pixel and
    channel, the variance of the mean image, and the MSE is its mean."""
    h1 = render_mean(mi, scene, max(1, spp // 2), seed, frozen)
    h2 = render_mean(mi, scene, max(1, spp // 2), seed + 1_000_003, frozen)
    noise_map = (h1 - h2) ** 2 / 4.0
    return 0.5 * (h1 + h2), float(np.mean(noise_map)), noise_map


def bias_floor(img, img_noise_map, truth, truth_noise_map):
    """``(floor, standard error of floor^2)`` of an image against the truth
    (both (H, W, C) means with their `halves` noise maps): per pixel,
    ``(img - truth)^2`` less both noise maps is an unbiased estimate of the
    squared bias, whose mean over the image is ``floor^2``; the standard
    error is measured from those per-pixel estimates themselves (Monte Carlo
    noise is heavy-tailed, so a Gaussian model of the noise estimate would
    understate it). Channels of a pixel are averaged first (they share
    paths, so they are not independent)."""
    d = ((img - truth) ** 2 - img_noise_map - truth_noise_map).reshape(img.shape[0] * img.shape[1], -1).mean(axis=1)
    return math.sqrt(max(float(d.mean()), 0.0)), float(d.std(ddof=1) / math.sqrt(d.size))


def curve(mi, scene, truth, truth_noise, args, floor=None, frozen=None):
    """``[[spp, seconds, RMSE (truth noise off), raw RMSE], ...]`` at 1, 2, 4, ...
    spp up to ``args.max_spp``; a rival's curve stops two points after it is
    within 10% of its ``floor`` (flat from there)."""
    out, within = [], 0
    frames = {}
    spp = 1
    while spp <= args.max_spp:
        n = min(spp, CHUNK_SPP)
        if n not in frames:
            frozen = args.frozen if frozen is None else frozen
            frames[n] = frame_function(mi, n, frozen)
            for w in range(FROZEN_WARMUP if frozen else 1):
                frames[n](scene, 90_000 + w)
        calls = spp // n
        times = []
        for r in range(args.repeats if spp <= CHUNK_SPP else 1):
            wait_idle()
            acc, t = None, 0.0
            for c in range(calls):
                t0 = time.perf_counter()
                img = frames[n](scene, 1000 * spp + 100 * r + c)
                t += time.perf_counter() - t0
                acc = img if acc is None else acc + img
            times.append(t)
        mse = float(np.mean((acc / calls - truth) ** 2))
        rmse = math.sqrt(max(mse - truth_noise, 0.0))
        out.append([spp, statistics.median(times), rmse, math.sqrt(mse)])
        if floor is not None and rmse <= 1.1 * floor:
            within += 1
            if within > 2:
                break
        spp *= 2
    return out


def seconds_to(curve_pts, target: float, extrapolate: bool = False):
    """Render seconds at which a curve first reaches RMSE ``target``
    (log-log interpolation); None if it never does, unless ``extrapolate``
    (then continued as 1/sqrt(seconds) from its last point)."""
    prev = None
    for _, t, e, _raw in curve_pts:
        if e <= target:
            if prev is None or prev[1] <= e or e <= 0:
                return t
            a = (math.log(prev[1]) - math.log(target)) / (math.log(prev[1]) - math.log(e))
            return math.exp(math.log(prev[0]) + a * (math.log(t) - math.log(prev[0])))
        prev = (t, e)
    if extrapolate and prev is not None and target > 0:
        return prev[0] * (prev[1] / target) ** 2
    return None


def seconds_near_floor(curve_pts, floor: float, within: float = 1.1):
    """``(seconds, extrapolated)``: render seconds at which a rival's curve
    comes within ``within`` of its ``floor``. Past the curve's end it is
    continued by its noise model, ``RMSE^2 = floor^2 + c / seconds`` (``c``
    from its last point); ``(None, False)`` without a floor."""
    if not floor or floor <= 0 or not curve_pts:
        return None, False
    t = seconds_to(curve_pts, within * floor)
    if t is not None:
        return t, False
    _, t_last, e_last, _ = curve_pts[-1]
    c = max(e_last ** 2 - floor ** 2, 0.0) * t_last
    return max(t_last, c / ((within ** 2 - 1.0) * floor ** 2)), True


def _free(scene):
    del scene
    gc.collect()


def study_one(mi, spec: str, args) -> dict:
    """The whole study of one data set (see the module docstring)."""
    path, field, name = data_path(spec, Path(args.data_dir))
    t0 = time.perf_counter()
    plan = plan_scene(str(path), args.field or field)
    load_s = time.perf_counter() - t0
    data = plan.data
    camera = None
    if getattr(args, "zoom", None):
        camera = zoom_camera(densest_point(data), args.zoom)
    study = Study(mi, plan, args, camera)
    values = data.values
    study.floor = positive_floor(values, data.source) if plan.transform == "log10" else None
    lo, hi = data.bounds
    n_fine = int((hi - lo).max())
    rec = {"data": spec, "name": name, "file": str(path), "cells": int(len(data)), "levels": int(len(data.levels)),
           "finest": n_fine, "cell_size_span": int(2 ** (int(data.levels.max()) - int(data.levels.min()))),
           "transform": plan.transform, "tf": plan.tf, "tf_range": list(plan.tf_range),
           "density_scale": plan.density_scale, "res": args.res, "truth_spp": args.truth_spp,
           "floor_spp": args.floor_spp, "frozen": args.frozen, "load_s": load_s, "rivals": [], "skipped": [],
           "zoom": getattr(args, "zoom", None), "camera": study.camera}
    print(f"{name}: {rec['cells']:,} cells, {rec['levels']} levels, finest {n_fine}^3, {plan.transform} values, "
          f"TF {plan.tf} over [{plan.tf_range[0]:.3g}, {plan.tf_range[1]:.3g}], density_scale "
          f"{plan.density_scale:.3g}", flush=True)
    # truth, and the amr medium's own curve
    check_alone("truth")
    t0 = time.perf_counter()
    scene = mi.load_dict(study.truth_scene())
    rec["amr_build_s"] = time.perf_counter() - t0
    med = [s for s in scene.shapes() if s.interior_medium() is not None][0].interior_medium()
    rec["amr_bytes"] = int(med.resident_bytes)
    del med
    t0 = time.perf_counter()
    truth, noise, truth_noise_map = halves(mi, scene, args.truth_spp, seed=1, frozen=args.frozen)
    rec["truth_s"] = time.perf_counter() - t0
    rec["truth_noise_rmse"] = math.sqrt(noise)
    rec["truth_mean"] = float(truth.mean())
    rec["amr_curve"] = curve(mi, scene, truth, noise, args)
    _free(scene)
    scene = None
    print(f"  truth {args.truth_spp} spp in {rec['truth_s']:.1f} s, noise RMSE {rec['truth_noise_rmse']:.2e} "
          f"(image mean {rec['truth_mean']:.3g}); amr curve ends at RMSE {rec['amr_curve'][-1][2]:.2e} "
          f"after {rec['amr_curve'][-1][1]:.2f} s", flush=True)
    # rivals
    budget = args.memory_limit * 2**30 if args.memory_limit else 0.8 * available_bytes()
    jobs = [(r, m, False) for r in args.resolutions for m in args.methods]
    if n_fine <= args.check_max and (n_fine not in args.resolutions or "nearest" not in args.methods):
        jobs.append((n_fine, "nearest", True))          # the finest nearest resample: the check alone
    for res, method, check in jobs:
        if res > n_fine:
            rec["skipped"].append({"resolution": res, "method": method, "why":
                                   f"finer than the finest level ({n_fine}^3): it holds nothing more"})
            continue
        renderers = ["heterogeneous"] if check else list(args.renderers)
        voxels = res ** 3
        fits = [r for r in renderers if BYTES_PER_VOXEL[r] * voxels <= budget]
        for r in set(renderers) - set(fits):
            rec["skipped"].append({"resolution": res, "method": method, "renderer": r, "why":
                                   f"needs about {BYTES_PER_VOXEL[r] * voxels / 2**30:.1f} GiB, above the "
                                   f"{budget / 2**30:.1f} GiB allowed"})
            print(f"  {method} {res}^3 {r}: skipped (memory)", flush=True)
        if not fits:
            continue
        t0 = time.perf_counter()
        try:
            with progress(rec["cells"], f"resampling {res}^3 ({method})") as bar:
                grid = study.transformed(resample_grid(data, res, method, bar))
        except ValueError as e:
            rec["skipped"].append({"resolution": res, "method": method, "why": str(e)})
            print(f"  {method} {res}^3: skipped: {e}", flush=True)
            continue
        resample_s = time.perf_counter() - t0
        for renderer in fits:
            check_alone(f"{renderer} {res}")
            t0 = time.perf_counter()
            scene = mi.load_dict(study.rival_scene(grid, renderer))
            build_s = time.perf_counter() - t0
            if renderer == "dense16":
                m = [s for s in scene.shapes() if s.interior_medium() is not None][0].interior_medium()
                mem = int(m.resident_bytes)
                del m
            else:
                mem = 16 * voxels
            # Dr.Jit 1.5's frozen replay fails on a grid of 2^30 float values ("determining size of
            # variable ... dsize=0", seen with the 1024^3 dense16 rival): such rivals run plain frames
            frozen = args.frozen and voxels < FREEZE_MAX_VOXELS
            img, img_noise, img_noise_map = halves(mi, scene, args.floor_spp, seed=7, frozen=frozen)
            mse = float(np.mean((img - truth) ** 2))
            floor, floor_se = bias_floor(img, img_noise_map, truth, truth_noise_map)
            row = {"resolution": res, "method": method, "renderer": renderer, "check": check, "frozen": frozen,
                   "resample_s": resample_s, "build_s": build_s, "bytes": mem, "floor": floor,
                   "floor_sq_se": floor_se, "floor_raw": math.sqrt(mse),
                   "floor_noise_rmse": math.sqrt(noise + img_noise),
                   "check_ratio": mse / (noise + img_noise) if noise + img_noise > 0 else None}
            # a floor whose square is under 4 standard errors of its estimate is not resolved:
            # no times to it
            row["resolved"] = floor ** 2 > RESOLVED_SE * floor_se
            if not check:
                row["curve"] = curve(mi, scene, truth, noise, args, floor if row["resolved"] else None, frozen)
                row["seconds_within_10pct"], row["rival_extrapolated"] = (
                    seconds_near_floor(row["curve"], floor) if row["resolved"] else (None, False))
                row["amr_seconds_to_floor"] = (seconds_to(rec["amr_curve"], floor, extrapolate=True)
                                               if row["resolved"] else None)
                row["amr_extrapolated"] = row["resolved"] and seconds_to(rec["amr_curve"], floor) is None
            _free(scene)
            scene = None
            rec["rivals"].append(row)
            extra = (f"check: MSE / noise {row['check_ratio']:.2f}" if check else
                     "floor under the truth's noise: not resolved" if not row["resolved"] else
                     f"within 10% after {row['seconds_within_10pct'] or float('nan'):.2f} s; amr reaches it "
                     f"after {row['amr_seconds_to_floor'] or float('nan'):.2f} s"
                     f"{' (extrapolated)' if row['amr_extrapolated'] else ''}")
            print(f"  {method:7s} {res:5d}^3 {renderer:13s} floor {floor:.2e} (raw {row['floor_raw']:.2e}), "
                  f"{mem / 2**20:8.1f} MiB, resample {resample_s:.1f} s + build {build_s:.1f} s; {extra}",
                  flush=True)
        del grid
        gc.collect()
    summarise(rec)
    return rec


def summarise(rec: dict) -> dict:
    """A data set's summary fields from its rows: the best rival (lowest
    floor) and the headline (the lowest resolved floor with both times: the
    rival's seconds to come within 10% of it over the amr medium's seconds
    to reach it)."""
    fitting = [r for r in rec["rivals"] if not r["check"]]
    rec["amr_end_rmse"] = rec["amr_curve"][-1][2]
    rec["within_noise"] = [f"{r['method']} {r['resolution']}^3 {r['renderer']}" for r in fitting if not r["resolved"]]
    fitting = [r for r in fitting if r["resolved"]]           # a floor under the noise is no measurement
    if fitting:
        best = min(fitting, key=lambda r: r["floor"])
        rec["best_rival"] = {k: best[k] for k in ("resolution", "method", "renderer", "floor", "resolved")}
        timed = [r for r in fitting if r["resolved"] and r["amr_seconds_to_floor"] and r["seconds_within_10pct"]]
        if timed:
            h = min(timed, key=lambda r: r["floor"])
            rec["headline"] = {"rival": f"{h['method']} {h['resolution']}^3 {h['renderer']}", "floor": h["floor"],
                               "rival_s": h["seconds_within_10pct"], "amr_s": h["amr_seconds_to_floor"],
                               "ratio": h["seconds_within_10pct"] / h["amr_seconds_to_floor"],
                               "amr_extrapolated": h["amr_extrapolated"],
                               "rival_extrapolated": h.get("rival_extrapolated", False)}
    return rec


# ---- run and report --------------------------------------------------------
def run_resample(specs, out: Path, args) -> list:
    """The study of every data spec; writes resample.json/.md/.png into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records = []
    for spec in specs:
        records.append(study_one(mi, spec, args))
        (out / "resample.json").write_text(json.dumps(records, indent=1, default=float))
    write_resample_table(records, out)
    plot_resample(records, out)
    return records


def _s(x, fmt="{:.2f}"):
    return "-" if x is None else fmt.format(x)


def write_resample_table(records, out: Path):
    lines = ["# AMR rendering against dense resamples: time against error", ""]
    for r in records:
        lines += [f"## {r['name']} ({r['cells']:,} cells, {r['levels']} levels, cell sizes spanning "
                  f"{r['cell_size_span']}x, finest {r['finest']}^3)", "",
                  f"Scene as `mi-amr render` plans it: {r['transform']} values, TF `{r['tf']}` over "
                  f"[{r['tf_range'][0]:.3g}, {r['tf_range'][1]:.3g}], density scale {r['density_scale']:.3g}; "
                  f"{r['res']}x{r['res']}"
                  f"{'' if not r.get('zoom') else ', a telephoto view of the densest cell spanning ' + format(r['zoom'], 'g') + ' of the domain'}. Truth: amr medium at {r['truth_spp']} spp in two halves "
                  f"({r['truth_s']:.1f} s), its noise RMSE {r['truth_noise_rmse']:.2e} (taken off every error). "
                  f"amr medium: {r['amr_bytes'] / 2**20:.1f} MiB, build {r['amr_build_s']:.2f} s.", "",
                  "| rival | renderer | floor RMSE | memory MiB | resample + build s | rival s to within 10% of "
                  "floor | amr s to the floor | rival / amr |", "|---|---|---|---|---|---|---|---|"]
        for x in r["rivals"]:
            if x["check"]:
                continue
            a, b = x["amr_seconds_to_floor"], x["seconds_within_10pct"]
            ratio = f"{b / a:.1f}x" if a and b else ""
            if not x["resolved"]:
                a = b = None
                ratio = f"floor under the noise ({x['floor_noise_rmse']:.1e})"
            lines.append(f"| {x['method']} {x['resolution']}^3 | {x['renderer']} | {x['floor']:.2e} | "
                         f"{x['bytes'] / 2**20:.0f} | {x['resample_s']:.1f} + {x['build_s']:.1f} | {_s(b)}"
                         f"{' (extrap.)' if b and x.get('rival_extrapolated') else ''} | "
                         f"{_s(a)}{' (extrap.)' if x['amr_extrapolated'] else ''} | {ratio} |")
        for x in r["skipped"]:
            lines.append(f"\n{x['method']} {x['resolution']}^3{' ' + x['renderer'] if 'renderer' in x else ''}: "
                         f"skipped: {x['why']}")
        checks = [x for x in r["rivals"] if x["check"] or (x["resolution"] == r["finest"] and
                                                             x["renderer"] == "heterogeneous")]
        for x in checks:
            lines.append(f"\nCheck: {x['method']} resample at the finest resolution ({x['resolution']}^3) in "
                         f"Mitsuba's heterogeneous medium against the amr truth: measured MSE / expected noise "
                         f"MSE = {x['check_ratio']:.2f} (1 = equal within noise), floor {x['floor']:.2e}.")
        if r.get("headline"):
            h = r["headline"]
            lines.append(f"\n**Headline**: to reach the floor of {h['rival']} ({h['floor']:.2e}) the amr medium "
                         f"needs {h['amr_s']:.2f} s{' (extrapolated)' if h['amr_extrapolated'] else ''}; the rival "
                         f"needs {h['rival_s']:.2f} s{' (extrapolated)' if h.get('rival_extrapolated') else ''} "
                         f"to come within 10% of it: {h['ratio']:.1f}x.")
        if r.get("within_noise"):
            lines.append(f"\nEqual to the truth within its noise: {', '.join(r['within_noise'])}.")
        if r.get("best_rival"):
            b = r["best_rival"]
            lines.append(f"\nLowest resolved floor of a resample that fits: {b['floor']:.2e} ({b['method']} "
                         f"{b['resolution']}^3, {b['renderer']}); the amr curve ends at {r['amr_end_rmse']:.2e} "
                         f"after {r['amr_curve'][-1][1]:.2f} s ({r['amr_curve'][-1][0]} spp).")
        lines.append("")
    lines += ["Floors: a rival's RMSE at high spp with its own and the truth's noise taken off (its bias). "
              "Seconds: render time of the frames alone (resampling and building apart). Ratio: the rival's "
              "seconds to come within 10% of its floor over the amr medium's seconds to reach that floor."]
    (out / "resample.md").write_text("\n".join(lines) + "\n")


def plot_resample(records, out: Path):
    """Log-log RMSE against seconds, one panel per data set (README-column size)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = len(records)
    if not n:
        return
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.6), squeeze=False)
    colours = {128: "tab:blue", 256: "tab:orange", 512: "tab:green", 1024: "tab:red"}
    for ax, r in zip(axes[0], records):
        c = [p for p in r["amr_curve"] if p[2] > 0]
        ax.loglog([p[1] for p in c], [p[2] for p in c], "k-", lw=3, marker="o", ms=3, label="amr medium")
        for x in r["rivals"]:
            if x["check"]:
                continue
            col = colours.get(x["resolution"], "tab:olive" if x["resolution"] < 128 else "tab:purple")
            ls = "-" if x["renderer"] == "heterogeneous" else ":"
            pts = [p for p in x["curve"] if p[2] > 0]
            ax.loglog([p[1] for p in pts], [p[2] for p in pts], ls=ls, color=col, marker=".", ms=3,
                      alpha=0.9 if x["method"] == "box" else 0.5,
                      label=f"{x['method']} {x['resolution']}^3 {x['renderer']}")
            if x["floor"] > 0:
                ax.axhline(x["floor"], color=col, ls="--", lw=0.8)
        ax.set_title(f"{r['name']}", fontsize=9)
        ax.set_xlabel("render seconds")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("RMSE vs truth")
    axes[0][-1].legend(fontsize=6, loc="upper right")
    fig.tight_layout()
    fig.savefig(out / "resample.png", dpi=100)
    plt.close(fig)


def main_args(args):
    """Entry from `mi_amr.bench.__main__` (``--resample``)."""
    mi.set_variant(args.variant)
    study = SimpleNamespace(
        res=args.res, truth_spp=args.truth_spp, floor_spp=args.floor_spp or
        args.truth_spp // 2, max_spp=args.max_spp, resolutions=args.resolutions, methods=args.resample_methods,
        renderers=args.renderers, check_max=args.check_max, memory_limit=args.resample_memory,
        frozen=not args.unfrozen, repeats=args.repeats, max_depth=args.max_depth, data_dir=args.data_dir,
        field=args.field, zoom=args.zoom)
    for name, seq, allowed in (("--resample-methods", study.methods, METHODS), ("--renderers", study.renderers,
                                                                              RENDERERS)):
        bad = [x for x in seq if x not in allowed]
        if bad:
            raise SystemExit(f"{name}: unknown {', '.join(bad)} (choose from {', '.join(allowed)})")
    specs = args.resample or list(DEFAULT_DATA)
    run_resample(specs, Path(args.out), study)
    print(f"wrote {args.out}/resample.json, resample.md and resample.png")
    return 0


if __name__ == "__main__":
    sys.exit("usage: python -m mi_amr.bench --resample [DATA ...] --out DIR")
