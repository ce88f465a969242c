"""Minorants and the estimators that use them: residual ratio tracking and
decomposition tracking (docs/design.md section 5b)."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.testing import block_z_scores, render_passes

from conftest import random_amr, volume_scene

LEAF_KINDS = [("grid", "hash", {"grid_refinement": 1}), ("grid", "hash", {"grid_refinement": 2}),
              ("kdtree", "hash", {}), ("abr", "abr", {}), ("brick", "brick", {})]


def dense_medium(reconstruction, traversal="grid", sampling="hash", tf="foggy", **kw):
    """Random multi-level data filling their box, with a TF that is nowhere
    zero over most of it: minorants are large."""
    cells = random_amr(seed=6, n=32, levels=3)
    if tf == "foggy":
        lo, hi = cells.value_range
        tf = mi_amr.TransferFunction([[0.9, 0.8, 0.7, 0.3], [0.8, 0.8, 0.8, 0.6], [0.7, 0.8, 0.9, 1.0],
                                      [0.9, 0.9, 0.9, 0.5]], (lo, hi))
    return mi.load_dict({"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 4.0,
                         "reconstruction": reconstruction, "traversal": traversal, "sampling": sampling,
                         "grid_resolution": 8, **kw})


def first_leaf(med, u, d):
    """(minorant, majorant, midpoint) of the first segment of positive
    length of a short ray from each local point ``u`` along ``d``: its
    leaf's bounds hold at every point inside it, such as its midpoint."""
    seg = med.structures.segments()
    o, dj = mi.Vector3f(u.T.copy()), mi.Vector3f(d.T.copy())
    t_hi = mi.Float(1e-3)
    state, fixed = seg.begin(o, dj, mi.Float(0.0), t_hi, mi.Bool(True))
    found = np.zeros(len(u), bool)
    lo_mu, hi_mu, mid = np.zeros(len(u)), np.zeros(len(u)), np.zeros(len(u))
    for _ in range(4):
        state, s = seg.advance(o, dj, state, fixed, t_hi, mi.Bool(True))
        t0, t1 = s.t0.numpy(), s.t1.numpy()
        new = ~found & s.valid.numpy() & (t1 > t0)
        lo_mu[new], hi_mu[new], mid[new] = s.mu_min.numpy()[new], s.mu.numpy()[new], 0.5 * (t0 + t1)[new]
        found |= new
    assert found.all()
    return lo_mu, hi_mu, u + d * mid[:, None]


@pytest.mark.parametrize("reconstruction", ["nearest", "tent"])
@pytest.mark.parametrize("traversal,sampling,extra", LEAF_KINDS)
def test01_minorant_and_majorant_bound_sigma_t(llvm, reconstruction, traversal, sampling, extra):
    """minorant <= sigma_t <= majorant at 10^5 random points (a tenth on cell
    faces and centres), for every leaf kind and both reconstructions, and
    the minorants are not trivially zero."""
    med = dense_medium(reconstruction, traversal, sampling, **extra)
    assert med.volume.covers_bounds
    rng = np.random.default_rng(1)
    u = rng.random((100_000, 3)).astype(np.float32)
    u[:10_000] = (rng.integers(0, 65, (10_000, 3)) / 64).astype(np.float32)
    u = np.clip(u, 0.0, np.nextafter(np.float32(1.0), np.float32(0.0)))
    d = rng.normal(size=u.shape).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(u == 0, np.abs(d), np.where(u > 0.99, -np.abs(d), d))     # into the cube
    lo_mu, hi_mu, x = first_leaf(med, u, d)
    _, sigma = med.eval_local(mi.Vector3f(x.astype(np.float32).T.copy()), True)
    st = sigma.numpy()
    assert np.all(lo_mu <= st * (1 + 1e-6)), np.max(lo_mu - st)
    assert np.all(st <= hi_mu * (1 + 1e-5) + 1e-6)
    assert (lo_mu > 0).mean() > 0.5 and lo_mu.sum() > 0.2 * st.sum()


