"""The ``amr`` medium and ``amrvolpath`` as well-formed Mitsuba objects:
dr.freeze, mi.traverse of the phase function, microflake phase functions,
get_majorant for any caller, plugin classes per variant."""

import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from conftest import random_amr, volume_scene


def amr_scene(integrator, majorant="ray", res=16, **medium):
    m = {"type": "amr", "data": random_amr(0, 16, 3), "transfer_function": "spiky",
         "density_scale": 20.0, "majorant": majorant, "phase": {"type": "hg", "g": 0.3}}
    m.update(medium)
    return mi.load_dict(volume_scene(m, res=res, integrator=integrator, max_depth=8))


def amr_medium(scene):
    return mi_amr.amr_media(scene)[0]


#: Frames of the frozen sequences: past the first replay, after which a
#: layout change (e.g. two variables that alias one buffer) shows as a new
#: recording.
SEEDS = (1, 2, 3, 4, 5)


def heterogeneous_recordings(integrator):
    """Recordings of the same frozen sequence with Mitsuba's heterogeneous
    medium: after the first frames, and after a parameter change (a new
    density grid and scale through mi.traverse) and three more frames."""
    rng = np.random.default_rng(0)
    grid = mi.TensorXf(rng.random((8, 8, 8, 1)).astype(np.float32))
    m = {"type": "heterogeneous", "sigma_t": {"type": "gridvolume", "data": grid}, "scale": 20.0}
    scene = mi.load_dict(volume_scene(m, res=16, integrator=integrator, max_depth=8))

    @dr.freeze
    def render(scene, seed):
        return mi.render(scene, spp=4, seed=seed)
    for seed in SEEDS:
        render(scene, dr.opaque(mi.UInt32, seed))
    before = render.n_recordings
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("sigma_t.data"))
    params[key] = mi.TensorXf(rng.random((8, 8, 8, 1)).astype(np.float32))
    params[key.replace("sigma_t.data", "scale")] = 35.0
    params.update()
    for seed in (4, 5, 4):
        render(scene, dr.opaque(mi.UInt32, seed))
    return before, render.n_recordings


@pytest.mark.parametrize("integrator,majorant,refinement", [
    ("volpath", "ray", 1), pytest.param("volpath", "global", 1, marks=pytest.mark.slow),
    pytest.param("amrvolpath", "ray", 1, marks=pytest.mark.slow), ("amrvolpath", "ray", 4), ("volpath", "ray", 4)])
def test01_frozen_render_replays_and_follows_tf_changes(variant, integrator, majorant, refinement):
    scene = amr_scene(integrator, majorant, grid_resolution=16, grid_refinement=refinement)

    @dr.freeze
    def render(scene, seed):
        return mi.render(scene, spp=4, seed=seed)

    frozen = [render(scene, dr.opaque(mi.UInt32, seed)).numpy() for seed in SEEDS]
    # as many recordings as Mitsuba's own heterogeneous medium needs
    recordings = render.n_recordings
    reference_before, reference_after = heterogeneous_recordings(integrator)
    assert recordings <= reference_before
    for seed, img in zip(SEEDS, frozen):
        plain = mi.render(scene, spp=4, seed=seed).numpy()
        assert np.isfinite(img).all()
        # same kernels, same seed: equal up to float reassociation
        np.testing.assert_allclose(img, plain, rtol=1e-4, atol=1e-5)

    # a TF and scale change through mi.traverse reaches the replayed kernels
    render_before = frozen[0]
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("tf_rgba"))
    rgba = np.array(params[key]).reshape(-1, 4)
    rgba[:, 3] = rgba[::-1, 3]
    params[key] = mi.Float(rgba.ravel())
    params[key.replace("tf_rgba", "density_scale")] = 35.0
    params.update()
    frozen = render(scene, dr.opaque(mi.UInt32, 4)).numpy()
    plain = mi.render(scene, spp=4, seed=4).numpy()
    np.testing.assert_allclose(frozen, plain, rtol=1e-4, atol=1e-5)
    frozen = render(scene, dr.opaque(mi.UInt32, 5)).numpy()
    np.testing.assert_allclose(frozen, mi.render(scene, spp=4, seed=5).numpy(), rtol=1e-4, atol=1e-5)
    frozen = render(scene, dr.opaque(mi.UInt32, 4)).numpy()
    assert np.abs(frozen - render_before).mean() > 0.01 * render_before.mean()
    # a new TF is new values in variables of the same layout: recorded again
    # no more often than Mitsuba's own medium after a change (amrvolpath: never)
    assert render.n_recordings - recordings <= (0 if integrator == "amrvolpath"
                                                else reference_after - reference_before)


