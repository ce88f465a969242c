"""The `amr` medium in Mitsuba's stock volpath, against gridvolume references.

Statistical tests compare per-block image means of two estimators over
independent passes: |z| < 4 for every block, z from the passes' standard
errors (see `mi_amr.testing.block_z_scores`).
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.data.io import write_exabricks
from mi_amr.testing import block_z_scores, render_passes
from mi_amr.reference import reference_medium

from conftest import random_amr, volume_scene

PASSES = 16
Z_MAX = 4.0


def amr_dict(cells, **kw):
    d = {"type": "amr", "data": cells}
    d.update(kw)
    return d


def assert_same_expectation(scene_a, scene_b, spp=16, block=4):
    a = render_passes(mi.load_dict(scene_a), PASSES, spp, seed0=0)
    b = render_passes(mi.load_dict(scene_b), PASSES, spp, seed0=10_000)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    z = block_z_scores(a, b, block)
    assert np.abs(z).max() < Z_MAX, f"max |z| = {np.abs(z).max():.2f}"
    return a, b


def nonlinear_tf(domain):
    """Opacity with several peaks and plateaus over the data's quantised values."""
    return mi_amr.TransferFunction.from_colormap(
        "plasma", [(0, 0), (0.25, 0.9), (0.45, 0.1), (0.7, 1.0), (1.0, 0.3)], domain, n=64)


def spatial_std(passes):
    """Spatial std of the mean image's first channel (0 for a constant image)."""
    return float(passes.mean(axis=0)[..., 0].std())


@pytest.fixture(scope="module")
def multilevel():
    cells = random_amr(21, n=16, levels=4, quantize=6)
    assert len(cells.levels) >= 3
    return cells


def test01_nearest_matches_gridvolume_nearest(variant, multilevel):
    tf = nonlinear_tf(multilevel.value_range)
    scale = 25.0
    a, _ = assert_same_expectation(
        volume_scene(amr_dict(multilevel, transfer_function=tf, density_scale=scale,
                              reconstruction="nearest")),
        volume_scene(reference_medium(multilevel, tf, scale, "nearest")))
    # the medium is visible: the image is not just the background
    assert spatial_std(a) > 0.02


def test02_tent_single_level_matches_gridvolume_trilinear(variant):
    rng = np.random.default_rng(4)
    v = rng.random((10, 12, 14)).astype(np.float32)
    cells = mi_amr.dense_to_amr(v, 0.0, 0)                 # one level
    tf = mi_amr.TransferFunction.from_colormap("viridis", [(0, 0), (1, 1)], (0, 1), n=2)
    tf.rgba[:, :3] = 0.8                                    # grey albedo, linear opacity
    a, _ = assert_same_expectation(
        volume_scene(amr_dict(cells, transfer_function=tf, density_scale=8.0)),
        volume_scene(reference_medium(cells, tf, 8.0, "tent")))
    assert spatial_std(a) > 0.02


def test03_ray_and_global_majorants_agree(variant, multilevel):
    kw = dict(transfer_function="spiky", density_scale=30.0)
    a, _ = assert_same_expectation(volume_scene(amr_dict(multilevel, majorant="ray", **kw)),
                                   volume_scene(amr_dict(multilevel, majorant="global", **kw)))
    assert spatial_std(a) > 0.02


