"""The sci-vis ray marcher (``amrvolpath``'s ``mode="ray_march"``,
docs/design.md section 14) against the estimator whose integral it
computes, an exact host walk, its own convergence order, and a host
computation of its shading.

Kernels are few: the medium-level tests call `AMRMedium.march` on a batch
of rays (one kernel per reconstruction), the image tests render 24^2 passes.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr import AMRCells, TransferFunction
from mi_amr.device.marching import AMBIENT, DIFFUSE, FLAT_SHARE, SHININESS, SPECULAR, GradientShading
from mi_amr.device.rng import Rng
from mi_amr.reference import emission_absorption_march
from mi_amr.testing import block_z_scores, brute_force, render_passes

from conftest import random_amr, volume_scene
from own_process import in_own_process, in_variant

#: Largest per-block |z| allowed between two estimators of one expectation
#: (24^2 images in 4^2 blocks: 36 blocks x 3 channels; 4.5 sigma).
Z_MAX = 4.5
TF = TransferFunction.from_colormap("viridis", [(0.0, 0.0), (0.3, 0.6), (0.6, 0.1), (1.0, 0.9)], (0.0, 1.2), n=64)


def two_level_field(seed=3):
    """A smooth blob on 16^3 finest cells, coarsened where it is flat into
    three levels: level boundaries inside the view."""
    return random_amr(seed)


def medium(cells, reconstruction="tent", traversal="grid", sampling="hash", scale=12.0, **extra):
    return dict({"type": "amr", "data": cells, "transfer_function": TF, "density_scale": scale,
                 "reconstruction": reconstruction, "traversal": traversal, "sampling": sampling}, **extra)


def rays(n, seed=0):
    """``n`` rays through the unit cube: from points on a sphere of radius 2
    about its centre towards random points inside it."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    o = 0.5 + 2.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    d = rng.uniform(0.2, 0.8, (n, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def march(med, o, d, step_scale=0.5, seed=7, light=None):
    """``(L, T)`` of `AMRMedium.march` along rays ``(o, d)`` (numpy)."""
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k]) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, k]) for k in range(3)]))
    rng = Rng(mi.UInt64(np.arange(len(o), dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(seed)))
    out = med.march(ray, mi.Float(dr.inf), rng, mi.Bool(True), dr.opaque(mi.Float, step_scale),
                    mi.Float(1.0), light)
    L = np.stack([np.asarray(c) for c in (out.L.x, out.L.y, out.L.z)], axis=1)
    return L, np.asarray(out.T)


@pytest.mark.parametrize("traversal,sampling,extra", [
    ("grid", "hash", {}), ("abr", "abr", {}),
    # the other walkers' levels: their own kernels, in the slow suite
    pytest.param("grid", "hash", {"grid_refinement": 2}, marks=pytest.mark.slow),
    pytest.param("brick", "brick", {}, marks=pytest.mark.slow),
    pytest.param("kdtree", "hash", {}, marks=pytest.mark.slow)])
def test01_nearest_march_is_the_exact_integral(llvm, traversal, sampling, extra):
    """With ``nearest`` the steps end on the faces of the lattice of the
    finest level under each leaf: along 400 rays the march equals an exact
    host walk over the voxels of the resampled field within 1e-4 of its
    mean, whatever ``step_scale`` (it only sets the steps of ``tent``), and
    ``T`` equals the walk's transmittance, for every traversal (a leaf
    whose level were coarser than a cell in it would step over that cell's
    faces and miss this)."""
    cells = two_level_field()
    med = mi.load_dict(medium(cells, "nearest", traversal, sampling, **extra))
    o, d = rays(400)
    ref = emission_absorption_march(cells, TF, 12.0, o, d, steps=None)
    ref_T = 1.0 - emission_absorption_march(cells, TransferFunction(
        np.column_stack([np.ones((len(TF), 3)), TF.rgba[:, 3]]), TF.domain), 12.0, o, d, steps=None).mean(axis=1)
    L, T = march(med, o, d, step_scale=0.5)
    L2, _ = march(med, o, d, step_scale=4.0, seed=99)
    tol = 1e-4 * ref.mean()
    assert ref.mean() > 0.05 and np.abs(L - ref).max() < tol, np.abs(L - ref).max() / ref.mean()
    assert np.abs(T - ref_T).max() < 1e-4
    np.testing.assert_allclose(L2, L, atol=1e-6)
    # power: the dense march of 64 equal steps is visibly off on the same rays
    coarse = emission_absorption_march(cells, TF, 12.0, o, d, steps=64)
    assert np.abs(coarse - ref).max() > 10 * tol


def test02_tent_march_converges_at_first_order_in_the_step(llvm):
    """One jittered offset per ray: a step of ``h`` misplaces each sample by
    ``(xi - 1/2) h`` against the interval's midpoint, so a ray's error is
    ``(xi - 1/2) sum_k h_k^2 f'(x_k)`` plus ``O(h^2)``: first order in
    ``h`` (its expectation over ``xi`` is second order). Within a segment
    of equal steps that sum telescopes to ``h (f(end) - f(start))``, so
    only the segments' ends keep the first-order term, and at coarse steps
    the second-order one still shows. With the same jitter, against a
    march of step 1/64: each halving of the step divides the RMS error by
    between 1.8 (first order, with margin) and 4.5 (second order, with
    margin), the finest halving by less than 3 (the first-order term
    takes over), and the errors are not zero."""
    cells = two_level_field()
    med = mi.load_dict(medium(cells, "tent"))
    o, d = rays(200, seed=1)
    ref, _ = march(med, o, d, step_scale=1 / 64)
    steps = [1.0, 0.5, 0.25, 0.125]
    err = np.array([np.sqrt(((march(med, o, d, step_scale=h)[0] - ref) ** 2).mean()) for h in steps])
    ratios = err[:-1] / err[1:]
    assert np.all((ratios > 1.8) & (ratios < 4.5)) and ratios[-1] < 3.0, (ratios, err)
    assert err[-1] > 1e-4 * ref.mean()


@pytest.mark.parametrize("reconstruction,traversal,sampling", [("tent", "grid", "hash"), ("nearest", "abr", "abr")])
def test03_ray_march_equals_emission_absorption_in_expectation(llvm, reconstruction, traversal, sampling):
    """The marcher computes Max's integral, which ``emission_absorption``
    estimates by Woodcock tracking: per 4^2-pixel block, their means over
    independent passes agree within `Z_MAX` standard errors; a medium of
    twice the density fails the same test (power)."""
    cells = two_level_field()

    def scene(mode, scale=12.0):
        return mi.load_dict(volume_scene(medium(cells, reconstruction, traversal, sampling, scale), res=24,
                                         integrator="amrvolpath", emitters="env") | {
            "integrator": {"type": "amrvolpath", "mode": mode, "step_scale": 0.25}})
    march_passes = render_passes(scene("ray_march"), 8, 4)
    tracked = render_passes(scene("emission_absorption"), 16, 64, seed0=1000)
    z = block_z_scores(march_passes, tracked, 4)
    assert np.abs(z).max() < Z_MAX, np.abs(z).max()
    denser = render_passes(scene("ray_march", 24.0), 8, 4)
    assert np.abs(block_z_scores(denser, tracked, 4)).max() > 2 * Z_MAX
    assert np.isfinite(march_passes).all() and march_passes.mean(axis=0).std() > 0.02


def test04_tf_change_compiles_nothing_and_equals_a_fresh_scene(llvm):
    """A TF and density change of a loaded ray-marched scene launches only
    kernels it launched before (their code compared with names erased), and
    renders the image of a scene loaded with the new TF (same seed)."""
    from test_interactive import _structure
    cells = two_level_field()
    base = medium(cells, "tent", grid_resolution=8)

    def scene(tf, scale):
        d = volume_scene(dict(base, transfer_function=tf, density_scale=scale), res=16, integrator="amrvolpath")
        d["integrator"]["mode"] = "ray_march"
        return mi.load_dict(d)
    import gc
    gc.collect()
    dr.eval()
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        sc = scene(TF, 12.0)
        mi.render(sc, spp=2, seed=0)
        mi_amr.set_transfer_function(sc, TF, density_scale=12.0)
        first = np.array(mi.render(sc, spp=2, seed=0))
        before = {_structure(h["ir"].getvalue()) for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT}
        tf = TransferFunction.from_colormap("magma", [(0, 0), (0.5, 1), (1, 0.2)], (0.0, 1.0), n=32)
        mi_amr.set_transfer_function(sc, tf, density_scale=30.0)
        second = np.array(mi.render(sc, spp=2, seed=0))
        history = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    new = [h for h in history if _structure(h["ir"].getvalue()) not in before]
    assert history and not new, [h["ir"].getvalue()[:2000] for h in new]
    assert np.isfinite(second).all() and np.abs(second - first).max() > 1e-3
    np.testing.assert_array_equal(np.array(mi.render(scene(tf, 30.0), spp=2, seed=0)), second)


def host_shading(cells, x, eps, rgb, light, view):
    """Blinn-Phong of docs/design.md section 14 on the host: the forward
    difference gradient of the tent field (brute force over every cell);
    where it vanishes, the colour unshaded (``AMBIENT + DIFFUSE``)."""
    diff = np.zeros_like(x)
    here = brute_force(cells, x)[0]
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        diff[:, k] = brute_force(cells, x + e)[0] - here
    grad = diff / eps
    length = np.linalg.norm(grad, axis=1, keepdims=True)
    n = grad / np.where(length > 0, length, 1.0)
    v = -view
    n = np.where((n @ v)[:, None] < 0, -n, n)
    h = (light + v) / np.linalg.norm(light + v)
    flat = np.abs(diff).max(axis=1) <= FLAT_SHARE * np.abs(here)      # no gradient: unshaded
    diffuse = np.where(flat, 1.0, np.maximum(n @ light, 0.0))
    specular = np.where(flat, 0.0, np.maximum(n @ h, 0.0) ** SHININESS)
    return rgb * (AMBIENT + DIFFUSE * diffuse)[:, None] + (SPECULAR * specular)[:, None]


def test05_gradient_shading_equals_a_host_computation(llvm):
    """`GradientShading` with the medium's tent look-ups at 64 points equals
    the host's Blinn-Phong on brute-force forward differences within 1e-4;
    a light from the other side changes it (power)."""
    cells = two_level_field()
    med = mi.load_dict(medium(cells, "tent"))
    rng = np.random.default_rng(2)
    u = rng.uniform(0.15, 0.85, (64, 3))
    light = np.array([0.48, 0.6, 0.64])
    # a view along no axis: a normal in a coordinate plane (a zero difference) is
    # then never perpendicular to it, where float32 and float64 might face it apart
    view = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    rgb = np.array([0.8, 0.5, 0.2])
    eps = 0.5 / float(np.max(cells.bounds[1] - cells.bounds[0]))
    shading = GradientShading(lambda p, a: med.value_local(p, a)[0], eps, lambda g: dr.normalize(mi.Vector3f(g)),
                              lambda p, a: mi.Vector3f(*map(float, light)), mi.Vector3f(*map(float, view)))
    p = mi.Point3f(*[mi.Float(u[:, k]) for k in range(3)])
    got = shading(p, med.value_local(p, True)[0], mi.Color3f(*map(float, rgb)), mi.Bool(True))
    got = np.stack([np.asarray(c) for c in (got.x, got.y, got.z)], axis=1)
    lo, hi = cells.bounds
    want = host_shading(cells, lo + u * (hi - lo), eps * float(np.max(hi - lo)), rgb, light, view)
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert np.ptp(want[:, 0]) > 0.3                      # the points see shading, not one colour
    other = host_shading(cells, lo + u * (hi - lo), eps * float(np.max(hi - lo)), rgb, -light, view)
    assert np.abs(other - want).max() > 0.05


def test06_gradient_shading_renders_and_options_are_checked(llvm):
    """``shading="gradient"`` under the scene's sun differs from flat
    shading and is finite; a clip plane that keeps nothing leaves the
    background; bad options are named in one line; amrprbvolpath refuses
    the mode."""
    cells = two_level_field()
    d = volume_scene(medium(cells), res=16, integrator="amrvolpath")
    flat = np.array(mi.render(mi.load_dict(d | {"integrator": {"type": "amrvolpath", "mode": "ray_march"}}), spp=2))
    lit = np.array(mi.render(mi.load_dict(d | {"integrator": {"type": "amrvolpath", "mode": "ray_march",
                                                               "shading": "gradient"}}), spp=2))
    assert np.isfinite(lit).all() and np.abs(lit - flat).max() > 0.02
    clipped = volume_scene(medium(cells, clip_normal=[1.0, 0.0, 0.0], clip_offset=-1.0), res=16,
                           integrator="amrvolpath", emitters="env")
    img = np.array(mi.render(mi.load_dict(clipped | {"integrator": {"type": "amrvolpath", "mode": "ray_march"}}),
                             spp=2))
    np.testing.assert_allclose(img, np.broadcast_to([0.6, 0.7, 0.8], img.shape), rtol=1e-5)
    for bad, match in (({"step_scale": 0.0}, "step_scale"), ({"shading": "phong"}, "shading")):
        with pytest.raises(Exception, match=match):
            mi.load_dict({"type": "amrvolpath", "mode": "ray_march", **bad})
    with pytest.raises(Exception, match="unknown mode 'ray_march'"):
        mi.load_dict({"type": "amrprbvolpath", "mode": "ray_march"})


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["spectral", "mono"])
@in_own_process
def test07_ray_march_equals_emission_absorption_in_every_variant(kind):
    """As test03 (tent, grid), in the spectral and the mono variant. Slow:
    two processes and four kernels of their own."""
    with in_variant(kind):
        cells = two_level_field()

        def scene(mode):
            d = volume_scene(medium(cells), res=24, integrator="amrvolpath", emitters="env")
            d["integrator"] = {"type": "amrvolpath", "mode": mode, "step_scale": 0.25}
            return mi.load_dict(d)
        a = render_passes(scene("ray_march"), 8, 4)
        b = render_passes(scene("emission_absorption"), 16, 64, seed0=1000)
    z = block_z_scores(a, b, 4)
    assert np.isfinite(a).all() and np.abs(z).max() < Z_MAX, np.abs(z).max()


