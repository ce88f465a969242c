"""Benchmark peer: Eradiate's Mitsuba fork on the benchmark's dense field.

    .venv-eradiate/bin/python mi_amr/bench/peer_eradiate.py JOB.npz OUT_DIR

A standalone script for the virtual environment that ``make peers``
(tools/setup-peers.sh) makes: ``eradiate-mitsuba`` 0.5.0 pins Dr.Jit 1.2.0,
so it cannot share a process (or an environment) with mi-amr's Mitsuba. It
imports numpy and the fork's ``mitsuba``/``drjit`` only, never ``mi_amr``.

The job (written by `mi_amr.bench.peers.write_job`) holds the reference's
dense grids with the transfer function baked in (``sigma_t`` [nz, ny, nx, 1],
``albedo`` [nz, ny, nx, 3], float32: what `reference_medium` hands to
Mitsuba's ``heterogeneous`` + ``gridvolume``, filter ``nearest``) and the
parameters of the benchmark scene (`mi_amr.bench.harness.bench_scene`).
Configurations:

``heterogeneous``
    the fork's ``heterogeneous`` medium with its default ``extremum_global``
    (one global majorant) in ``volpath``: the same estimator as our
    ``reference`` configuration, and the peer's normaliser.
``extremum-auto``, ``extremum-N``
    the same medium with a nested ``extremum_grid`` (a DDA-walked majorant /
    minorant grid over the volume's bounds; ``resolution`` [0, 0, 0] asks
    for the fork's adaptive choice (a search on the cost model of Yue et al.
    2011), N: N^3 cells) in ``eovolpath``, the fork's integrator that walks
    the extremum structure (delta tracking per segment, residual ratio
    tracking for shadow rays).

Timing mirrors `mi_amr.bench.protocol.alternate_passes`: per round, each
configuration in turn loads its scene, renders untimed warm-up frames, waits
until the process is idle and times one frame (seed = round); one scene is
alive at a time. Frames are ``dr.freeze``-recorded ``mi.render`` calls when
the job asks for frozen frames (Dr.Jit 1.2.0 has ``dr.freeze``) and every
configuration can be recorded; else all are timed as plain frames and
``peer.json`` says why (``note``). With eradiate-mitsuba 0.5.0 the
``extremum_grid`` configurations cannot be recorded (its extremum structures
have no traversal callback for ``dr.freeze``), so its frames are plain.

Writes ``OUT_DIR/peer.json`` and, per configuration, the mean of the timed
frames as ``OUT_DIR/<config>.npy`` (float64, H x W x 3); with ``save_frames``
also every timed frame as ``OUT_DIR/<config>.frames.npy`` (rounds x H x W x 3).
"""

from __future__ import annotations

import gc
import importlib.metadata
import json
import resource
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

#: Version of the job file layout (`mi_amr.bench.peers.write_job`).
JOB_VERSION = 1
#: What a job file must hold besides the two grids.
JOB_KEYS = ("density_scale", "resolution", "spp", "max_depth", "rounds", "configs", "frozen")
#: Untimed frames before a timed one (as `mi_amr.bench.harness.FROZEN_WARMUP`).
FROZEN_WARMUP = 3
#: The fork's variant closest to the benchmark's ``llvm_ad_rgb``: the same.
DEFAULT_VARIANT = "llvm_ad_rgb"


