"""Sample-parallel rendering (mi_amr.distributed): chunks merged from the
film's weighted sums, in this process and on a Dask LocalCluster."""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mi_amr import distributed as D
from mi_amr.testing import block_z_scores
from mi_amr.images import read_exr

from conftest import cloud_scene_xml, random_amr, volume_scene

ROOT = Path(__file__).resolve().parents[1]
pytest.importorskip("dask.distributed")


def _scene_dict(res=24, rfilter="box", seed=2):
    s = volume_scene({"type": "amr", "data": random_amr(seed, levels=3), "transfer_function": "spiky",
                      "density_scale": 30.0}, res=res, integrator="amrvolpath")
    s["sensor"]["film"]["rfilter"] = {"type": rfilter}
    return s


def _scene_xml(tmp_path):
    return cloud_scene_xml(tmp_path, data=random_amr(2, levels=3))


@pytest.fixture(scope="module")
def client():
    c = D.local_cluster(2)
    yield c
    cluster = c.cluster
    c.close()
    cluster.close()


def test01_chunk_plan_and_seeds():
    assert D.chunk_plan(10, 4) == [4, 3, 3]
    assert D.chunk_plan(3, 16) == [3]
    assert sum(D.chunk_plan(1000, 7)) == 1000
    seeds = D.chunk_seeds(3, 5) + D.chunk_seeds(4, 5)
    assert len(set(seeds)) == 10
    with pytest.raises(ValueError, match="spp"):
        D.chunk_plan(0)
    with pytest.raises(ValueError, match="chunks"):
        D.chunk_plan(10**6, 1)
    with pytest.raises(ValueError, match="seed"):
        D.chunk_seeds(-1, 2)


def test02_merge_divides_summed_sums_by_summed_weights():
    """Two chunks whose pixels got different filter weights: the merge is
    (s1 + s2) / (w1 + w2), not the mean of the two normalised images."""
    a = np.array([[[2.0, 4.0, 6.0, 2.0]]], np.float32)          # value (1, 2, 3), weight 2
    b = np.array([[[3.0, 3.0, 3.0, 1.0]]], np.float32)          # value (3, 3, 3), weight 1
    np.testing.assert_allclose(D.merge([a, b])[0, 0], [5 / 3, 7 / 3, 3.0], rtol=1e-6)
    assert D.merge([np.zeros((1, 1, 4), np.float32)])[0, 0].tolist() == [0, 0, 0]


def test03_one_chunk_is_one_mitsuba_render(llvm):
    """Equal to float rounding: the film adds overlapping filter splats with
    atomics, in an order that varies between runs."""
    scene = mi.load_dict(_scene_dict(rfilter="gaussian"))
    local = np.array(D.render_local(scene, 8, chunk_spp=8, seed=5))
    ref = np.array(mi.render(scene, spp=8, seed=D.chunk_seeds(5, 1)[0]))
    np.testing.assert_allclose(local, ref, rtol=1e-5, atol=1e-6)
    assert local.std() > 0


def test04_chunks_agree_with_one_render_for_a_wide_filter(llvm):
    """Gaussian filter: 4 chunks of 4 spp merged, against single renders of
    16 spp (other seeds): per-block means agree within 5 standard errors."""
    scene = mi.load_dict(_scene_dict(res=32, rfilter="gaussian"))
    a = np.stack([np.array(D.render_local(scene, 16, chunk_spp=4, seed=s)) for s in range(6)])
    b = np.stack([np.array(mi.render(scene, spp=16, seed=1000 + s)) for s in range(6)])
    z = block_z_scores(a, b)
    assert np.abs(z).max() < 5, np.abs(z).max()


