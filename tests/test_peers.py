"""The optional benchmark peer (Eradiate's Mitsuba fork, mi_amr/bench/peers.py
and the standalone mi_amr/bench/peer_eradiate.py). Everything but the last
test runs without the fork's environment; the end-to-end run needs
``make peers`` (.venv-eradiate) and is marked slow."""

import argparse
import importlib.util
import json
import os
import subprocess

from pathlib import Path

import numpy as np
import pytest

import mi_amr
import mitsuba as mi
from mi_amr.testing import block_z_scores, render_passes
from mi_amr.bench import peers
from mi_amr.bench.harness import bench_scene
from mi_amr.reference import baked_grids, reference_medium

from conftest import random_amr


def load_peer_script():
    """peer_eradiate.py as a module, from its path (it imports numpy only at
    module level: the fork's mitsuba is imported when it runs)."""
    spec = importlib.util.spec_from_file_location("peer_eradiate_under_test", peers.ERADIATE_SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test01_job_round_trip(tmp_path):
    pe = load_peer_script()
    assert pe.JOB_VERSION == peers.JOB_VERSION
    rng = np.random.default_rng(1)
    s = rng.random((5, 6, 7, 1), dtype=np.float32)
    a = rng.random((5, 6, 7, 3), dtype=np.float32)
    path = peers.write_job(tmp_path / "job.bin", s, a, density_scale=60.0, resolution=48, spp=4, max_depth=64,
                           rounds=3, configs=peers.ERADIATE_CONFIGS, frozen=True)
    assert path == tmp_path / "job.bin"                      # no .npz appended
    job = pe.read_job(path)
    assert job["sigma_t"].dtype == np.float32 and np.array_equal(job["sigma_t"], s)
    assert np.array_equal(job["albedo"], a)
    assert job["density_scale"] == 60.0 and job["resolution"] == 48 and job["spp"] == 4
    assert job["max_depth"] == 64 and job["rounds"] == 3 and job["frozen"] is True
    assert job["configs"] == list(peers.ERADIATE_CONFIGS) and job["variant"] == "llvm_ad_rgb"
    assert job["filter_type"] == "nearest" and job["scene"] == peers.SCENE
    assert pe.config_parts("heterogeneous") == (None, "volpath")
    assert pe.config_parts("extremum-auto") == ([0, 0, 0], "eovolpath")
    assert pe.config_parts("extremum-32") == ([32, 32, 32], "eovolpath")
    for bad in ("extremum-0", "extremum-x", "grid"):
        with pytest.raises(ValueError, match="unknown peer configuration"):
            pe.config_parts(bad)
    with pytest.raises(ValueError, match="expected"):
        peers.write_job(tmp_path / "bad", s, a[..., :2], density_scale=1, resolution=8, spp=1, max_depth=8,
                        rounds=1)


def job_is_reference(job: dict, cells, tf, scale: float, method: str):
    """A peer job holds what `reference_medium` gives Mitsuba for the same
    cells, TF, scale and reconstruction: the same grids, bit for bit, its
    density scale and its ``gridvolume`` filter."""
    med = reference_medium(cells, tf, scale, method)
    assert np.array_equal(job["sigma_t"], np.array(med["sigma_t"]["data"]))
    assert np.array_equal(job["albedo"], np.array(med["albedo"]["data"]))
    assert job["density_scale"] == med["scale"] and job["filter_type"] == med["sigma_t"]["filter_type"]


def test02_job_grids_are_the_references(llvm, tmp_path, monkeypatch):
    """The job `peers.run_peers` builds for the fork (read back as the
    peer reads it) holds the reference's grids, scale and filter and the
    benchmark's settings; a failed peer run costs its rows, each with the
    reason. The peer itself is not run here (its launcher hands the job
    back; test06 runs it end to end): the check fails on a job of another
    TF or another reconstruction."""
    pe = load_peer_script()
    cells = random_amr(2, n=8, levels=2)
    tf = mi_amr.TransferFunction.preset("spiky", cells.value_range)
    jobs = []

    def launcher(job, out, timeout, venv=None):
        jobs.append(pe.read_job(job))
        raise RuntimeError("eradiate peer failed (not run in this test)")
    monkeypatch.setattr(peers, "eradiate_python", lambda venv=None: Path("/no/such/python"))
    monkeypatch.setattr(peers, "run_eradiate", launcher)
    args = argparse.Namespace(reconstruction="nearest", memory_limit=1.0, frozen=True, res=24, spp=3,
                              max_depth=17, repeats=2)
    rows = peers.run_peers(["eradiate"], "d", "spiky", cells, tf, 10.0, args, np.zeros((24, 24, 3)), [], tmp_path)
    assert [r["config"] for r in rows] == [f"eradiate/{c}" for c in peers.ERADIATE_CONFIGS]
    assert all("not run in this test" in r["skipped"] for r in rows)
    (job,) = jobs
    job_is_reference(job, cells, tf, 10.0, "nearest")
    assert (job["resolution"], job["spp"], job["max_depth"], job["rounds"], job["frozen"]) == (24, 3, 17, 2, True)
    assert job["configs"] == list(peers.ERADIATE_CONFIGS) and job["scene"] == peers.SCENE
    with pytest.raises(AssertionError):                  # another TF's grids
        job_is_reference(job, cells, mi_amr.TransferFunction.preset("foggy", cells.value_range), 10.0, "nearest")
    with pytest.raises(AssertionError):                  # another reconstruction's
        job_is_reference(job, cells, tf, 10.0, "tent")


def test03_scene_matches_bench_scene(llvm):
    """peers.SCENE mirrors bench.bench_scene (the peer cannot import it)."""
    d = bench_scene({"type": "homogeneous"}, 16, {"type": "volpath"})
    T = mi.ScalarTransform4f
    S = peers.SCENE
    cam = T().look_at(S["origin"], S["target"], S["up"])
    assert np.allclose(np.array(d["sensor"]["to_world"].matrix), np.array(cam.matrix))
    assert d["sensor"]["fov"] == S["fov"]
    assert d["env"]["radiance"]["value"] == S["env"]
    assert d["sun"]["direction"] == S["sun_direction"] and d["sun"]["irradiance"]["value"] == S["sun_irradiance"]
    cube = T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5)
    assert np.allclose(np.array(d["volume"]["to_world"].matrix), np.array(cube.matrix))