def read_job(path) -> dict:
    """The job as a dict: the scalars and lists of its ``meta`` JSON, plus
    ``sigma_t`` and ``albedo`` (float32 arrays). Needs numpy only."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        job = dict(meta, sigma_t=np.asarray(z["sigma_t"], dtype=np.float32),
                   albedo=np.asarray(z["albedo"], dtype=np.float32))
    if job.get("version") != JOB_VERSION:
        raise ValueError(f"{path}: job version {job.get('version')}, this peer reads {JOB_VERSION}")
    missing = [k for k in JOB_KEYS if k not in job]
    if missing:
        raise ValueError(f"{path}: job lacks {missing}")
    s, a = job["sigma_t"], job["albedo"]
    if s.ndim != 4 or s.shape[3] != 1 or a.shape != s.shape[:3] + (3,):
        raise ValueError(f"{path}: sigma_t {s.shape} / albedo {a.shape}: expected [nz,ny,nx,1] / [nz,ny,nx,3]")
    for c in job["configs"]:
        config_parts(c)
    return job


def config_parts(config: str):
    """``(extremum resolution or None, integrator type)`` of a configuration
    name: ``heterogeneous`` -> (None, volpath), ``extremum-auto`` ->
    ([0, 0, 0], eovolpath), ``extremum-N`` -> ([N, N, N], eovolpath)."""
    if config == "heterogeneous":
        return None, "volpath"
    if config.startswith("extremum-"):
        r = config.split("-", 1)[1]
        if r == "auto":
            return [0, 0, 0], "eovolpath"
        if r.isdigit() and int(r) > 0:
            return [int(r)] * 3, "eovolpath"
    raise ValueError(f"unknown peer configuration {config!r}: heterogeneous, extremum-auto or extremum-N")


def load_scene(mi, job, config, tensors):
    """``(scene, extremum structure or None)``: the benchmark scene
    (`mi_amr.bench.harness.bench_scene`) with the configuration's medium;
    ``tensors``: the (sigma_t, albedo) TensorXf."""
    T = mi.ScalarTransform4f
    extremum_res, integrator = config_parts(config)
    filter_type = job.get("filter_type", "nearest")
    sigma = mi.load_dict({"type": "gridvolume", "data": tensors[0], "filter_type": filter_type})
    albedo = mi.load_dict({"type": "gridvolume", "data": tensors[1], "filter_type": filter_type})
    scale = float(job["density_scale"])
    medium = {"type": "heterogeneous", "sigma_t": sigma, "albedo": albedo, "scale": scale}
    extremum = None
    if extremum_res is not None:
        # the structure bounds sigma_t * scale: it takes the medium's scale
        # (as heterogeneous does for its default extremum_global); it shares
        # the medium's sigma_t volume object
        extremum = mi.load_dict({"type": "extremum_grid", "volume": sigma, "resolution": extremum_res,
                                 "scale": scale})
        medium["extremum"] = extremum
    s = job.get("scene", {})
    res = int(job["resolution"])
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": int(job["max_depth"])},
        "sensor": {"type": "perspective", "fov": s.get("fov", 38),
                   "to_world": T().look_at(s.get("origin", [1.7, 1.25, 2.4]), s.get("target", [0.5, 0.47, 0.5]),
                                           s.get("up", [0, 1, 0])),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": s.get("env", [0.5, 0.55, 0.65])}},
        "sun": {"type": "directional", "direction": s.get("sun_direction", [-0.5, -1.0, -0.35]),
                "irradiance": {"type": "rgb", "value": s.get("sun_irradiance", 2.5)}},
        "volume": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                   "bsdf": {"type": "null"}, "interior": medium}})
    return scene, extremum


def extremum_resolution(mi, scene):
    """The extremum grid's resolution [x, y, z] in ``scene``, or None."""
    for k, v in mi.traverse(scene).items():
        if k.endswith("extremum_structure.resolution"):
            return [int(x) for x in np.array(v).ravel()]
    return None


def process_cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def wait_idle(slice_s: float = 0.02, busy_share: float = 0.25, limit_s: float = 2.0) -> float:
    """As `mi_amr.bench.harness.wait_idle`: wait until this process uses less
    than ``busy_share`` of a core over a ``slice_s`` slice (at most ``limit_s``)."""
    t_start = time.perf_counter()
    while True:
        c0, t0 = process_cpu_seconds(), time.perf_counter()
        time.sleep(slice_s)
        if process_cpu_seconds() - c0 < busy_share * (time.perf_counter() - t0):
            break
        if time.perf_counter() - t_start > limit_s:
            break
    return time.perf_counter() - t_start


