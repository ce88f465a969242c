"""The amrvolpath integrator: same expectation as volpath, every structure."""


import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.data.datasets import make_dataset
from mi_amr.testing import block_z_scores, render_passes

from conftest import volume_scene

PASSES = 32
#: Largest |z| allowed over the 36 blocks of a 24x24 image: each z has 2 x 31
#: degrees of freedom, so two equal estimators exceed 4.5 somewhere with
#: probability about 0.3% (16 passes and 4.0: about 3%, which a change of
#: random streams alone can hit).
Z_MAX = 4.5


#: Reference images (stock volpath, the same seeds) by case: the tests of one
#: data set, TF and medium options compare against the very same image, so it
#: is rendered once per test process.
REFERENCES = {}


def agree(scene_a, scene_b, spp=8, block=4, reference_key=None):
    a = render_passes(mi.load_dict(scene_a), PASSES, spp, seed0=0)
    key = None if reference_key is None else (reference_key, spp)
    b = REFERENCES.get(key) if key is not None else None
    if b is None:
        b = render_passes(mi.load_dict(scene_b), PASSES, spp, seed0=50_000)
        if key is not None:
            REFERENCES[key] = b
    assert np.isfinite(a).all() and np.isfinite(b).all()
    z = np.abs(block_z_scores(a, b, block)).max()
    assert z < Z_MAX, f"max |z| = {z:.2f}"
    return a


def surface_scene(integrator, medium):
    T = mi.ScalarTransform4f
    return {"type": "scene", "integrator": {"type": integrator, "max_depth": 24},
            "sensor": {"type": "perspective", "fov": 40, "to_world": T().look_at([0, 1, 4], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}}},
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.6, 0.7]}},
            "light": {"type": "sphere", "center": [2, 2, 1], "radius": 0.3,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 10}}},
            "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium},
            "ball": {"type": "sphere", "radius": 0.4,
                     "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.3, 0.2]}}},
            "glass": {"type": "sphere", "center": [0.5, 0.5, 0.5], "radius": 0.2, "bsdf": {"type": "dielectric"}},
            "floor": {"type": "rectangle", "to_world": T().translate([0, -1.01, 0]).rotate([1, 0, 0], -90).scale(3),
                      "bsdf": {"type": "diffuse"}}}


@pytest.mark.parametrize("kind", ["homogeneous", "heterogeneous"])
def test01_matches_volpath_without_amr_media(variant, kind):
    T = mi.ScalarTransform4f
    if kind == "homogeneous":
        med = {"type": "homogeneous", "sigma_t": 1.0, "albedo": {"type": "rgb", "value": [0.9, 0.7, 0.5]}}
    else:
        grid = np.random.default_rng(1).random((8, 8, 8, 1)).astype(np.float32)
        med = {"type": "heterogeneous", "albedo": 0.8, "scale": 2.0,
               "sigma_t": {"type": "gridvolume", "data": mi.TensorXf(grid), "to_world": T().translate(-1).scale(2)}}
    agree(surface_scene("amrvolpath", med), surface_scene("volpath", med))


DATA = {}


def dataset(name):
    if name not in DATA:
        DATA[name] = make_dataset(name, cells=2500, levels=4, seed=1)
    return DATA[name]


SCALE = {"spiky": 40.0, "foggy": 150.0}
SCALE_STADIUM = {"spiky": 600.0, "foggy": 300.0}     # a small object needs more density

# Every traversal with each brick sampling, spread over the data sets and TFs;
# the default (grid/hash) on every data set and TF. The full matrix is `slow`.
FAST = [("cloud", "spiky", "grid", "abr"), ("shell", "foggy", "abr", "brick"),
        ("cloud", "spiky", "brick", "abr"), ("cloud", "foggy", "kdtree", "brick"),
        ("shell", "spiky", "grid", "brick"), ("stadium", "foggy", "abr", "abr")]