def test02_data_with_holes_get_no_minorant(llvm):
    """Where the cells do not fill their box a point may have no value, so
    every minorant is 0."""
    cells = random_amr(seed=6, n=16, levels=2)
    keep = np.ones(len(cells.value), bool)
    keep[np.argmax(cells.pos.sum(axis=1))] = False               # a hole in a corner
    holed = mi_amr.AMRCells(cells.pos[keep], cells.level[keep], cells.value[keep])
    med = mi.load_dict({"type": "amr", "data": holed, "transfer_function": "constant", "density_scale": 1.0})
    assert not med.volume.covers_bounds
    assert med.structures.grid.minorant.numpy().max() == 0 and med.global_majorant > 0


def test03_zero_minorants_give_the_plain_estimators_exactly(llvm):
    """With all minorants 0, residual ratio tracking and decomposition
    tracking take the same random numbers and steps as ratio and delta
    tracking: the same image for the same seed."""
    cells = random_amr(seed=6, n=16, levels=2)
    keep = np.ones(len(cells.value), bool)
    keep[0] = False
    holed = mi_amr.AMRCells(cells.pos[keep], cells.level[keep], cells.value[keep])
    med = {"type": "amr", "data": holed, "transfer_function": "ramp", "density_scale": 6.0}
    images = []
    for on in (True, False):
        scene = volume_scene(med, res=16, integrator="amrvolpath")
        scene["integrator"].update(residual_ratio_tracking=on, decomposition_tracking=on)
        images.append(np.array(mi.render(mi.load_dict(scene), spp=8, seed=3)))
    np.testing.assert_array_equal(images[0], images[1])
    assert images[0].std() > 0.01


@pytest.mark.parametrize("traversal,refinement", [("grid", 1), ("grid", 2), ("kdtree", 1)])
def test04_residual_ratio_tracking_matches_the_exact_optical_depth(llvm, traversal, refinement):
    """Residual ratio tracking through a nearest field with large minorants:
    per ray within 5 standard errors of exp(-optical depth), with fewer
    look-ups than plain ratio tracking and a smaller variance."""
    from stress_oracles import assert_transmittance, face_rays, optical_depth_nearest, ratio_tracking
    med = dense_medium("nearest", traversal, grid_refinement=refinement)
    cells = med.cells
    o, d = face_rays(32, np.random.default_rng(5), 300)
    sigma = 4.0 * med.tf(cells.value)[:, 3].astype(np.float64)
    expected = np.exp(-optical_depth_nearest(cells, sigma, o, np.where(np.abs(d) < 1e-12, 0.0, d)))
    results = {}
    for control in (True, False):
        T, counts = ratio_tracking(med, o, d, 256, control=control)
        assert counts.capped.numpy().sum() == 0
        assert_transmittance(T, expected)
        results[control] = (T.var(axis=1).mean(), counts.lookups.numpy().mean())
    assert results[True][1] < 0.7 * results[False][1]
    assert results[True][0] < results[False][0]


def grey_tf(cells):
    """Alpha 0.3-1 over the data, one colour: the albedo is known without a look-up."""
    lo, hi = cells.value_range
    return mi_amr.TransferFunction([[0.8, 0.8, 0.8, a] for a in (0.3, 0.6, 1.0, 0.5)], (lo, hi))


@pytest.mark.parametrize("reconstruction", [pytest.param("nearest", marks=pytest.mark.slow), "tent"])
def test05_decomposition_tracking_agrees_with_stock_volpath(llvm, reconstruction):
    """amrvolpath with both estimators on, against Mitsuba's volpath on the
    same one-colour medium: 32 independent passes each, |z| < 4.5 per 4x4
    block; free-flight look-ups per real collision and look-ups per shadow
    ray both drop below 0.8x of the plain estimators'."""
    cells = random_amr(seed=6, n=32, levels=3)
    med = {"type": "amr", "data": cells, "transfer_function": grey_tf(cells), "density_scale": 4.0,
           "reconstruction": reconstruction}
    a_scene = volume_scene(med, res=24, integrator="amrvolpath")
    a = render_passes(mi.load_dict(a_scene), 32, 8, seed0=0)
    b = render_passes(mi.load_dict(volume_scene(med, res=24, integrator="volpath")), 32, 8, seed0=50_000)
    z = np.abs(block_z_scores(a, b, 4)).max()
    assert z < 4.5, z
    per = {on: _counters(a_scene, on) for on in (True, False)}
    assert per[True]["lookups_per_collision"] < 0.8 * per[False]["lookups_per_collision"]
    assert per[True]["lookups_per_shadow_ray"] < 0.8 * per[False]["lookups_per_shadow_ray"]


