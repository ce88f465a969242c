"""``python -m mi_amr.bench --adaptive``: seconds to a picture within 2% RMSE
of the converged one, fixed spp against adaptive sampling, raw against
denoised, and the default command's whole process beside yt's
(docs/performance/adaptive.md).

Per data set, the picture ``mi-amr render DATA --field F --res RES`` makes
(its plan, ``multi``): a reference of two independent half buffers (``--adaptive-ref-spp``
samples each, cached under ``--out``), whose own relative error is
estimated from their difference (`mi_amr.adaptive.tile_errors` over the
whole picture) and taken off every error measured against it (independent
noise adds in squares: ``err^2 = |x - ref|^2 - ref_err^2``). Errors are RMSE
over the reference's mean. Then, in this process with the kernels
compiled: fixed spp (8 to 128, raw, denoised and denoised with the albedo
guide of `mi_amr.denoising`) and adaptive sampling at several noise
thresholds (raw and denoised), each with its seconds. Then the whole
process of the default command and of yt's ``create_scene`` + render +
save on the same output (only outputs yt reads), alternated ``--rounds``
times, wall and CPU seconds, with the load average.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

from .. import adaptive, denoising
from ..autoscene import plan_scene
from ..data.enzo_example import write_example
from ..images import read_exr
from ..rendering import use_variant
from ..scene_writer import scene_for
from .scale import data_file

#: Data sets: name -> (how to find the data, field).
CASES = ("enzo", "blocks", "1e7")
#: Fixed sample counts measured.
FIXED_SPP = (8, 16, 32, 64, 128)
#: Noise thresholds of adaptive sampling measured.
NOISES = (0.15, 0.1, 0.07, 0.05, 0.035)
#: The target: RMSE over the converged picture's mean.
TARGET = 0.02

YT_SCRIPT = """import sys, yt
yt.set_log_level(50)
ds = yt.load(sys.argv[1])
sc = yt.create_scene(ds, sys.argv[2])
sc.camera.resolution = (int(sys.argv[3]), int(sys.argv[3]))
sc.render()
sc.save(sys.argv[4], sigma_clip=4.0)
"""


def case_data(name: str, out: Path) -> tuple[Path, str | None, bool]:
    """``(data path, field, yt reads it)`` of a data set."""
    if name == "enzo":
        folder = out / "enzo"
        if not (folder / "DD0018" / "DD0018").exists():
            write_example(folder)
        return folder / "DD0018" / "DD0018", "density", True
    if name == "blocks":
        return Path("scenes/data/blocks.cells"), None, False
    if name == "1e7":
        return data_file("blocks", 10 ** 7, Path("out/data")), None, False
    raise ValueError(f"--adaptive: unknown data set {name!r} (known: {', '.join(CASES)})")


def rel_err(img, ref, ref_mse: float) -> dict:
    """RMSE of ``img`` against ``ref`` over the reference's mean: as
    measured (``measured``) and with the reference's own error taken off
    (``err``)."""
    d2 = float(np.mean((np.asarray(img, np.float64)[..., :3] - ref) ** 2))
    m = float(ref.mean())
    return {"err": float(np.sqrt(max(d2 - ref_mse, 0.0))) / m, "measured": float(np.sqrt(d2)) / m}


def pixel_means(sums) -> np.ndarray:
    w = sums[..., -1:]
    return np.where(w > 0, sums[..., :3] / np.where(w > 0, w, 1.0), 0.0)


def reference(scene, res: int, spp: int, cache: Path, chunk: int = 32):
    """Two half buffers of ``spp`` samples each (cached): ``(mean picture,
    its mean squared error estimate, seconds to render)``."""
    if cache.exists():
        z = np.load(cache)
        a, b, seconds = z["a"], z["b"], float(z["seconds"])
    else:
        pixels = np.arange(res * res, dtype=np.uint32)
        t0 = time.perf_counter()
        halves = []
        for h in range(2):
            total = None
            for k in range(-(-spp // chunk)):
                s = adaptive.render_pixels(scene, pixels, min(chunk, spp - k * chunk), 50_000 + 1000 * h + k)
                total = s.astype(np.float64) if total is None else total + s
            halves.append(total)
        a, b = halves
        seconds = time.perf_counter() - t0
        np.savez_compressed(cache, a=a, b=b, seconds=seconds)
    ma, mb = pixel_means(a), pixel_means(b)
    ref = 0.5 * (ma + mb)
    return ref, float(np.mean((0.5 * (ma - mb)) ** 2)), seconds


def timed(fn, *a, **kw):
    t0 = time.perf_counter()
    r = fn(*a, **kw)
    return r, time.perf_counter() - t0


def in_process(data, field, res: int, ref_spp: int, out: Path, name: str) -> dict:
    """The in-process rows of one data set (module docstring)."""
    use_variant(say=False)
    plan, plan_s = timed(plan_scene, str(data), field)
    scene, load_s = timed(mi.load_dict, scene_for(plan, res=res, spp=16))
    pixels = np.arange(res * res, dtype=np.uint32)
    _, compile_s = timed(adaptive.render_pixels, scene, pixels, 1, 7)       # the kernel, compiled or from the cache
    ref, ref_mse, ref_s = reference(scene, res, ref_spp, out / f"ref-{name}-{res}-{ref_spp}.npz")
    rec = {"data": name, "path": str(data), "res": res, "ref_spp": 2 * ref_spp, "ref_seconds": ref_s,
           "ref_err": float(np.sqrt(ref_mse)) / float(ref.mean()), "first_launch_seconds": compile_s,
           "plan_seconds": plan_s, "load_seconds": load_s,
           "fixed": [], "adaptive": []}
    print(f"{name}: reference {2 * ref_spp} spp, its own error {100 * rec['ref_err']:.2f}%", flush=True)
    albedo, guide_s = timed(denoising.albedo_guide, scene, 3)
    albedo, guide_s = timed(denoising.albedo_guide, scene, 3)               # warm: its kernel compiled once
    rec["guide_seconds"] = guide_s
    for spp in FIXED_SPP:
        sums, s = timed(adaptive.render_pixels, scene, pixels, spp, 1000 + spp)
        img = pixel_means(sums).astype(np.float32)
        clean, ds = timed(denoising.denoise, img)
        guided = denoising.denoise(img, albedo)
        row = {"spp": spp, "seconds": s, "denoise_seconds": ds, "raw": rel_err(img, ref, ref_mse),
               "denoised": rel_err(clean, ref, ref_mse), "guided": rel_err(guided, ref, ref_mse)}
        rec["fixed"].append(row)
        print(f"  fixed {spp:4d} spp {s:7.2f} s: raw {100 * row['raw']['err']:.2f}%, denoised "
              f"{100 * row['denoised']['err']:.2f}%, albedo-guided {100 * row['guided']['err']:.2f}%", flush=True)
    for noise in NOISES:
        r = adaptive.render_adaptive(scene, noise=noise, max_spp=1024, seed=2000 + int(1000 * noise))
        clean, ds = timed(denoising.denoise, r.image)
        row = {"noise": noise, "seconds": r.seconds, "denoise_seconds": ds, "mean_spp": r.samples,
               "min_spp": float(r.spp.min()), "max_spp": float(r.spp.max()), "stopped": r.stopped,
               "estimated": adaptive.estimated_picture_error(r.tile_error), "raw": rel_err(r.image, ref, ref_mse),
               "denoised": rel_err(clean, ref, ref_mse)}
        rec["adaptive"].append(row)
        print(f"  adaptive {noise:.3f} {r.seconds:7.2f} s, {r.samples:6.1f} spp mean: raw "
              f"{100 * row['raw']['err']:.2f}% (estimated {100 * row['estimated']:.2f}%), denoised "
              f"{100 * row['denoised']['err']:.2f}%", flush=True)
    rec["to_target"] = to_target(rec)
    np.save(out / f"ref-{name}-{res}.npy", ref.astype(np.float32))
    return rec


def to_target(rec) -> dict:
    """Seconds to within `TARGET` of each way (the fastest row that is;
    None: none is), denoising included."""
    found = {}
    for way, rows, key in (("fixed raw", rec["fixed"], "raw"), ("fixed denoised", rec["fixed"], "denoised"),
                           ("fixed albedo-guided", rec["fixed"], "guided"),
                           ("adaptive raw", rec["adaptive"], "raw"), ("adaptive denoised", rec["adaptive"], "denoised")):
        extra = (lambda r: r["denoise_seconds"]) if key != "raw" else (lambda r: 0.0)
        if key == "guided":
            extra = (lambda r: r["denoise_seconds"] + rec["guide_seconds"])
        ok = [r["seconds"] + extra(r) for r in rows if r[key]["err"] <= TARGET]
        found[way] = min(ok) if ok else None
    return found


def whole_process(data, field, res: int, rounds: int, out: Path, yt_reads: bool, ref=None, ref_mse=0.0) -> dict:
    """The default command's and yt's whole process, alternated (module
    docstring): wall and CPU seconds each round; the default picture's error."""
    ours, yts = [], []
    err = []
    for k in range(rounds):
        exr = out / f"default-{k}.exr"
        argv = [sys.executable, "-m", "mi_amr.tools.cli", "render", str(data), "--res", str(res), "-o", str(exr)]
        if field:
            argv += ["--field", field]
        run = run_timed(argv)
        ours.append(run)
        printed = run.pop("stdout")
        run["summary"] = next((line.strip() for line in printed.splitlines() if "spp mean" in line), "")
        took = [line.split(" in ")[-1].split()[0] for line in printed.splitlines() if "frame(s) in" in line]
        run["render_seconds"] = float(took[0]) if took else None      # rendering and denoising, as printed
        if ref is not None:
            err.append({"denoised": rel_err(read_exr(exr.with_name(exr.stem + "-denoised.exr")), ref, ref_mse),
                        "raw": rel_err(read_exr(exr), ref, ref_mse)})
        if yt_reads:
            png = out / f"yt-{k}.png"
            run = run_timed([sys.executable, "-c", YT_SCRIPT, str(data), field or "density", str(res), str(png)])
            run.pop("stdout")
            yts.append(run)
    startup = run_timed([sys.executable, "-c", "import mi_amr.tools.cli, mitsuba as mi; "
                         "from mi_amr.rendering import use_variant; use_variant(say=False)"])
    startup.pop("stdout")
    return {"ours": ours, "yt": yts, "default_err": err, "startup": startup}