def frame_function(mi, dr, spp: int, frozen: bool):
    """``frame(scene, seed)`` -> float64 image, plain or ``dr.freeze``-recorded
    (as `mi_amr.bench.harness.frame_function`)."""
    if not frozen:
        return lambda scene, seed: np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)

    @dr.freeze
    def render(scene, seed):
        return mi.render(scene, spp=spp, seed=seed)

    return lambda scene, seed: np.array(render(scene, dr.opaque(mi.UInt32, seed)), dtype=np.float64)


def run(job: dict, out: Path) -> dict:
    variant = job.get("variant") or DEFAULT_VARIANT
    mi.set_variant(variant)
    out.mkdir(parents=True, exist_ok=True)
    tensors = (mi.TensorXf(np.ascontiguousarray(job["sigma_t"])), mi.TensorXf(np.ascontiguousarray(job["albedo"])))
    configs = list(job["configs"])
    frozen = bool(job["frozen"]) and hasattr(dr, "freeze")
    note = None
    if job["frozen"] and not frozen:
        note = f"drjit {dr.__version__} has no dr.freeze: plain frames timed"
    spp, rounds = int(job["spp"]), int(job["rounds"])
    recs = {c: {"frame_seconds": [], "load_seconds": [], "integrator": config_parts(c)[1],
                "extremum_resolution": None, "automatic": config_parts(c)[0] == [0, 0, 0]} for c in configs}
    acc = {c: None for c in configs}
    frames = {c: [] for c in configs}
    if frozen:
        # every configuration frozen, or none (a fair comparison within the
        # peer): eradiate-mitsuba 0.5.0's extremum structures declare no
        # traversal callback, so dr.freeze cannot record eovolpath's virtual
        # call on them ("validate(): The frozen function included a virtual
        # function call ...")
        for c in configs:
            scene, extremum = load_scene(mi, job, c, tensors)
            try:
                frame_function(mi, dr, spp, True)(scene, 49_999)
            except Exception as e:
                frozen = False
                cause = e.__cause__ or e
                note = (f"dr.freeze cannot record {c} ({type(cause).__name__}: "
                        f"{str(cause).splitlines()[0][:200]}...): every configuration timed as plain frames")
                print(f"peer_eradiate: {note}", file=sys.stderr, flush=True)
                break
            finally:
                del scene, extremum
                gc.collect()
    for r in range(rounds):
        for c in configs:
            t0 = time.perf_counter()
            scene, extremum = load_scene(mi, job, c, tensors)
            recs[c]["load_seconds"].append(time.perf_counter() - t0)
            recs[c]["extremum_resolution"] = extremum_resolution(mi, scene)
            frame = frame_function(mi, dr, spp, frozen)
            for w in range(FROZEN_WARMUP if frozen else 1):
                frame(scene, 50_000 + 10 * r + w)
            wait_idle()
            t0 = time.perf_counter()
            img = frame(scene, r)
            recs[c]["frame_seconds"].append(time.perf_counter() - t0)
            acc[c] = img if acc[c] is None else acc[c] + img
            if job.get("save_frames"):
                frames[c].append(img)
            del scene, extremum, frame, img
            gc.collect()
            print(f"peer_eradiate: round {r} {c:16s} {recs[c]['frame_seconds'][-1] * 1e3:8.1f} ms", flush=True)
    for c in configs:
        np.save(out / f"{c}.npy", acc[c] / rounds)
        recs[c]["image"] = f"{c}.npy"
        if job.get("save_frames"):
            np.save(out / f"{c}.frames.npy", np.stack(frames[c]))
    result = {"peer": "eradiate",
              "versions": {"eradiate-mitsuba": importlib.metadata.version("eradiate-mitsuba"),
                           "mitsuba": mi.__version__, "drjit": dr.__version__, "variant": variant},
              "frozen": frozen, "frozen_requested": bool(job["frozen"]), "note": note,
              "spp": spp, "rounds": rounds, "resolution": int(job["resolution"]),
              "grid_shape": list(job["sigma_t"].shape[:3]), "configs": recs}
    (out / "peer.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print(__doc__.strip().splitlines()[2], file=sys.stderr)
        return 2
    run(read_job(argv[0]), Path(argv[1]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
