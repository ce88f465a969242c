"""Optional benchmark peers: other renderers on the same field and scene.

``python -m mi_amr.bench --peers eradiate`` renders each data set x TF case
also with Eradiate's Mitsuba fork (``eradiate-mitsuba`` 0.5.0: its
``heterogeneous`` medium with a nested ``extremum_grid`` majorant grid in its
``eovolpath`` integrator). The fork pins Dr.Jit 1.2.0, so it runs in its own
virtual environment (``make peers`` -> ``.venv-eradiate``) as a separate
process, `mi_amr/bench/peer_eradiate.py`, fed a job file: the reference's
dense grids with the TF baked in (`reference.baked_grids`) and the
benchmark's scene parameters. Its frames are timed like ours
(`protocol.alternate_passes`: rounds of A B C, warm-up frames, one timed frame
per pass, one scene alive) but in that other process, so they are not
interleaved with our configurations' frames: compare within the peer
(``efficiency_vs_own_heterogeneous``) first, and across processes
(``efficiency_vs_reference``, against our ``reference`` record of the same
case) with that in mind.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from .._llvm import find_llvm19
from ..reconstruction import reconstruction_method
from ..reference import baked_grids

ROOT = Path(__file__).resolve().parents[2]
PEERS = ("eradiate",)
ERADIATE_VENV = ROOT / ".venv-eradiate"
ERADIATE_SCRIPT = Path(__file__).with_name("peer_eradiate.py")
#: The peer's configurations: its normaliser, the adaptive grid and fixed grids.
ERADIATE_CONFIGS = ("heterogeneous", "extremum-auto", "extremum-16", "extremum-32", "extremum-64")
#: Job file layout version (`peer_eradiate.JOB_VERSION`).
JOB_VERSION = 1
#: The benchmark view of `harness.bench_scene`, as plain numbers for the peer
#: (tests/test_peers.py checks that the two agree).
SCENE = {"origin": [1.7, 1.25, 2.4], "target": [0.5, 0.47, 0.5], "up": [0, 1, 0], "fov": 38,
         "env": [0.5, 0.55, 0.65], "sun_direction": [-0.5, -1.0, -0.35], "sun_irradiance": 2.5}


class PeerUnavailable(RuntimeError):
    """A peer's environment is missing."""


def write_job(path, sigma_t, albedo, *, density_scale: float, resolution: int, spp: int, max_depth: int,
              rounds: int, configs=ERADIATE_CONFIGS, frozen: bool = True, variant: str = "llvm_ad_rgb",
              filter_type: str = "nearest", save_frames: bool = True, scene: dict | None = None) -> Path:
    """Write a peer job (read by `peer_eradiate.read_job`): the two grids
    (float32 ``[nz, ny, nx, 1]`` and ``[nz, ny, nx, 3]``) and a JSON ``meta``."""
    sigma_t = np.ascontiguousarray(sigma_t, dtype=np.float32)
    albedo = np.ascontiguousarray(albedo, dtype=np.float32)
    if sigma_t.ndim != 4 or sigma_t.shape[3] != 1 or albedo.shape != sigma_t.shape[:3] + (3,):
        raise ValueError(f"sigma_t {sigma_t.shape} / albedo {albedo.shape}: expected [nz,ny,nx,1] / [nz,ny,nx,3]")
    meta = {"version": JOB_VERSION, "density_scale": float(density_scale), "resolution": int(resolution),
            "spp": int(spp), "max_depth": int(max_depth), "rounds": int(rounds), "configs": list(configs),
            "frozen": bool(frozen), "variant": variant, "filter_type": filter_type,
            "save_frames": bool(save_frames), "scene": dict(SCENE if scene is None else scene)}
    path = Path(path)
    with open(path, "wb") as f:                 # np.savez would append .npz to other names
        np.savez(f, sigma_t=sigma_t, albedo=albedo, meta=np.array(json.dumps(meta)))
    return path


def eradiate_python(venv: Path | None = None) -> Path:
    """The peer environment's interpreter; `PeerUnavailable` when missing."""
    venv = Path(venv or ERADIATE_VENV)
    py = venv / "bin" / "python"
    if not py.exists():
        raise PeerUnavailable(f"the eradiate peer needs {venv} (Eradiate's Mitsuba fork, eradiate-mitsuba "
                              f"0.5.0, in its own environment): run make peers")
    return py


def run_eradiate(job: Path, out: Path, timeout: float, venv: Path | None = None) -> dict:
    """Run `peer_eradiate.py` on a job in the peer environment; returns its
    ``peer.json``. Raises `PeerUnavailable`, or RuntimeError on a failed or
    timed-out run (with the tail of its output)."""
    py = eradiate_python(venv)
    job, out = Path(job).resolve(), Path(out).resolve()     # the peer runs in ``out``
    env = dict(os.environ)
    if "DRJIT_LIBLLVM_PATH" not in env:
        if find_llvm19():
            env["DRJIT_LIBLLVM_PATH"] = find_llvm19()
    env.pop("PYTHONPATH", None)                 # nothing of this environment's Mitsuba
    cmd = [str(py), str(ERADIATE_SCRIPT), str(job), str(out)]
    try:
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, cwd=str(out))
    except subprocess.TimeoutExpired as e:
        raise RuntimeError(f"eradiate peer: no result within {timeout:.0f} s ({' '.join(cmd)})") from e
    if r.returncode != 0 or not (out / "peer.json").exists():
        tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-15:])
        raise RuntimeError(f"eradiate peer failed (exit {r.returncode}, "
                           f"{'no' if not (out / 'peer.json').exists() else 'a'} peer.json): {' '.join(cmd)}\n{tail}")
    return json.loads((out / "peer.json").read_text())