def test08_surfaces_are_shaded_locally_without_noise(llvm):
    """The marcher's picture has no noise anywhere: a diffuse floor (no
    medium in front) under a directional light shows ``reflectance *
    (AMBIENT + DIFFUSE max(n.l, 0))``, the same for two seeds; the light
    from below the floor leaves the ambient share (power)."""
    T = mi.ScalarTransform4f

    def floor(direction, seed):
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "amrvolpath", "mode": "ray_march"},
            "sensor": {"type": "perspective", "fov": 30, "to_world": T().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 8, "height": 8}},
            "floor": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                                                        "value": [0.5, 0.4, 0.3]}}},
            "sun": {"type": "directional", "direction": direction, "irradiance": {"type": "rgb", "value": 3.0}}})
        return np.array(mi.render(scene, spp=2, seed=seed))
    d = np.array([0.6, 0.0, -0.8])
    img = floor(d.tolist(), 0)
    want = np.array([0.5, 0.4, 0.3]) * (AMBIENT + DIFFUSE * 0.8)
    np.testing.assert_allclose(img, np.broadcast_to(want, img.shape), rtol=1e-5)
    np.testing.assert_allclose(floor(d.tolist(), 1), img, rtol=1e-5)
    below = floor((-d).tolist(), 0)
    np.testing.assert_allclose(below, np.broadcast_to(np.array([0.5, 0.4, 0.3]) * AMBIENT, img.shape), rtol=1e-5)