FAST += [(d, t, "grid", "hash") for d in ("cloud", "shell", "stadium") for t in ("spiky", "foggy")]
FULL = [(d, t, tr, s) for d in ("cloud", "shell", "stadium") for t in ("spiky", "foggy")
        for tr in ("grid", "abr", "brick", "kdtree") for s in ("abr", "brick", "hash")]


def _combo(data_name, tf, traversal, sampling, **medium):
    cells = dataset(data_name)
    scale = (SCALE_STADIUM if data_name == "stadium" else SCALE)[tf]
    kw = dict(type="amr", data=cells, transfer_function=tf, density_scale=scale, **medium)
    view = {}
    if data_name == "stadium":                # zoom onto the small object
        lo, hi = cells.bounds
        i = int(np.argmax(cells.value))
        view = dict(target=(cells.pos[i] + 0.5 * cells.width[i] - lo) / (hi - lo), fov=6)
    a = agree(volume_scene(dict(kw, traversal=traversal, sampling=sampling), res=24, integrator="amrvolpath", **view),
              volume_scene(dict(kw), res=24, integrator="volpath", **view),
              reference_key=(data_name, tf, tuple(sorted(medium.items()))))
    assert a.mean(axis=0)[..., 0].std() > 0.005          # the volume is visible


@pytest.mark.parametrize("data_name,tf,traversal,sampling", FAST)
def test02_structures_agree_with_stock_volpath(llvm, data_name, tf, traversal, sampling):
    _combo(data_name, tf, traversal, sampling)


@pytest.mark.parametrize("data_name,tf,reconstruction", [("stadium", "spiky", "tent"), ("cloud", "foggy", "nearest")])
def test02b_two_level_grid_agrees_with_stock_volpath(llvm, data_name, tf, reconstruction):
    """The two-level grid (coarse macrocells of 4^3 fine ones, refined where
    the rule says) in amrvolpath, against stock volpath on the same medium."""
    _combo(data_name, tf, "grid", "hash", grid_refinement=4, reconstruction=reconstruction)


@pytest.mark.slow
@pytest.mark.parametrize("data_name,tf,traversal,sampling", [c for c in FULL if c not in FAST])
def test03_full_matrix_agrees_with_stock_volpath(llvm, data_name, tf, traversal, sampling):
    _combo(data_name, tf, traversal, sampling)


def test04_counters(llvm):
    cells = dataset("cloud")
    integ = mi.load_dict({"type": "amrvolpath", "counters": True})
    scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "spiky",
                                       "density_scale": 40.0}, res=16))
    mi.render(scene, integrator=integ, spp=4)
    c = integ.counters()
    assert c["real"] > 0 and c["steps"] > 0 and c["capped"] == 0 and c["shadow_lookups"] > 0
    assert c["lookups"] == c["null"] + c["real"]
    assert c["lookups_per_collision"] >= 1.0
    integ.reset_counters()
    assert integ.counters()["lookups"] == 0
    # an empty transfer function: no density look-up at all
    empty = mi_amr.TransferFunction(np.zeros((4, 4)), (0, 1))
    scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": empty}, res=16))
    img = np.array(mi.render(scene, integrator=integ, spp=4))
    c = integ.counters()
    assert c["lookups"] == c["shadow_lookups"] == c["steps"] == c["shadow_steps"] == 0
    assert np.isfinite(img).all()
    # counters off: nothing is counted
    off = mi.load_dict({"type": "amrvolpath"})
    mi.render(scene, integrator=off, spp=2)
    assert off.counters()["lookups"] == 0


def test05_bad_parameters(llvm):
    with pytest.raises(Exception, match="unknown parameter 'maxdepth'"):
        mi.load_dict({"type": "amrvolpath", "maxdepth": 3})
    with pytest.raises(Exception, match="rr_depth"):
        mi.load_dict({"type": "amrvolpath", "rr_depth": 0})