def test04_xml_and_dict_give_identical_images(variant, multilevel, tmp_path):
    write_exabricks(multilevel, tmp_path / "data.cells")
    xml = tmp_path / "scene.xml"
    xml.write_text("""<scene version="3.0.0">
    <integrator type="volpath"><integer name="max_depth" value="16"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="1.8, 1.3, 2.6" target="0.5, 0.5, 0.5" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/>
            <rfilter type="box"/></film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="0.6, 0.7, 0.8"/></emitter>
    <medium type="amr" id="m">
        <string name="filename" value="data.cells"/>
        <string name="transfer_function" value="spiky"/>
        <float name="density_scale" value="20"/>
        <phase type="hg"><float name="g" value="0.4"/></phase>
    </medium>
    <shape type="cube">
        <transform name="to_world"><scale value="0.5"/><translate value="0.5, 0.5, 0.5"/></transform>
        <bsdf type="null"/>
        <ref name="interior" id="m"/>
    </shape>
</scene>""")
    T = mi.ScalarTransform4d        # the XML parser composes transforms in double precision
    d = {"type": "scene", "integrator": {"type": "volpath", "max_depth": 16},
         "sensor": {"type": "perspective", "fov": 40,
                    "to_world": T().look_at([1.8, 1.3, 2.6], [0.5, 0.5, 0.5], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}}},
         "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.6, 0.7, 0.8]}},
         "cube": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                  "bsdf": {"type": "null"},
                  "interior": amr_dict(multilevel, transfer_function="spiky", density_scale=20.0,
                                       phase={"type": "hg", "g": 0.4})}}
    a = np.array(mi.render(mi.load_file(str(xml)), spp=8, seed=3))
    b = np.array(mi.render(mi.load_dict(d), spp=8, seed=3))
    assert np.isfinite(a).all() and spatial_std(a[None]) > 0.01
    np.testing.assert_array_equal(a, b)


def test05_to_world_places_the_unit_cube(variant, multilevel):
    """A scaled, rotated, translated medium equals the reference placed the same way."""
    T = mi.ScalarTransform4f
    tw = T().translate([3, -2, 1]) @ T().rotate([0, 1, 0], 30) @ T().scale([2, 1, 1.5])
    tf = nonlinear_tf(multilevel.value_range)
    assert_same_expectation(
        volume_scene(amr_dict(multilevel, transfer_function=tf, density_scale=10.0,
                              reconstruction="nearest", to_world=tw), to_world=tw),
        volume_scene(reference_medium(multilevel, tf, 10.0, "nearest", to_world=tw), to_world=tw))


def test06_volpathmis_and_phase_functions(variant, multilevel):
    tf = mi_amr.TransferFunction.preset("foggy", multilevel.value_range)
    phase = {"type": "hg", "g": 0.6}
    assert_same_expectation(
        volume_scene(amr_dict(multilevel, transfer_function=tf, density_scale=60.0,
                              reconstruction="nearest", phase=phase), integrator="volpathmis"),
        volume_scene(dict(reference_medium(multilevel, tf, 60.0, "nearest"), phase=phase)))


def test07_empty_transfer_function_shows_background_exactly(variant, multilevel):
    tf = mi_amr.TransferFunction(np.zeros((8, 4)), (0, 1))
    for majorant in ("ray", "global"):
        scene = mi.load_dict(volume_scene(amr_dict(multilevel, transfer_function=tf, majorant=majorant),
                                          emitters="env"))
        img = np.array(mi.render(scene, spp=4))
        np.testing.assert_allclose(img, np.broadcast_to([0.6, 0.7, 0.8], img.shape), rtol=1e-6)


def test08_bad_parameters_give_clear_errors(variant, multilevel, tmp_path):
    with pytest.raises(Exception, match="unknown parameter 'densty_scale'"):
        mi.load_dict(amr_dict(multilevel, densty_scale=2.0))
    with pytest.raises(Exception, match="unknown reconstruction 'cubic'"):
        mi.load_dict(amr_dict(multilevel, reconstruction="cubic"))
    with pytest.raises(Exception, match="unknown majorant"):
        mi.load_dict(amr_dict(multilevel, majorant="local"))
    with pytest.raises(Exception, match="unknown transfer function preset"):
        mi.load_dict(amr_dict(multilevel, transfer_function="no-such-tf"))
    with pytest.raises(Exception, match="density_scale must be"):
        mi.load_dict(amr_dict(multilevel, density_scale=-1.0))
    with pytest.raises(Exception, match="exactly one of 'filename'"):
        mi.load_dict({"type": "amr"})
    with pytest.raises(Exception, match="no such file"):
        mi.load_dict({"type": "amr", "filename": str(tmp_path / "nope.cells")})