def _render_cloud(tmp_path, mode, seed, spp=None):
    """``mi-amr render scenes/data/cloud.cells --res 32 --mode MODE`` in
    this process: the image (numpy)."""
    from mi_amr.images import read_exr
    from mi_amr.tools.cli import main
    out = tmp_path / f"{mode}-{seed}.exr"
    argv = ["render", "scenes/data/cloud.cells", "--res", "32", "--mode", mode, "--seed", str(seed), "-o", out]
    assert main([str(a) for a in argv + ([] if spp is None else ["--spp", spp])]) == 0
    return read_exr(out)


def test09_the_command_line_marches_data_at_a_few_samples(llvm, tmp_path, capsys):
    """``mi-amr render DATA --mode ray_march``: 4 spp unless asked (said in
    its printout), the written scene keeps the mode, the picture is finite
    and shows the data."""
    a = _render_cloud(tmp_path, "ray_march", 0)
    assert "4 spp" in capsys.readouterr().out
    assert 'value="ray_march"' in (tmp_path / "ray_march-0.xml").read_text()
    assert np.isfinite(a).all() and a.std() > 0.05


@pytest.mark.slow
def test09b_the_marched_picture_has_no_noise(llvm, tmp_path):
    """Two seeds of the command line's marched picture differ less than a
    fifth as much as ``emission_absorption``'s two seeds at the same spp
    (only the pixels' footprints differ). Slow: the data scene's
    emission_absorption kernels are its own."""
    a, b = _render_cloud(tmp_path, "ray_march", 0), _render_cloud(tmp_path, "ray_march", 1)
    c, d = _render_cloud(tmp_path, "emission_absorption", 0, 4), _render_cloud(tmp_path, "emission_absorption", 1, 4)
    assert np.abs(a - b).mean() < 0.2 * np.abs(c - d).mean()