def test04_missing_env_says_run_make_peers(tmp_path, monkeypatch):
    with pytest.raises(peers.PeerUnavailable, match="run make peers"):
        peers.eradiate_python(tmp_path / "no-venv")
    monkeypatch.setattr(peers, "ERADIATE_VENV", tmp_path / "no-venv")
    args = argparse.Namespace(reconstruction="nearest", memory_limit=1.0, frozen=True, res=8, spp=1,
                              max_depth=8, repeats=1, variant="llvm_ad_rgb")
    with pytest.raises(peers.PeerUnavailable, match=r"\.venv-eradiate|no-venv"):
        peers.run_peers(["eradiate"], "d", "spiky", random_amr(1, n=8, levels=2), None, 1.0, args,
                        np.zeros((8, 8, 3)), [], tmp_path)
    assert peers.run_peers(None, "d", "spiky", None, None, 1.0, args, None, [], tmp_path) == []


def test05_peer_records(tmp_path):
    """Records from a peer.json: RMSE over the timed frames, efficiencies."""
    ref = np.full((4, 4, 3), 0.5)
    rng = np.random.default_rng(3)
    configs = {}
    for c, noise, t in (("heterogeneous", 0.2, [2.0, 1.0, 3.0]), ("extremum-auto", 0.1, [1.0, 1.0, 1.0])):
        fr = ref + noise * rng.standard_normal((3, 4, 4, 3))
        np.save(tmp_path / f"{c}.frames.npy", fr)
        np.save(tmp_path / f"{c}.npy", fr.mean(axis=0))
        configs[c] = {"frame_seconds": t, "load_seconds": [0.1] * 3, "integrator": "x", "image": f"{c}.npy",
                      "automatic": c.endswith("auto"), "extremum_resolution": [4, 5, 6] if c != "heterogeneous" else None}
    result = {"configs": configs, "spp": 2, "frozen": False, "versions": {}, "note": None}
    recs = peers.peer_records(result, tmp_path, ref, {"efficiency": 2.0}, {"dataset": "d", "tf": "t"}, 100)
    h, e = recs
    assert h["config"] == "eradiate/heterogeneous" and e["config"] == "eradiate/extremum-auto (R=4x5x6)"
    fr = np.load(tmp_path / "heterogeneous.frames.npy")
    mse = np.mean([np.mean((f - ref) ** 2) for f in fr])
    assert h["seconds_per_frame"] == 2.0 and h["rmse"] == pytest.approx(mse ** 0.5)
    assert h["efficiency"] == pytest.approx(1 / (mse * 2.0))
    assert h["efficiency_vs_reference"] == pytest.approx(h["efficiency"] / 2.0)
    assert h["efficiency_vs_own_heterogeneous"] == pytest.approx(1.0)
    assert e["efficiency_vs_own_heterogeneous"] == pytest.approx(e["efficiency"] / h["efficiency"])
    assert e["structure_bytes"] == 100 + 8 * 120 and h["dataset"] == "d"


@pytest.mark.slow
@pytest.mark.skipif(not (peers.ERADIATE_VENV / "bin" / "python").exists(),
                    reason="no .venv-eradiate (make peers)")
def test06_eradiate_peer_matches_reference(llvm, tmp_path, monkeypatch):
    """End to end at 32x32, 4 spp: the fork's heterogeneous (and its
    extremum_grid in eovolpath) agree with our reference in expectation
    (8x8-block z-scores of 8 independent passes each). Paths are given
    relative, as the benchmark's ``--out`` often is (the peer runs in its
    output folder)."""
    monkeypatch.chdir(tmp_path)
    cells = random_amr(3, n=16, levels=3, quantize=5)
    tf = mi_amr.TransferFunction.preset("foggy", cells.value_range)
    scale = 100.0
    s, a = baked_grids(cells, tf, "nearest")
    job = peers.write_job(tmp_path / "job.npz", s, a, density_scale=scale, resolution=32, spp=4, max_depth=64,
                          rounds=8, configs=["heterogeneous", "extremum-8"], frozen=False)
    result = peers.run_eradiate(Path("job.npz"), Path("."), timeout=300)
    assert result["versions"]["eradiate-mitsuba"] == "0.5.0" and result["versions"]["variant"] == "llvm_ad_rgb"
    assert result["configs"]["extremum-8"]["extremum_resolution"] == [8, 8, 8]
    scene = mi.load_dict(bench_scene(reference_medium(cells, tf, scale, "nearest"), 32,
                                     {"type": "volpath", "max_depth": 64}))
    ours = render_passes(scene, 8, 4, seed0=1000)          # seeds apart from the peer's 0..7
    assert ours.mean(axis=0)[..., 0].std() > 0.01           # not a blank image
    for c in ("heterogeneous", "extremum-8"):
        theirs = np.load(tmp_path / f"{c}.frames.npy")
        assert theirs.shape == (8, 32, 32, 3)
        assert np.allclose(np.load(tmp_path / f"{c}.npy"), theirs.mean(axis=0))
        assert np.abs(block_z_scores(ours, theirs, 8)).max() < 4.0, c
