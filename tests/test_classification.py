"""One owner of the TF and the density scale (`mi_amr.transfer.classification`)
and the structure cache: both update paths give the same structures and the
same image, a bad parameter changes nothing, and cached host structures go
away with their data."""

import gc

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from conftest import random_amr, volume_scene
from mi_amr.structures.cache import HOST_CACHE


def _scene(traversal, data):
    m = {"type": "amr", "data": data, "transfer_function": "spiky", "density_scale": 20.0,
         "traversal": traversal}
    return mi.load_dict(volume_scene(m, res=16, integrator="amrvolpath", max_depth=8))


def _majorants(med):
    """Every built structure's leaf majorants and minorants, and the
    kd-tree's topology where there is one."""
    out = {name: (dev.majorant.numpy(), dev.minorant.numpy())
           for name, dev in med.structures.device.items() if hasattr(dev, "update_majorants")}
    if "kdtree" in med.structures.device:
        t = med.structures.device["kdtree"]
        out["kdtree_topology"] = (t.axis.numpy(), t.split.numpy())
    return out


@pytest.mark.parametrize("traversal", ["grid", "kdtree"])
def test01_params_update_and_set_transfer_function_agree(llvm, traversal):
    """A new TF and density scale through ``mi.traverse`` + ``params.update()``
    and through `set_transfer_function` give the same majorants, the same
    kd-tree (rebuilt for the new classification on both paths) and the same
    image for the same seed (same kernels and random numbers: equal up to
    float reassociation, rtol 1e-5)."""
    data = random_amr(0, 16, 3)
    scene = _scene(traversal, data)
    med = mi_amr.amr_media(scene)[0]
    new_tf = mi_amr.TransferFunction.preset("foggy", med.tf.domain)
    before = _majorants(med)

    mi_amr.set_transfer_function(scene, new_tf, density_scale=35.0)
    by_call = _majorants(med)
    img_call = mi.render(scene, spp=4, seed=3).numpy()

    mi_amr.set_transfer_function(scene, mi_amr.TransferFunction.preset("spiky", med.tf.domain), density_scale=20.0)
    for name, (mu, mu_min) in before.items():
        np.testing.assert_array_equal(_majorants(med)[name][0], mu)
    params = mi.traverse(scene)
    prefix = next(k for k in params.keys() if k.endswith("tf_rgba"))[:-len("tf_rgba")]
    params[prefix + "tf_rgba"] = mi.Float(new_tf.rgba.ravel().astype(np.float32))
    params[prefix + "tf_domain"] = mi.Float(np.asarray(new_tf.domain, np.float32))
    params[prefix + "density_scale"] = 35.0
    params.update()
    by_params = _majorants(med)
    img_params = mi.render(scene, spp=4, seed=3).numpy()

    assert med.density_scale == 35.0 and np.array_equal(med.tf.rgba, new_tf.rgba)
    assert by_call.keys() == by_params.keys()
    for name in by_call:
        for a, b in zip(by_call[name], by_params[name]):
            np.testing.assert_array_equal(a, b)
    assert any(not np.array_equal(before[n][0], by_call[n][0]) for n in before)
    np.testing.assert_allclose(img_params, img_call, rtol=1e-5, atol=1e-6)


def test02_density_scale_alone_rebuilds_the_kdtree_on_both_paths(llvm):
    """The SAH kd-tree's cost depends on the scaled majorants: a density
    scale change alone rebuilds it, through ``params.update()`` too."""
    scene = _scene("kdtree", random_amr(1, 16, 3))
    med = mi_amr.amr_media(scene)[0]
    mu = med.global_majorant
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("density_scale"))
    params[key] = 7.0
    params.update()
    assert "kdtree_rebuild" in med.build_seconds
    assert med.density_scale == 7.0
    assert med.global_majorant == pytest.approx(mu * 7.0 / 20.0, rel=1e-6)


def test03_a_bad_parameter_changes_nothing(llvm):
    """An invalid density scale through ``params.update()`` raises a clear
    error and the medium keeps its last valid state, in the traversed
    variable too."""
    scene = _scene("grid", random_amr(2, 16, 3))
    med = mi_amr.amr_media(scene)[0]
    mu = med.structures.grid.majorant.numpy().copy()
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("density_scale"))
    params[key] = -1.0
    with pytest.raises(ValueError, match="density_scale"):
        params.update()
    assert med.density_scale == 20.0 and med.classification.scale.numpy()[0] == 20.0
    np.testing.assert_array_equal(med.structures.grid.majorant.numpy(), mu)
    with pytest.raises(ValueError, match="TransferFunction"):
        med.set_transfer_function("spiky")


def test04_host_structures_are_shared_and_go_away_with_their_data(llvm):
    """Two media on one data object build the blocks and bricks once (the
    same objects); once the data and the media are gone, so are the cache
    entries (nothing is stored on the data object)."""
    data = random_amr(3, 16, 3)
    media = [mi.load_dict({"type": "amr", "data": data, "traversal": "brick", "sampling": "brick"})
             for _ in range(2)]
    assert media[0].volume is media[1].volume
    assert media[0].structures.host["bricks"] is media[1].structures.host["bricks"]
    assert "_mi_amr_cache" not in data.__dict__ and "_mi_amr_cache" not in media[0].volume.__dict__
    keys = HOST_CACHE.keys(data) | HOST_CACHE.keys(media[0].volume)
    assert "volume" in keys and ("bricks", 8) in keys
    ids = {id(data), id(media[0].volume)}
    assert ids <= HOST_CACHE.ids()
    del media, data
    gc.collect()
    assert not ids & HOST_CACHE.ids()