def test10_glowing_gas_adds_its_emission_as_emission_absorption_does(llvm):
    """The two halves of tests/test_emission.py test01b (values 0.25 then
    0.75 along the ray, emission in proportion to the value, sigma
    constant, black TF colour): the marcher gives ``L_e1 (1 - e^{-s/2}) +
    e^{-s/2} L_e2 (1 - e^{-s/2})`` exactly (nearest: no noise; 1e-5)."""
    from test_emission import BLACK, GLOW, ortho_scene, two_level_cells
    sigma, scale = 1.3, 2.0
    cells = two_level_cells()
    glow = TransferFunction(np.array([[*GLOW, 0.0], [*GLOW, 1.0]]), (0.0, 1.0))
    medium = {"type": "amr", "data": AMRCells(cells.pos, cells.level, cells.value), "transfer_function": BLACK,
              "density_scale": sigma, "reconstruction": "nearest", "emission": glow, "emission_scale": scale}
    img = np.array(mi.render(mi.load_dict(ortho_scene(medium, mode="ray_march")), spp=2, seed=5)).reshape(-1, 3)
    half = np.exp(-sigma / 2)
    expected = scale * np.asarray(GLOW) * (0.25 * (1 - half) + half * 0.75 * (1 - half))
    # every pixel's ray crosses the slab over a length within 2.2e-4 of 1
    np.testing.assert_allclose(img, np.broadcast_to(expected, img.shape), rtol=5e-4)