def run_timed(argv) -> dict:
    """Run a command: its wall seconds, CPU seconds (user + system of the
    child), exit status and output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(argv, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(argv[:6])}... failed: {p.stderr.strip()[-400:]}")
    return {"wall": wall, "cpu": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "stdout": p.stdout, "load": os.getloadavg()[0]}


def main_args(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res, rounds = args.adaptive_res, args.rounds_adaptive
    results = []
    for name in args.adaptive or CASES:
        data, field, yt_reads = case_data(name, out)
        load0 = os.getloadavg()
        rec = in_process(data, field, res, args.adaptive_ref_spp, out, name)
        ref = np.load(out / f"ref-{name}-{res}.npy")
        a = np.load(out / f"ref-{name}-{res}-{args.adaptive_ref_spp}.npz")
        ref_mse = float(np.mean((0.5 * (pixel_means(a["a"]) - pixel_means(a["b"]))) ** 2))
        if rounds:
            rec["whole_process"] = whole_process(data, field, res, rounds, out, yt_reads, ref, ref_mse)
        rec["load_average"] = [load0, os.getloadavg()]
        results.append(rec)
        (out / "adaptive.json").write_text(json.dumps(results, indent=1))
        print(json.dumps(rec.get("to_target")), flush=True)
        if "whole_process" in rec:
            wp = rec["whole_process"]
            for who in ("ours", "yt"):
                if wp[who]:
                    print(f"  {who}: wall {[round(r['wall'], 2) for r in wp[who]]} s, cpu "
                          f"{[round(r['cpu'], 2) for r in wp[who]]} s", flush=True)
            print(f"  default picture: {wp['default_err']}; start-up {wp['startup']['wall']:.2f} s", flush=True)
    print(f"wrote {out / 'adaptive.json'}")
    return 0