def test09_scalar_variant_is_refused():
    mi.set_variant("scalar_rgb")
    try:
        with pytest.raises(Exception, match="needs a JIT Mitsuba variant.*scalar variants are refused"):
            mi.load_dict({"type": "amr", "data": random_amr(0)})
    finally:
        mi.set_variant("llvm_ad_rgb")


def test10_majorant_bounds_extinction(variant, multilevel):
    """sigma_t <= the macrocell majorant at random points (sampled densely)."""
    for rec in ("tent", "nearest"):
        med = mi.load_dict(amr_dict(multilevel, transfer_function=nonlinear_tf(multilevel.value_range),
                                    density_scale=7.0,
                                    reconstruction=rec, grid_resolution=6))
        rng = np.random.default_rng(5)
        u = rng.random((50000, 3)).astype(np.float32)
        mei = dr.zeros(mi.MediumInteraction3f, len(u))
        mei.p = mi.Point3f(u.T)
        _, _, sigma_t = med.get_scattering_coefficients(mei)
        st = np.array(sigma_t)[0] if np.array(sigma_t).shape[0] == 3 else np.array(sigma_t)[:, 0]
        res = med.grid.res
        idx = np.clip(np.floor(u * res), 0, res - 1).astype(int)
        maj = med.majorant_grid[idx[:, 2], idx[:, 1], idx[:, 0]]
        assert np.all(st <= maj * (1 + 1e-5) + 1e-6)
        assert st.max() > 0
        assert med.global_majorant == pytest.approx(float(med.majorant_grid.max()))


@pytest.mark.parametrize("setting,faster", [({"majorant": "global"}, "majorant='ray'"),
                                            ({"traversal": "kdtree"}, "traversal='grid'")])
def test11_slow_settings_warn_once_and_name_the_faster_one(llvm, capfd, setting, faster):
    """A setting that cannot reach the heterogeneous medium's efficiency
    (docs/performance/settings.md) warns at load, once per process, and
    names the faster setting."""
    from mi_amr.plugins import medium as medium_module
    medium_module._WARNED.clear()
    cells = mi_amr.dense_to_amr(np.ones((8, 8, 8), np.float32), 0.0, 1)
    for _ in range(2):
        mi.load_dict({"type": "amr", "data": cells, **setting})
    out = capfd.readouterr()                # Mitsuba's log goes to stdout or stderr
    assert (out.out + out.err).count(faster) == 1
    mi.load_dict({"type": "amr", "data": cells})
    out = capfd.readouterr()
    assert faster not in out.out + out.err


def test12_stock_volpath_warns_once_where_it_is_predicted_slower(llvm, capfd):
    """When stock volpath renders a medium whose majorants keep most rays
    near the global one (a fog filling the cube: the ray-wise majorant saves
    nothing), one warning per process names amrvolpath; a medium with empty
    space around a small dense core (where it pays), amrvolpath itself, and
    a second such render say nothing."""
    from conftest import volume_scene
    from mi_amr.plugins import medium as medium_module
    from mi_amr.structures.cost_model import volpath_collision_share, volpath_speedup
    medium_module._WARNED.clear()
    fog = mi_amr.dense_to_amr(np.ones((16, 16, 16), np.float32), 0.0, 1)
    x = np.linspace(-1, 1, 16)
    r = np.sqrt(x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2)
    core = mi_amr.dense_to_amr(np.where(r < 0.3, 1.0, 0.0).astype(np.float32), 0.0, 1)

    def medium(cells):
        return {"type": "amr", "data": cells, "transfer_function": "foggy", "density_scale": 5.0}

    assert volpath_collision_share(mi.load_dict(medium(fog)).majorant_grid) == pytest.approx(1.0)
    assert volpath_speedup(mi.load_dict(medium(core)).majorant_grid) > 1.0
    for cells, integrator in ((core, "volpath"), (fog, "amrvolpath"), (fog, "volpath"), (fog, "volpath")):
        mi.render(mi.load_dict(volume_scene(medium(cells), res=4, integrator=integrator, max_depth=4)), spp=1)
    out = capfd.readouterr()
    text = out.out + out.err
    assert text.count("stock volpath is predicted") == 1 and "amrvolpath" in text.split("stock volpath")[1]
