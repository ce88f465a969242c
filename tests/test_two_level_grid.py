"""The two-level macrocell grid: its refinement rule, its majorants, its walk
and the cost model's choice of it (docs/design.md section 4)."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.data.datasets import make_dataset
from mi_amr.device.grid import MAX_SKIP_EDGE, SKIP_BITS, DeviceTwoLevelGrid
from mi_amr.device.ray import intersect_unit_cube, safe_rcp
from mi_amr.device.segments import TwoLevelGridSegments
from mi_amr.structures.cost_model import GridPlan, auto_grid, plan_cost, refine_gain
from mi_amr.data.volume import as_method, as_volume

from conftest import random_amr


def two_level_medium(reconstruction="nearest", tf="spiky", res=16, f=4, **kw):
    cells = random_amr(seed=2, n=32, levels=3)
    return mi.load_dict({"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 20.0,
                         "reconstruction": reconstruction, "grid_resolution": res,
                         "grid_refinement": f, **kw})


def checkerboard_refinement(med):
    """Refine every other coarse macrocell whatever the rule says (the walk
    must be right for any pattern)."""
    g = med.structures.grid
    rc = np.asarray(g.host.res) // g.refinement
    i = np.arange(g.n_coarse)
    pattern = ((i % rc[0]) + (i // rc[0]) % rc[1] + i // (rc[0] * rc[1])) % 2 == 0
    block_max = dr.block_reduce(dr.ReduceOp.Max, g.fine.majorant, g.refinement ** 3)
    g.coarse_mu = dr.select(mi.Bool(pattern), -1.0, block_max)
    g.coarse_skip = g._skip_cubes(g.coarse_mu != 0.0)
    dr.make_opaque(g.coarse_mu, g.coarse_skip)
    return pattern


def test01_refine_rule(llvm):
    """A coarse macrocell is refined when its look-ups and steps per unit
    length drop: one dense fine macrocell among empty ones, yes; uniform
    majorants or an empty macrocell, no."""
    n, keep, refine = 64.0, 0.5, 4.0
    one_dense = refine_gain(n, 100.0, 100.0, keep, refine, np.maximum)      # mean 100/64
    uniform = refine_gain(n, 64 * 7.0, 7.0, keep, refine, np.maximum)
    empty = refine_gain(n, 0.0, 0.0, keep, refine, np.maximum)
    assert one_dense > 0 and uniform < 0 and empty < 0
    assert one_dense == pytest.approx(keep + 100.0 - refine - 100.0 / 64)
    # the same rule, as the device evaluates it on a TF change
    g = refine_gain(mi.Float(n), mi.Float(100.0, 448.0, 0.0), mi.Float(100.0, 7.0, 0.0),
                    mi.Float(keep), mi.Float(refine), dr.maximum)
    np.testing.assert_allclose(g.numpy(), [one_dense, uniform, empty], rtol=1e-6)


@pytest.mark.parametrize("reconstruction", ["nearest", "tent"])
def test02_majorants_bound_the_field(llvm, reconstruction):
    """Fine majorants equal a uniform grid's at the same resolution; a kept
    coarse macrocell's majorant is the largest of its fine ones; and the
    majorant the walk uses bounds sigma_t at 10^5 random points (a tenth on
    fine macrocell faces and centres)."""
    med = two_level_medium(reconstruction)
    g = med.structures.grid
    assert isinstance(g, DeviceTwoLevelGrid) and g.refinement == 4
    uniform = two_level_medium(reconstruction, f=1)
    f, r = 4, 16
    fine = g.grid_order(g.fine.majorant.numpy())
    np.testing.assert_array_equal(fine, uniform.majorant_grid)
    mu_c = g.coarse_mu.numpy()
    blocks = fine.reshape(4, f, 4, f, 4, f).max(axis=(1, 3, 5)).ravel()
    kept = mu_c >= 0
    assert kept.any() and (~kept).any(), "the rule should refine some coarse macrocells here, not all"
    np.testing.assert_allclose(mu_c[kept], blocks[kept], rtol=1e-6)
    rng = np.random.default_rng(3)
    u = rng.random((100_000, 3)).astype(np.float32)
    u[:10_000] = (rng.integers(0, 2 * r + 1, (10_000, 3)) / (2 * r)).astype(np.float32)
    mei = dr.zeros(mi.MediumInteraction3f, len(u))
    mei.p = mi.Point3f(u.T)
    _, _, sigma_t = med.get_scattering_coefficients(mei)
    st = np.array(sigma_t)[0]
    idx = np.clip(np.floor(u * r), 0, r - 1).astype(int)
    maj = med.majorant_grid[idx[:, 2], idx[:, 1], idx[:, 0]]
    assert np.all(st <= maj * (1 + 1e-5) + 1e-6) and st.max() > 0
    assert med.global_majorant == pytest.approx(float(fine.max()))


def walk(med, o, d):
    """All segments of rays ``o + t d`` (local, numpy (N, 3)) through the
    unit cube: (t0, t1, mu, valid), each (steps, N)."""
    seg = TwoLevelGridSegments(med.structures.grid)
    oj, dj = mi.Vector3f(o.T.astype(np.float32)), mi.Vector3f(d.T.astype(np.float32))
    hit, t_lo, t_hi = intersect_unit_cube(oj, safe_rcp(dj))
    t_lo = dr.maximum(t_lo, 0.0)
    state, fixed = seg.begin(oj, dj, t_lo, t_hi, hit)
    out = []
    for _ in range(int(seg.max_steps()[0]) + 1):
        state, s = seg.advance(oj, dj, state, fixed, t_hi, hit)
        out.append([s.t0.numpy(), s.t1.numpy(), s.mu.numpy(), s.valid.numpy()])
        if not s.valid.numpy().any():
            break
    t0, t1, mu, valid = (np.array(x) for x in zip(*out))
    return t0, t1, mu, valid, t_lo.numpy(), t_hi.numpy(), hit.numpy()


def test03_walk_tiles_each_ray_with_the_right_majorants(llvm):
    """Random, axis-parallel and face-grazing rays: the segments of the walk
    follow each other without gap or overlap from the ray's entry to its
    exit, every step moves forward, the walk ends within `max_steps`, and
    each segment carries the majorant the grid holds at its quarter points
    (the fine one in a refined coarse macrocell, the coarse one elsewhere), for
    a checkerboard of refined coarse macrocells."""
    med = two_level_medium()
    refined = checkerboard_refinement(med)
    check_walk(med)
    assert refined.any() and (med.majorant_grid > 0).any()


def test03b_walk_skips_empty_space(llvm):
    """Where the TF leaves coarse macrocells empty, the walk crosses the
    empty cube that stretches from them along the ray's octant in one step
    (``coarse_skip``: per octant, the largest power-of-two cube up to
    ``MAX_SKIP_EDGE`` with the macrocell as its corner that brute force
    finds empty, or a smaller one only where the next one would reach below
    the grid) and still tiles each ray with the right majorants."""
    med = two_level_medium(res=32, f=2, tf=mi_amr.TransferFunction(
        [[1, 1, 1, 0], [1, 1, 1, 0], [1, 1, 1, 0], [1, 1, 1, 1]], (0.0, 1.0)))
    g = med.structures.grid
    rc = np.asarray(g.host.res) // g.refinement
    occupied = (g.coarse_mu.numpy() != 0).reshape(rc[2], rc[1], rc[0])
    words = g.coarse_skip.numpy().reshape(rc[2], rc[1], rc[0])
    got = np.stack([1 << ((words >> (SKIP_BITS * o)) & ((1 << SKIP_BITS) - 1)) for o in range(8)])
    zs, ys, xs = np.meshgrid(*[np.arange(r) for r in rc[::-1]], indexing="ij")
    for octant in range(8):
        down = [(octant >> axis) & 1 for axis in range(3)]      # x, y, z
        for z, y, x in zip(zs.ravel(), ys.ravel(), xs.ravel()):
            k = got[octant, z, y, x]

            def box(m):
                lo = [c - (m - 1) * dn for c, dn in zip((x, y, z), down)]
                return tuple(slice(max(l, 0), max(l + m, 0)) for l in lo[::-1])

            def empty(m):
                return not occupied[box(m)].any()
            if occupied[z, y, x]:
                assert k == 1
                continue
            assert 1 <= k <= MAX_SKIP_EDGE and k & (k - 1) == 0 and empty(k), (octant, x, y, z, k)
            below = any(c - (2 * k - 1) * dn < 0 for c, dn in zip((x, y, z), down))
            if 2 * k <= min(max(rc), MAX_SKIP_EDGE) and not below:
                assert not empty(2 * k), (octant, x, y, z, k)     # the largest that brute force finds
    assert (got[:, ~occupied] > 1).any() and occupied.any()
    steps = check_walk(med)
    med_plain = two_level_medium(res=32, f=2, tf=med.tf)
    g2 = med_plain.structures.grid
    g2.coarse_skip = dr.zeros(mi.UInt32, g2.n_coarse)
    assert steps < 0.8 * check_walk(med_plain)


def check_walk(med):
    """Random, axis-parallel and face-grazing rays through ``med``'s walk:
    the assertions of test03. Returns the number of segments."""
    rng = np.random.default_rng(7)
    n = 3000
    o = rng.random((n, 3)) * 1.6 - 0.3
    d = rng.normal(size=(n, 3))
    res = med.majorant_grid.shape[0]
    o[:500, :2] = rng.integers(0, res + 1, (500, 2)) / res    # along fine macrocell edges
    o[:500, 2] = -0.2
    d[:500] = [0, 0, 1]
    d[500:800, 0] = 0                                            # in planes x = const
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t0, t1, mu, valid, t_lo, t_hi, hit = walk(med, o, d)
    assert hit.sum() > 1500
    assert not valid[-1].any(), "a ray is still walking after max_steps"
    k = valid.sum(axis=0)
    for i in np.nonzero(hit & (t_hi > t_lo))[0][:2000]:
        a, b, m = t0[:k[i], i], t1[:k[i], i], mu[:k[i], i]
        assert a[0] == t_lo[i] and b[-1] == pytest.approx(t_hi[i], abs=1e-6)
        np.testing.assert_array_equal(a[1:], b[:-1])
        assert np.all(b > a)
        long = (b - a) > 1e-4                    # guard steps are 1e-7 long
        for frac in (0.25, 0.5, 0.75):           # a skip segment crosses several macrocells
            x = o[i] + d[i] * (a + frac * (b - a))[:, None]
            c = np.clip(np.floor(x * res), 0, res - 1).astype(int)
            eff = med.majorant_grid[c[:, 2], c[:, 1], c[:, 0]]
            np.testing.assert_array_equal(m[long], eff[long])
    return int(k.sum())


def test04_transmittance_equals_the_exact_optical_depth(llvm):
    """Ratio tracking over a checkerboard-refined two-level grid, for rays on
    cell faces, edges and corners: per ray within 5 standard errors of
    exp(-optical depth) of the nearest field."""
    from stress_oracles import assert_transmittance, face_rays, optical_depth_nearest, ratio_tracking
    med = two_level_medium(tf="ramp", f=2, res=8)
    checkerboard_refinement(med)
    cells = med.cells
    o, d = face_rays(32, np.random.default_rng(5), 300)
    sigma = 20.0 * med.tf(cells.value)[:, 3].astype(np.float64)
    expected = np.exp(-optical_depth_nearest(cells, sigma, o, np.where(np.abs(d) < 1e-12, 0.0, d)))
    T, counts = ratio_tracking(med, o, d, 256)
    assert counts.capped.numpy().sum() == 0
    assert_transmittance(T, expected)


def test05_refinement_follows_the_tf(llvm):
    """On a TF change the refined set is decided again on the device, equal
    to the host cost model's decision on the same majorants; an all-zero TF
    refines nothing and gives zero majorants."""
    med = two_level_medium()
    g = med.structures.grid
    for tf in ("spiky", "foggy", "ramp"):
        mi_amr.set_transfer_function(med, tf, density_scale=20.0)
        fine = g.grid_order(g.fine.majorant.numpy())
        _, host = plan_cost(fine.astype(np.float64) * med.world_scale, GridPlan(16, 4))
        np.testing.assert_array_equal(g.coarse_mu.numpy() < 0, host.ravel(), err_msg=tf)
    zero = mi_amr.TransferFunction([[1, 1, 1, 0]] * 4, med.tf.domain)
    mi_amr.set_transfer_function(med, zero, density_scale=20.0)
    assert g.refined_fraction() == 0 and med.majorant_grid.max() == 0


def test06_cost_model_refines_a_small_object_in_a_large_domain(llvm):
    """The stadium data (a small refined torus in a large coarse domain)
    get a two-level grid by default, with its fine macrocells on the
    torus only; uniform data get a uniform grid."""
    cells = make_dataset("stadium", cells=6000, levels=7, seed=1)
    tf = mi_amr.TransferFunction.preset("spiky", cells.value_range)
    plan, costs = auto_grid(as_volume(cells, "nearest"), tf, 600.0, support=as_method("nearest"), masks=True)
    assert plan.refinement > 1 and costs[plan] < min(c for p, c in costs.items() if p.refinement == 1)
    med = mi.load_dict({"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 600.0,
                        "reconstruction": "nearest"})
    g = med.structures.grid
    assert isinstance(g, DeviceTwoLevelGrid) and 0 < g.refined_fraction() < 0.1
    flat = random_amr(seed=1, n=16, levels=1)
    plan, _ = auto_grid(as_volume(flat), mi_amr.TransferFunction.preset("constant", (0.0, 2.0)), 5.0)
    assert plan.refinement == 1


@pytest.mark.parametrize("value,message", [(3, "power of two"), (0, "grid_refinement"), (128, "grid_refinement")])
def test07_bad_refinement_is_refused(llvm, value, message):
    with pytest.raises(RuntimeError, match=message):
        two_level_medium(f=value)


def test08_stock_volpath_stops_its_span_walk_near_the_global_majorant(llvm):
    """Stock volpath asks `intersect_aabb` for the majorant of the rest of
    the ray at every null collision; on a two-level grid that walk stops once
    it meets `SPAN_STOP_SHARE` of the global majorant and answers the global
    one up to the cube's exit. Per ray the answer bounds the exact span's
    majorant and is within 1/share of it; an empty ray is still empty; and
    the image agrees with Mitsuba's own heterogeneous medium on the same
    field (32 passes each, |z| < 4.5 per 4x4 block)."""
    from conftest import volume_scene
    from mi_amr.plugins.medium import SPAN_STOP_SHARE
    from mi_amr.testing import block_z_scores, render_passes
    from mi_amr.reference import reference_medium
    med = two_level_medium(tf="foggy", f=2)
    assert med._span_stop == SPAN_STOP_SHARE
    assert two_level_medium(f=1)._span_stop is None           # uniform grids walk to the end
    rng = np.random.default_rng(4)
    n = 4096
    o = rng.uniform(-0.5, 1.5, (n, 3))
    target = rng.uniform(0.0, 1.0, (n, 3))
    ray = mi.Ray3f(mi.Point3f(*o.T), dr.normalize(mi.Vector3f(*(target - o).T)))
    G = med.global_majorant
    answers = {}
    for stop in (SPAN_STOP_SHARE, None):
        med._span_stop = stop
        found, t0, t1 = med.intersect_aabb(ray)
        mu = med._ray_majorant.mu                 # what get_majorant answers for this ray
        answers[stop] = [np.array(a) for a in (found, t0, t1, mu)]
    (fa, t0a, t1a, mua), (fb, t0b, t1b, mub) = answers[SPAN_STOP_SHARE], answers[None]
    np.testing.assert_array_equal(fa, fb)
    assert fb.sum() > n // 4
    assert np.all(mua[fb] >= mub[fb]) and np.all(mua[fb] <= np.maximum(mub[fb] / SPAN_STOP_SHARE, mub[fb]) + 1e-5)
    # a walk that stopped early runs on to the exit (no trailing trim): some did
    stopped = fb & (mua == np.float32(G))
    assert np.all(t1a[stopped] >= t1b[stopped] - 1e-5) and (t1a[stopped] > t1b[stopped] + 1e-3).sum() > 50
    np.testing.assert_array_equal(t1a[fb & ~stopped], t1b[fb & ~stopped])
    np.testing.assert_allclose(t0a[fb], t0b[fb], atol=1e-5)
    med._span_stop = SPAN_STOP_SHARE
    cells = med.cells
    d = {"type": "amr", "data": cells, "transfer_function": "foggy", "density_scale": 20.0,
         "reconstruction": "nearest", "grid_resolution": 16, "grid_refinement": 2}
    del med
    a = render_passes(mi.load_dict(volume_scene(d, res=24, max_depth=16)), 32, 8, seed0=0)
    tf = mi_amr.TransferFunction.preset("foggy", cells.value_range)
    ref = reference_medium(cells, tf, 20.0, "nearest")
    b = render_passes(mi.load_dict(volume_scene(ref, res=24, max_depth=16)), 32, 8, seed0=50_000)
    z = np.abs(block_z_scores(a, b, 4)).max()
    assert z < 4.5, z