def test01b_device_tables_do_not_alias_the_callers_arrays(variant):
    """The medium keeps its own copy of the TF table: an in-place edit of the
    caller's array (CPU: Dr.Jit would map it, not copy it) reaches neither
    the kernels nor the traversed parameter until the TF is set again, so
    the majorants always match the table the kernels read."""
    tf = mi_amr.TransferFunction.preset("spiky", (0.0, 1.0))
    medium = amr_medium(amr_scene("amrvolpath", transfer_function=tf))
    table, param = medium.tf_device.rgba.numpy().copy(), medium.classification.tf_rgba.numpy().copy()
    tf.rgba[:, 3] = 1.0
    np.testing.assert_array_equal(medium.tf_device.rgba.numpy(), table)
    np.testing.assert_array_equal(medium.classification.tf_rgba.numpy(), param)
    medium.set_transfer_function(tf)
    assert medium.tf_device.rgba.numpy()[3::4].min() == 1.0
    tf.rgba[:, 3] = 0.0
    assert medium.tf_device.rgba.numpy()[3::4].min() == 1.0


def backlit_scene(integrator, g):
    """A constant medium (optical depth 1 across) lit only by a sun behind
    it, shining towards the camera: what the camera sees is light that
    the phase function sends forward, so it grows with ``g``."""
    T = mi.ScalarTransform4f
    m = {"type": "amr", "data": random_amr(0, 8, 2), "transfer_function": "constant",
         "density_scale": 1.0, "phase": {"type": "hg", "g": g}}
    d = volume_scene(m, res=12, integrator=integrator, max_depth=8, emitters="")
    d["sensor"]["to_world"] = T().look_at([0.5, 0.5, 3.0], [0.5, 0.5, 0.5], [0, 1, 0])
    d["sun"] = {"type": "directional", "direction": [0.15, -0.1, 1.0],
                "irradiance": {"type": "rgb", "value": 1.0}}
    return mi.load_dict(d)


@pytest.mark.parametrize("integrator", ["volpath", "amrvolpath"])
def test02_traverse_exposes_the_phase_function(variant, integrator):
    """``...phase_function.g`` is a scene parameter, and updating it changes
    the render as loading the scene with that ``g`` does: per-pass image
    means agree within 5 standard errors, and forward scattering (g = 0.8)
    is clearly brighter than backward (g = -0.8) in this backlit scene."""
    scene = backlit_scene(integrator, -0.8)
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.endswith("phase_function.g")]
    assert len(keys) == 1
    assert any(k.endswith("density_scale") for k in params.keys())

    def pass_means(scene):
        return np.array([mi.render(scene, spp=16, seed=s).numpy().mean() for s in range(6)])
    backward = pass_means(scene)
    params[keys[0]] = 0.8
    params.update()
    assert float(mi.traverse(scene)[keys[0]][0]) == pytest.approx(0.8)
    updated = pass_means(scene)
    loaded = pass_means(backlit_scene(integrator, 0.8))
    se = np.sqrt(updated.var(ddof=1) / 6 + loaded.var(ddof=1) / 6)
    assert abs(updated.mean() - loaded.mean()) < 5 * se + 1e-6, (updated.mean(), loaded.mean(), se)
    assert np.isfinite(updated).all()
    assert updated.mean() > 3 * backward.mean() > 0, (updated.mean(), backward.mean())


def test03_microflake_phase_functions_are_refused(variant):
    with pytest.raises((ValueError, RuntimeError), match="microflake"):
        S = mi.TensorXf(np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], np.float32).reshape(1, 1, 1, 6))
        mi.load_dict({"type": "amr", "data": random_amr(0, 8, 2),
                      "phase": {"type": "sggx", "S": {"type": "gridvolume", "data": S}}})


