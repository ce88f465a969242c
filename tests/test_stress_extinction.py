"""Stress tests of extinction (marker ``stress``): Beer-Lambert from
tau = 1e-6 to 1e6, values at and beyond the TF domain, single-entry TF
peaks and all-zero TFs. ``--stress-size large`` runs bigger cases."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr

from stress_oracles import constant_cells, box_lengths, optical_depth_nearest, ratio_tracking, grid_majorant_at, assert_transmittance, spiky_cells, single_entry_tf

pytestmark = pytest.mark.stress


@pytest.mark.parametrize("traversal", ["grid", "brick"])
@pytest.mark.parametrize("tau", [1e-6, 1e-2, 1.0, 5.0, 30.0, 1e3])
def test01_ratio_tracking_matches_beer_lambert(llvm, tau, traversal, stress_size):
    """Transmittance through a constant medium along axis-parallel, diagonal
    and degenerate-direction rays equals exp(-sigma d) within 4 standard errors."""
    med = mi.load_dict({"type": "amr", "data": constant_cells(), "transfer_function": "constant",
                        "density_scale": tau, "traversal": traversal, "sampling": "hash"})
    n = 20000 if stress_size == "small" else 2_000_000
    rng = np.random.default_rng(1)
    o = np.column_stack([rng.random(n), rng.random(n), np.full(n, -1.0)])   # enter through z = 0
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    d[: n // 4] = [1e-30, -1e-30, 1.0]                                    # tiny components
    d[n // 2:] = [0.3, -0.2, 1.0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    T, counts = ratio_tracking(med, o, d, 1, seed=3)
    T = T[:, 0]
    length = box_lengths(o, d, np.zeros((1, 3)), np.ones((1, 3)))[:, 0]   # inside the unit cube
    expected = np.exp(-tau * length)
    assert np.isfinite(T).all() and (T >= 0).all() and (T <= 1 + 1e-6).all()
    diff = T - expected
    # standard error: the sample's, but never below the binomial one that a
    # tight majorant gives (T is 0 or 1 per ray when mu = sigma_t), which a
    # sample without any collision (tau = 1e-6) cannot estimate
    se = max(diff.std() / np.sqrt(n), np.sqrt(np.mean(expected * (1 - expected)) / n), 1e-7)
    assert abs(diff.mean()) < 4 * se, (diff.mean(), se)
    assert counts.capped.numpy().sum() == 0
    # tracking cost stays bounded: about tau * length look-ups per ray
    assert counts.lookups.numpy().mean() < 3 * tau * length.mean() + 2


@pytest.mark.parametrize("alpha,scale", [(1.0, 1e6), (1e-6, 1e12)])
def test06_extinction_up_to_1e6_stays_bounded(llvm, alpha, scale):
    """tau = 1e6 through a constant medium (opacity 1 x density 1e6, or
    opacity 1e-6 x density 1e12): T = 0 after one look-up per ray (tight
    majorant), free-flight distances follow Exp(sigma) (mean 1/sigma), and
    images are finite and obey the white furnace."""
    from conftest import volume_scene
    tau = alpha * scale
    tf = mi_amr.TransferFunction([[1, 1, 1, alpha]] * 2, (0.0, 2.0))
    med = mi.load_dict({"type": "amr", "data": constant_cells(), "transfer_function": tf,
                        "density_scale": scale})
    n = 4096
    rng = np.random.default_rng(2)
    o = np.column_stack([rng.random(n), rng.random(n), np.full(n, -1.0)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    T, counts = ratio_tracking(med, o, d, 1)
    assert (T == 0).all()
    assert counts.lookups.numpy().max() == 1 and counts.capped.numpy().sum() == 0
    ray = mi.Ray3f(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f(d.T.astype(np.float32)))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, n)
    flight = med.free_flight(ray, mi.Float(np.inf), sampler, mi.Bool(True))
    depth = flight.t.numpy() - 1.0                   # distance travelled inside
    assert flight.collided.numpy().all() and np.allclose(flight.sigma_t.numpy(), tau, rtol=1e-6)
    # Exp(tau): mean 1/tau, standard error 1/(tau sqrt(n)); t is float32 near 1
    # (spacing 1.2e-7), so allow that rounding on top
    assert abs(depth.mean() - 1 / tau) < 4 / (tau * np.sqrt(n)) + 1.2e-7, depth.mean()
    for integrator in ("volpath", "amrvolpath"):
        scene = mi.load_dict(volume_scene({"type": "amr", "data": constant_cells(), "transfer_function": tf,
                                           "density_scale": scale}, res=16, integrator=integrator, emitters="env"))
        img = np.array(mi.render(scene, spp=4))
        assert np.isfinite(img).all()
        # white furnace: albedo 1 and a constant environment, so each path
        # brings back the environment's radiance or (cut at max_depth) nothing
        env = np.array([0.6, 0.7, 0.8])
        assert (img <= env + 1e-5).all() and img.mean() > 0.2


@pytest.mark.parametrize("value", [0.25, 1.0, 1.5, 2.0, 7.0])
def test10_values_at_below_and_above_the_tf_domain(llvm, value):
    """Values outside the TF domain take the end entries (clamped, as in
    ParaView); the majorants cover them, so ratio tracking matches
    exp(-sigma d) at, below, inside and above the domain [1, 2]."""
    rgba = np.column_stack([np.ones((3, 3)), [0.2, 0.5, 0.9]])
    tf = mi_amr.TransferFunction(rgba, (1.0, 2.0))
    med = mi.load_dict({"type": "amr", "data": constant_cells(4, value), "transfer_function": tf,
                        "density_scale": 2.0, "reconstruction": "nearest"})
    u = np.clip((value - 1.0) / 1.0, 0, 1) * 2
    alpha = np.interp(u, [0, 1, 2], rgba[:, 3])
    _, sigma = med.eval_local(mi.Vector3f([0.3], [0.6], [0.2]), True)
    assert sigma.numpy()[0] == pytest.approx(2.0 * alpha, rel=1e-6)
    rng = np.random.default_rng(1)
    o = np.column_stack([rng.random(64), rng.random(64), np.full(64, -0.5)])
    d = np.tile([0.0, 0.0, 1.0], (64, 1))
    T, counts = ratio_tracking(med, o, d, 256)
    assert_transmittance(T, np.full(64, np.exp(-2.0 * alpha)))


@pytest.mark.parametrize("traversal", ["grid", "kdtree", "brick"])
def test11_single_entry_tf_peak(llvm, traversal):
    """A TF with one non-zero entry: with nearest reconstruction the cells of
    exactly that value are opaque and all others empty, and ratio tracking
    matches the exact optical depth per ray; with tent reconstruction every
    density stays below the majorant of the macrocell or leaf holding it
    (interpolated values cross the peak between cells)."""
    cells = spiky_cells()
    assert (cells.value == 0.5).any() and (cells.value != 0.5).any()
    tf = single_entry_tf(0.5)
    med = mi.load_dict({"type": "amr", "data": cells, "reconstruction": "nearest", "transfer_function": tf,
                        "density_scale": 4.0, "traversal": traversal})
    rng = np.random.default_rng(8)
    o = np.column_stack([rng.random((150, 2)), np.full(150, -0.5)])
    d = np.column_stack([rng.normal(0, 0.3, (150, 2)), np.ones(150)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sigma = 4.0 * tf(cells.value)[:, 3].astype(np.float64)
    assert set(np.unique(sigma)) == {0.0, 4.0}
    T, counts = ratio_tracking(med, o, d, 256)
    assert_transmittance(T, np.exp(-optical_depth_nearest(cells, sigma, o, d)))
    # tent: sigma <= the majorant of the structure cell holding each point
    tent = mi.load_dict({"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 4.0,
                         "traversal": traversal})
    u = rng.random((200000, 3)).astype(np.float32)
    _, s = tent.eval_local(mi.Vector3f(u.T.copy()), True)
    s = s.numpy()
    assert s.max() > 3.0                             # the peak is met somewhere
    seg = tent.structures.segments()
    if traversal == "grid":
        mu = grid_majorant_at(tent, u)
    else:
        leaf = seg.tree.locate(mi.Vector3f(u.T.copy()), mi.Vector3f(1, 1, 1))
        mu = dr.gather(mi.Float, seg.tree.majorant, leaf).numpy()
    assert (s <= mu * (1 + 1e-6)).all(), np.max(s - mu)


@pytest.mark.parametrize("traversal", ["grid", "kdtree"])
def test18_all_zero_tf_costs_nothing_and_shows_the_background(llvm, traversal):
    """Opacity 0 everywhere: no density look-up and no traversal step in
    amrvolpath, and both integrators return exactly the background."""
    from conftest import random_amr, volume_scene
    tf = mi_amr.TransferFunction(np.column_stack([np.ones((8, 3)), np.zeros(8)]), (0.0, 1.0))
    for integrator in ("volpath", "amrvolpath"):
        d = volume_scene({"type": "amr", "data": random_amr(seed=3), "transfer_function": tf,
                          "density_scale": 1e6, "traversal": traversal},
                         res=12, integrator=integrator, emitters="env")
        if integrator == "amrvolpath":
            d["integrator"]["counters"] = True
        scene = mi.load_dict(d)
        img = np.array(mi.render(scene, spp=4))
        np.testing.assert_array_equal(img, np.broadcast_to(np.float32([0.6, 0.7, 0.8]), img.shape))
        if integrator == "amrvolpath":
            c = scene.integrator().counters()
            assert c["lookups"] == 0 and c["steps"] == 0 and c["shadow_lookups"] == 0