def test05_cluster_equals_local(llvm, client, tmp_path):
    """Same seeds, same chunks: a scene dictionary (its AMR data and
    transforms pickled once to each worker) and an XML scene (data read on
    the workers) render on two worker processes as in this process."""
    d = _scene_dict()
    remote = np.array(D.render(d, 12, client=client, chunk_spp=3, seed=7))
    local = np.array(D.render_local(d, 12, chunk_spp=3, seed=7))
    np.testing.assert_allclose(remote, local, rtol=1e-5, atol=1e-6)
    assert local.std() > 0
    xml = _scene_xml(tmp_path)
    remote = np.array(D.render(str(xml), 8, client=client, chunk_spp=2, seed=1, res="20", tf="spiky"))
    local = np.array(D.render_local(str(xml), 8, chunk_spp=2, seed=1, params={"res": "20", "tf": "spiky"}))
    assert remote.shape == (20, 20, 3)
    np.testing.assert_allclose(remote, local, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test06_a_killed_worker_loses_nothing(llvm, tmp_path):
    """Kill one of two worker processes (SIGKILL) while it renders a chunk:
    its chunk runs again elsewhere and the image equals the local render."""
    xml = _scene_xml(tmp_path)
    params = {"res": "48", "tf": "spiky"}
    c = D.local_cluster(2)
    try:
        pids = c.run(os.getpid)
        out = {}

        def work():
            try:
                out["img"] = np.array(D.render(str(xml), 48, client=c, chunk_spp=2, seed=3, **params))
            except BaseException as e:          # pragma: no cover - reported below
                out["err"] = e
        t = threading.Thread(target=work)
        t.start()
        victim = None
        deadline = time.time() + 120
        while victim is None and time.time() < deadline:     # both workers have chunks
            busy = [w for w, tasks in c.processing().items() if tasks]
            victim = busy[0] if len(busy) == 2 else None
            time.sleep(0.05)
        assert victim is not None, "the workers got no chunks"
        time.sleep(1.0)                           # scenes loaded, chunks under way
        assert c.processing().get(victim), "the victim had no chunk to lose"
        os.kill(pids[victim], signal.SIGKILL)
        t.join(300)
        assert not t.is_alive(), "render hung after a worker died"
        assert "err" not in out, out.get("err")
    finally:
        cluster = c.cluster
        c.close()
        cluster.close()
    local = np.array(D.render_local(str(xml), 48, chunk_spp=2, seed=3, params=params))
    np.testing.assert_allclose(out["img"], local, rtol=1e-5, atol=1e-6)


def test07_unreadable_data_fails_with_the_workers_error(llvm, client, tmp_path):
    xml = cloud_scene_xml(tmp_path, cells="missing.cells")
    t0 = time.time()
    with pytest.raises(Exception, match="missing.cells"):
        D.render(str(xml), 4, client=client, chunk_spp=2, res="8")
    assert time.time() - t0 < 120


def test08_unpicklable_dict_values_are_named(client):
    d = {"type": "scene", "thing": {"type": "x", "value": threading.Lock()}}
    with pytest.raises(TypeError, match=r"scene\['thing'\]\['value'\]"):
        D.render(d, 1, client=client)


@pytest.mark.slow
def test09_cli_workers_frames(tmp_path):
    """``mi-amr render --workers 2 --frames -D tf=spiky,foggy``: one EXR and
    PNG per frame, each equal to a plain render of that frame."""
    xml = _scene_xml(tmp_path)
    cmd = [sys.executable, "-m", "mi_amr.tools.cli", "render", str(xml), "--spp", "4", "-q", "-D", "res=16"]
    r = subprocess.run(cmd + ["-o", str(tmp_path / "f.exr"), "--workers", "2", "--frames", "-D", "tf=spiky,foggy"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    for k, tf in enumerate(("spiky", "foggy")):
        r = subprocess.run(cmd + ["-o", str(tmp_path / f"p{k}.exr"), "-D", f"tf={tf}"],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        framed = read_exr(tmp_path / f"f_{k:03d}.exr")
        assert (tmp_path / f"f_{k:03d}.png").is_file()
        np.testing.assert_allclose(framed, read_exr(tmp_path / f"p{k}.exr"), rtol=1e-5, atol=1e-6)
    assert not np.allclose(read_exr(tmp_path / "f_000.exr"), read_exr(tmp_path / "f_001.exr"))


def test10_import_does_not_need_dask():
    code = "import sys, mi_amr, mi_amr.distributed; print('dask' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"