def _counters(scene_dict, on, seed=1, spp=8):
    s = dict(scene_dict)
    s["integrator"] = dict(scene_dict["integrator"], counters=True, decomposition_tracking=on,
                           residual_ratio_tracking=on)
    scene = mi.load_dict(s)
    mi.render(scene, spp=spp, seed=seed)
    return scene.integrator().counters()


def test05b_coloured_tf_keeps_delta_tracking(llvm):
    """With a TF of several colours a real collision needs a look-up for its
    albedo, so decomposition tracking would save none: free flights stay
    plain delta tracking (the same counts as with it off), while shadow
    rays still gain from residual ratio tracking."""
    cells = random_amr(seed=6, n=32, levels=3)
    med = dense_medium("nearest")
    scene = volume_scene({"type": "amr", "data": cells, "transfer_function": med.tf, "density_scale": 4.0,
                          "reconstruction": "nearest"}, res=24, integrator="amrvolpath")
    on, off = _counters(scene, True), _counters(scene, False)
    assert on["lookups_per_shadow_ray"] < 0.9 * off["lookups_per_shadow_ray"]      # 0.82 here
    scene["integrator"]["residual_ratio_tracking"] = False
    dt_only = mi.load_dict(dict(scene, integrator=dict(scene["integrator"], counters=True)))
    mi.render(dt_only, spp=8, seed=1)
    c = dt_only.integrator().counters()
    assert (c["lookups"], c["real"]) == (off["lookups"], off["real"])


@pytest.mark.parametrize("traversal,sampling,extra", [k if k[0] != "kdtree" else pytest.param(*k, marks=pytest.mark.slow)
                                                      for k in LEAF_KINDS])
def test05c_estimators_are_on_where_minorants_carry_the_majorant(llvm, traversal, sampling, extra):
    """By default amrvolpath uses the minorant estimators on a medium only
    where its minorants carry at least half of its majorants at load: the
    foggy dense medium (a TF nowhere near zero) yes, the spiky one (zero
    almost everywhere) no; the same counts as with the options set to that
    choice, and the options given still win."""
    foggy = dense_medium("nearest", traversal, sampling, **extra)
    spiky = dense_medium("nearest", traversal, sampling, tf="spiky", **extra)
    assert foggy.minorant_fraction >= 0.5 and foggy.minorants_pay
    assert spiky.minorant_fraction < 0.1 and not spiky.minorants_pay
    del foggy, spiky
    cells = random_amr(seed=6, n=32, levels=3)
    for tf, pays in (("foggy", True), ("spiky", False)):
        med = dense_medium("nearest", traversal, sampling, tf=tf, **extra)
        scene = volume_scene({"type": "amr", "data": cells, "transfer_function": med.tf, "density_scale": 4.0,
                              "reconstruction": "nearest", "traversal": traversal, "sampling": sampling,
                              "grid_resolution": 8, **extra}, res=16, integrator="amrvolpath")
        del med
        s = mi.load_dict(dict(scene, integrator=dict(scene["integrator"], counters=True)))
        mi.render(s, spp=4, seed=1)
        auto = s.integrator().counters()
        del s
        assert auto == _counters(scene, pays, spp=4)
        if pays:
            assert auto != _counters(scene, False, spp=4)


def test06_two_level_coarse_minorant_is_the_least_fine_one(llvm):
    """A kept coarse macrocell's minorant is the smallest minorant of its
    fine macrocells inside the domain."""
    med = dense_medium("nearest", grid_refinement=2, grid_resolution=12)      # 6^3 coarse, no padding
    g = med.structures.grid
    fine = g.fine.minorant.numpy().reshape(-1, 8)
    np.testing.assert_allclose(g.coarse_min.numpy(), fine.min(axis=1), rtol=1e-6)
    med = dense_medium("nearest", grid_refinement=4, grid_resolution=10)      # 3^3 coarse of 4^3, padded
    g = med.structures.grid
    inside = g.fine_inside.numpy().reshape(-1, 64).astype(bool)
    fine = np.where(inside, g.fine.minorant.numpy().reshape(-1, 64), np.inf)
    np.testing.assert_allclose(g.coarse_min.numpy(), fine.min(axis=1), rtol=1e-6)
    assert (~inside).any()