def peer_records(result: dict, out: Path, ref_img, reference=None, base: dict | None = None,
                 grid_bytes: int = 0) -> list[dict]:
    """Benchmark records of a peer run: per configuration the median frame
    time, the RMSE over its timed frames against ``ref_img`` (the mean
    per-frame MSE, as `protocol.apply_timing`), ``1 / (MSE x seconds)``, and
    that efficiency against ``reference`` (our ``reference`` record of the
    case) and against the peer's own ``heterogeneous``."""
    recs = []
    for config, c in result["configs"].items():
        frames = np.load(out / f"{config}.frames.npy") if (out / f"{config}.frames.npy").exists() else None
        if frames is None:                      # only the mean: its MSE stands for the frames'
            frames = np.load(out / c["image"])[None]
        mses = [float(np.mean((f - ref_img) ** 2)) for f in frames]
        times = c["frame_seconds"]
        seconds, mse = statistics.median(times), float(sum(mses) / len(mses))
        res = c.get("extremum_resolution")
        name = f"eradiate/{config}"
        if c.get("automatic") and res:
            name += f" (R={'x'.join(str(x) for x in res)})"
        rec = dict(base or {})
        rec.update(config=name, peer="eradiate", peer_config=config, versions=result["versions"],
                   frozen=result["frozen"], peer_note=result.get("note"), spp=result["spp"],
                   seconds_per_frame=seconds, seconds_per_spp=seconds / result["spp"], frame_seconds=list(times),
                   rmse=mse ** 0.5, efficiency=1.0 / (mse * seconds) if mse > 0 else float("inf"),
                   build_s=statistics.median(c["load_seconds"]), curve=[], mean=float(np.mean(frames)),
                   integrator=c["integrator"], extremum_resolution=res,
                   resolved=(f"{c['integrator']}, extremum_grid {'x'.join(str(x) for x in res)}"
                             if res else f"{c['integrator']}, extremum_global"),
                   lookups_per_collision=None, null_per_collision=None, lookups_per_shadow_ray=None,
                   structure_bytes=grid_bytes + (8 * int(np.prod(res)) if res else 0), majorant_update_s=None)
        recs.append(rec)
    own = next((r for r in recs if r["peer_config"] == "heterogeneous"), None)
    ref_eff = reference.get("efficiency") if reference else None
    for rec in recs:
        rec["efficiency_vs_reference"] = rec["efficiency"] / ref_eff if ref_eff else None
        rec["efficiency_vs_own_heterogeneous"] = (rec["efficiency"] / own["efficiency"]
                                                  if own and own.get("efficiency") else None)
    return recs


def run_peers(peers, name, tf_name, cells, tf, scale, args, ref_img, measured, out) -> list[dict]:
    """The peers' records of one benchmark case (data set ``name`` x TF):
    nothing when ``peers`` is empty. ``measured``: our records of the case
    (their ``reference`` normalises ``efficiency_vs_reference``); ``out``:
    the results folder (the peer's files go to ``out/peers/<name>-<tf>``)."""
    if not peers:
        return []
    recs = []
    for peer in peers:
        if peer != "eradiate":
            raise ValueError(f"unknown peer {peer!r}: one of {PEERS}")
        eradiate_python()                        # fail before the resampling when missing
        method = reconstruction_method(args.reconstruction)
        base = {"dataset": name, "tf": tf_name, "cells": len(cells), "density_scale": scale}
        peer_out = Path(out) / "peers" / f"{name}-{tf_name}"
        peer_out.mkdir(parents=True, exist_ok=True)
        try:
            sigma_t, albedo = baked_grids(cells, tf, method, memory_limit=int(args.memory_limit * 2**30))
        except MemoryError as e:
            return [dict(base, config=f"eradiate/{c}", skipped=str(e)) for c in ERADIATE_CONFIGS]
        frozen = bool(getattr(args, "frozen", False))
        with tempfile.TemporaryDirectory() as tmp:
            job = write_job(Path(tmp) / "job.npz", sigma_t, albedo, density_scale=scale, resolution=args.res,
                            spp=args.spp, max_depth=args.max_depth, rounds=args.repeats, frozen=frozen,
                            variant="llvm_ad_rgb",     # the wheel's only JIT rgb variant (no CUDA ones)
                            filter_type=method.grid_filter)
            # a generous limit: five configurations x rounds x (warm-up + timed) frames
            timeout = 900 + 120 * args.repeats * len(ERADIATE_CONFIGS)
            try:
                result = run_eradiate(job, peer_out, timeout)
            except PeerUnavailable:
                raise
            except RuntimeError as e:            # a failed peer run costs its rows, not the benchmark
                print(f"{name:8s} {tf_name:6s} eradiate peer skipped: {e}", file=sys.stderr, flush=True)
                return [dict(base, config=f"eradiate/{c}", skipped=str(e).splitlines()[0])
                        for c in ERADIATE_CONFIGS]
        reference = next((r for r in measured if r.get("config") == "reference" and "skipped" not in r), None)
        rows = peer_records(result, peer_out, ref_img, reference, base, grid_bytes=sigma_t.nbytes + albedo.nbytes)
        for rec in rows:
            rel = rec["efficiency_vs_reference"]
            own = rec["efficiency_vs_own_heterogeneous"]
            print(f"{name:8s} {tf_name:6s} {rec['config']:24s} {rec['seconds_per_spp'] * 1e3:8.2f} ms/spp "
                  f"rmse {rec['rmse']:.4f} eff x{rel if rel is not None else float('nan'):6.2f} "
                  f"(x{own if own is not None else float('nan'):5.2f} vs its heterogeneous) "
                  f"build {rec['build_s']:6.2f}s", flush=True)
        recs += rows
    return recs