def test04_get_majorant_bounds_sigma_t_for_any_caller(variant):
    """A caller that does not follow sample_interaction's order (no
    intersect_aabb, or one for another ray) gets a majorant >= sigma_t;
    sample_interaction itself gets the tighter ray-wise majorant."""
    scene = amr_scene("volpath", res=8)
    med = amr_medium(scene)
    rng = np.random.default_rng(5)
    n = 4096
    o = rng.random((n, 3)) * 0.2 - 0.3                 # just outside the box
    d = rng.normal(size=(n, 3))
    d[:, :] = np.abs(d) / np.linalg.norm(d, axis=1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f(d.T.astype(np.float32)))
    other = mi.Ray3f(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f(-d.T.astype(np.float32)))
    global_mu = med.global_majorant

    def mei_of(r):
        mei = dr.zeros(mi.MediumInteraction3f, n)
        mei.wi = -r.d
        return mei

    # no intersect_aabb at all
    assert np.allclose(med.get_majorant(mei_of(ray)).numpy(), global_mu)
    # intersect_aabb for one ray, get_majorant for another
    med.intersect_aabb(ray)
    assert np.allclose(med.get_majorant(mei_of(other)).numpy(), global_mu)
    # ... and get_scattering_coefficients for another: sigma_n = mu - sigma_t >= 0
    med.intersect_aabb(ray)
    mei = mei_of(other)
    mei.p = mi.Point3f(rng.random((n, 3)).T.astype(np.float32))
    _, sigma_n, sigma_t = med.get_scattering_coefficients(mei)
    np.testing.assert_allclose((sigma_n + sigma_t).numpy()[0], global_mu, rtol=1e-5)

    # in stock volpath, sample_interaction gets the tighter ray-wise
    # majorant (the interaction's wi is -d of the ray just intersected)
    from mi_amr.plugins.medium import _RayMajorant
    hits = []
    lookup = _RayMajorant.lookup

    def counting_lookup(self, mei):
        mu = lookup(self, mei)
        hits.append(mu is not None)
        return mu
    _RayMajorant.lookup = counting_lookup
    try:
        mi.render(scene, spp=1)
    finally:
        _RayMajorant.lookup = lookup
    assert hits and all(hits)


def test05_plugins_follow_the_variant_active_at_instantiation(tmp_path):
    """Imported under a scalar variant, then used on llvm_ad_rgb."""
    code = (
        "import mitsuba as mi\n"
        "mi.set_variant('scalar_rgb')\n"
        "import mi_amr\n"
        "mi.set_variant('llvm_ad_rgb')\n"
        "import sys; sys.path.insert(0, %r)\n"
        "from conftest import random_amr, volume_scene\n"
        "scene = mi.load_dict(volume_scene({'type': 'amr', 'data': random_amr(0, 8, 2)}, res=8,"
        " integrator='amrvolpath'))\n"
        "img = mi.render(scene, spp=2).numpy()\n"
        "m = mi_amr.amr_media(scene)[0]\n"
        "assert isinstance(m, mi_amr.plugins.medium.AMRMedium) and isinstance(m, mi.Medium)\n"
        "print('ok', float(img.mean()) > 0)\n" % str(__import__('pathlib').Path(__file__).parent))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("ok True")


@pytest.mark.parametrize("phase", [{"type": "isotropic"}, pytest.param({"type": "rayleigh"}, marks=pytest.mark.slow),
                                   pytest.param({"type": "tabphase", "values": "0.4, 1.0, 1.8"},
                                                marks=pytest.mark.slow),
                                   {"type": "blendphase", "weight": 0.4, "phase1": {"type": "isotropic"},
                                    "phase2": {"type": "hg", "g": -0.5}}])
def test06_every_phase_function_agrees_with_volpath(llvm, phase):
    """amrvolpath draws the path's numbers from its own stream (independent
    sampler) while the phase function context still names the sampler: every
    built-in phase function but the refused microflake ones gives the image
    of stock volpath (z-test over independent passes, |z| < 4.5)."""
    from mi_amr.testing import block_z_scores, render_passes
    a = render_passes(amr_scene("amrvolpath", phase=phase, res=16), 16, 16)
    b = render_passes(amr_scene("volpath", phase=phase, res=16), 16, 16, seed0=100)
    assert np.isfinite(a).all()
    z = np.abs(block_z_scores(a, b, 4)).max()
    assert z < 4.5, f"{phase['type']}: max |z| = {z:.2f}"
