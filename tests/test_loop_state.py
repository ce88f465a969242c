"""Symbolic loops are recorded once (docs/design.md section 6).

Dr.Jit records a symbolic loop a second time when its state holds a
variable the body leaves unchanged, and every loop nested in it is then
recorded once per recording of its parent: the per-frame tracing cost of
``amrvolpath`` doubles at each level. These tests render with every leaf
kind, both reconstructions and both estimator settings, and count how often
each loop body is traced per loop: once for every loop, and at most twice
for the integrator's path loop where the scene's sampler is not the
independent one (that loop then carries the Mitsuba sampler, whose stream
increment never changes).
"""

from collections import defaultdict

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr

from conftest import random_amr, volume_scene

CONFIGS = [("grid", "hash", {"grid_refinement": 1}), ("grid", "hash", {"grid_refinement": 2}),
           ("kdtree", "hash", {}), ("abr", "abr", {}), ("brick", "brick", {}), ("grid", "brick", {})]


class BodyCounter:
    """Wraps ``dr.while_loop``: body traces per loop call, by label."""

    def __init__(self, monkeypatch):
        self.calls = defaultdict(list)
        original = dr.while_loop

        def counting(state, cond, body, *args, label=None, **kw):
            n = [0]

            def counted(*st):
                n[0] += 1
                return body(*st)
            out = original(state, cond, counted, *args, label=label, **kw)
            self.calls[label].append(n[0])
            return out
        monkeypatch.setattr(dr, "while_loop", counting)

    def check(self, what, path_limit=1):
        assert self.calls, f"{what}: no symbolic loop was traced"
        for label, counts in self.calls.items():
            limit = path_limit if label == "amrvolpath" else 1
            assert max(counts) <= limit, (f"{what}: loop {label!r} traced its body {max(counts)} times "
                                          f"(at most {limit}): its state holds a variable it never changes")


def medium_dict(traversal, sampling, reconstruction, **kw):
    cells = random_amr(seed=3, n=16, levels=3)
    return {"type": "amr", "data": cells, "transfer_function": mi_amr.TransferFunction.preset("foggy", cells.value_range),
            "density_scale": 20.0, "reconstruction": reconstruction, "traversal": traversal,
            "sampling": sampling, "grid_resolution": 4, **kw}


@pytest.mark.parametrize("traversal,sampling,kw", CONFIGS)
@pytest.mark.parametrize("reconstruction", [pytest.param("nearest", marks=pytest.mark.slow), "tent"])
@pytest.mark.parametrize("minorants", [False, True])
def test01_amrvolpath_loops_traced_once(llvm, monkeypatch, traversal, sampling, kw, reconstruction, minorants):
    scene = mi.load_dict(volume_scene(medium_dict(traversal, sampling, reconstruction, **kw),
                                      res=8, integrator="amrvolpath"))
    integ = scene.integrator()
    integ.residual = integ.decomposition = minorants
    counter = BodyCounter(monkeypatch)
    img = np.array(mi.render(scene, spp=1))
    assert np.isfinite(img).all()
    counter.check(f"{traversal}/{sampling} {reconstruction} minorants={minorants}")
    assert {"amrvolpath", "amrvolpath_shadow", "amr_track"} <= set(counter.calls)


def test02_other_media_and_stock_volpath(llvm, monkeypatch):
    """A second, non-amr medium (the shadow loop's own random stream feeds
    its sample_interaction) and the ray majorant of stock volpath."""
    scene_d = volume_scene(medium_dict("grid", "hash", "nearest"), res=8, integrator="amrvolpath")
    scene_d["fog"] = {"type": "sphere", "center": [0.5, 0.5, 1.6], "radius": 0.3, "bsdf": {"type": "null"},
                      "interior": {"type": "homogeneous", "sigma_t": 2.0, "albedo": 0.8}}
    counter = BodyCounter(monkeypatch)
    assert np.isfinite(np.array(mi.render(mi.load_dict(scene_d), spp=1))).all()
    counter.check("amrvolpath with a homogeneous medium")

    counter = BodyCounter(monkeypatch)
    scene = mi.load_dict(volume_scene(medium_dict("grid", "hash", "nearest", majorant="ray"), res=8))
    assert np.isfinite(np.array(mi.render(scene, spp=1))).all()
    assert "amr_span_majorant" in counter.calls
    counter.check("volpath with majorant=ray")


@pytest.mark.parametrize("sampler", ["stratified", "ldsampler"])
def test03_other_samplers(llvm, monkeypatch, sampler):
    """A sampler other than the independent one draws every number of the
    path itself (the path loop carries it and may be recorded twice); its
    image agrees with the independent sampler's within Monte Carlo error."""
    scene_d = volume_scene(medium_dict("grid", "hash", "nearest"), res=8, integrator="amrvolpath")
    scene_d["sensor"]["sampler"] = {"type": sampler, "sample_count": 64}
    counter = BodyCounter(monkeypatch)
    img = np.array(mi.render(mi.load_dict(scene_d), spp=64), dtype=np.float64)
    counter.check(f"amrvolpath with a {sampler} sampler", path_limit=2)
    scene_d["sensor"]["sampler"] = {"type": "independent", "sample_count": 64}
    scene = mi.load_dict(scene_d)
    means = np.array([np.array(mi.render(scene, spp=64, seed=s), dtype=np.float64).mean() for s in range(8)])
    se = means.std(ddof=1)          # one frame's standard error (of its mean over pixels)
    assert abs(img.mean() - means.mean()) < 4.5 * se * np.sqrt(1 + 1 / 8), (img.mean(), means, se)


@pytest.mark.parametrize("mode", ["emission_absorption", "single"])
def test04_lighting_modes(llvm, monkeypatch, mode):
    """The cheap lighting modes of amrvolpath (docs/design.md section 6d)
    record their loops once too."""
    scene_d = volume_scene(medium_dict("grid", "hash", "tent"), res=8, integrator="amrvolpath")
    scene_d["integrator"]["mode"] = mode
    counter = BodyCounter(monkeypatch)
    assert np.isfinite(np.array(mi.render(mi.load_dict(scene_d), spp=1))).all()
    counter.check(f"amrvolpath mode={mode}")
    assert {"amrvolpath", "amr_track"} <= set(counter.calls)
