"""Stress tests (marker ``stress``): extinction extremes, degenerate rays,
determinism and fuzzed loaders. ``--stress-size large`` runs bigger cases."""

import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.data.io import read_exabricks
from mi_amr.testing import brute_force

pytestmark = pytest.mark.stress


def constant_cells(n=4, value=1.0):
    """n^3 level-0 cells of one value: with the `constant` TF, sigma_t = scale."""
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return mi_amr.AMRCells(g, np.zeros(len(g), int), np.full(len(g), value))


# ---- Oracles ------------------------------------------------------------------
def box_lengths(o, d, lo, hi, t_max=np.inf):
    """Length (in the units of ``o``) of each ray ``o + t d`` (t in [0, t_max],
    float64, (R, 3)) inside each half-open box ``[lo, hi)`` ((B, 3)) -> (R, B).
    An axis along which a ray does not move counts as inside when
    ``lo <= o < hi`` there."""
    o, d = o[:, None, :], d[:, None, :]
    lo, hi = lo[None], hi[None]
    flat = d == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t0 = np.where(flat, np.where((lo <= o) & (o < hi), -np.inf, np.inf), np.minimum(ta, tb)).max(axis=2)
    t1 = np.where(flat, np.inf, np.maximum(ta, tb)).min(axis=2)
    t0 = np.maximum(t0, 0.0)
    t1 = np.minimum(t1, t_max)
    return np.clip(t1 - t0, 0.0, None) * np.linalg.norm(d[:, 0, :], axis=1)[:, None]


def optical_depth_nearest(cells, sigma, o, d, chunk=64):
    """Exact optical depth along rays in the unit cube (= data bounds, with
    an identity to_world) through piecewise-constant cells of extinction
    ``sigma`` per cell, t in [0, inf)."""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    clo = (cells.pos - lo) / ext
    chi = (cells.pos + cells.width[:, None] - lo) / ext
    out = np.zeros(len(o))
    for s in range(0, len(o), chunk):
        out[s:s + chunk] = box_lengths(o[s:s + chunk], d[s:s + chunk], clo, chi) @ sigma
    return out


def ratio_tracking(med, o, d, replicas, seed=0):
    """Ratio-tracking transmittance of ``replicas`` copies of each ray:
    ``(T (R, replicas), counts)`` with the rays in the medium's world space."""
    n = len(o) * replicas
    O = np.repeat(o, replicas, axis=0).astype(np.float32)
    D = np.repeat(d, replicas, axis=0).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(O.T.copy()), mi.Vector3f(D.T.copy()))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    T, counts = med.transmittance(ray, mi.Float(np.inf), sampler, mi.Bool(True))
    return T.numpy().reshape(len(o), replicas), counts


def grid_majorant_at(med, u):
    """Majorant of the macrocell holding each local point ``u`` ((M, 3))."""
    g = med.structures.grid
    return dr.gather(mi.Float, g.majorant, g.flat(g.cell_of(mi.Vector3f(np.ascontiguousarray(u.T))))).numpy()


def assert_transmittance(T, expected, z_max=5.0, floor=2e-3):
    """Each ray's mean estimate equals its expected transmittance within
    ``z_max`` standard errors (estimated from the replicas, floored)."""
    assert np.isfinite(T).all() and (T >= 0).all() and (T <= 1 + 1e-5).all()
    mean = T.mean(axis=1)
    se = np.maximum(T.std(axis=1) / np.sqrt(T.shape[1]), floor)
    z = (mean - expected) / se
    worst = int(np.argmax(np.abs(z)))
    assert np.abs(z).max() < z_max, (worst, mean[worst], expected[worst], se[worst])


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


def test02_same_seed_gives_bit_identical_images(llvm):
    cells = mi_amr.data.datasets.make_dataset("cloud", cells=2000, seed=3)
    from conftest import volume_scene
    for integrator in ("volpath", "amrvolpath"):
        scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "spiky",
                                           "density_scale": 50.0}, res=24, integrator=integrator))
        a = np.array(mi.render(scene, spp=4, seed=11))
        b = np.array(mi.render(scene, spp=4, seed=11))
        np.testing.assert_array_equal(a, b)


def test03_camera_inside_the_medium(llvm):
    """Rays that start inside the volume (no boundary crossing) are tracked."""
    cells = constant_cells()
    T = mi.ScalarTransform4f
    scene = {"type": "scene", "integrator": {"type": "amrvolpath", "max_depth": 8},
             "sensor": {"type": "perspective", "fov": 60, "medium": {"type": "ref", "id": "m"},
                        "to_world": T().look_at([0.5, 0.5, 0.5], [0.5, 0.5, 2.0], [0, 1, 0]),
                        "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
             "m": {"type": "amr", "id": "m", "data": cells, "transfer_function": "constant", "density_scale": 3.0},
             "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
             "cube": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                      "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "m"}}}
    img = np.array(mi.render(mi.load_dict(scene), spp=64))
    assert np.isfinite(img).all()
    # albedo 1, constant radiance 1 everywhere: radiance is 1 (up to noise and the depth limit)
    assert 0.7 < img.mean() <= 1.05


@pytest.mark.parametrize("seed", range(40))
def test04_fuzzed_cells_files_give_clear_errors(tmp_path, seed):
    """Random and truncated bytes, inconsistent sizes, NaN/Inf, absurd levels
    and coordinates: a ValueError naming the file, or valid cells."""
    rng = np.random.default_rng(seed)
    kind = seed % 5
    n = int(rng.integers(1, 50))
    rec = np.zeros((n, 4), "<i4")
    rec[:, 3] = 0
    rec[:, :3] = np.arange(n)[:, None] * np.array([1, 0, 0])
    val = rng.random(n).astype("<f4")
    if kind == 0:
        cells_bytes = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        scal_bytes = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
    else:
        if kind == 1:
            rec[rng.integers(0, n), 3] = int(rng.choice([-5, 31, 2**30]))
        elif kind == 2:
            val[rng.integers(0, n)] = rng.choice([np.nan, np.inf, -np.inf])
        elif kind == 3:
            rec[rng.integers(0, n), :3] = int(rng.choice([2**31 - 1, -2**31]))
        cells_bytes, scal_bytes = rec.tobytes(), val.tobytes()
        if kind == 4:
            cells_bytes = cells_bytes[: int(rng.integers(0, len(cells_bytes)))]
    (tmp_path / "f.cells").write_bytes(cells_bytes)
    (tmp_path / "f.scalars").write_bytes(scal_bytes)
    try:
        c = read_exabricks(tmp_path / "f.cells")
    except ValueError as e:
        assert "f.cells" in str(e) or "f.scalars" in str(e)
        return
    assert np.isfinite(c.value).all() and (c.level >= 0).all()


def test05_single_cell_and_huge_beside_tiny_cells(llvm):
    """One cell; a level-8 cell beside 512 level-0 cells; data offset by 2^24."""
    from conftest import volume_scene
    one = mi_amr.AMRCells([[0, 0, 0]], [0], [1.0])
    fine = np.stack(np.meshgrid(*[np.arange(256, 264)] * 3, indexing="ij"), -1).reshape(-1, 3)
    huge = mi_amr.AMRCells(np.concatenate([[[0, 0, 0]], fine]), np.r_[8, np.zeros(len(fine), int)],
                           np.r_[1.0, np.linspace(0, 1, len(fine))])
    c = mi_amr.dense_to_amr(np.random.default_rng(0).random((8, 8, 8)), 0.0, 2)
    far = mi_amr.AMRCells(c.pos + (1 << 24), c.level, c.value)
    for cells in (one, huge, far):
        for integrator in ("volpath", "amrvolpath"):
            scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "ramp",
                                               "density_scale": 5.0}, res=12, integrator=integrator,
                                              emitters="env"))
            img = np.array(mi.render(scene, spp=4))
            assert np.isfinite(img).all()
            # the medium absorbs/scatters something: not the bare background everywhere
            assert np.abs(img - np.array([0.6, 0.7, 0.8])).max() > 1e-3



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
    hit, t, _, sigma_t, c = med.free_flight(ray, mi.Float(np.inf), sampler, mi.Bool(True))
    depth = t.numpy() - 1.0                          # distance travelled inside
    assert hit.numpy().all() and np.allclose(sigma_t.numpy(), tau, rtol=1e-6)
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


def face_rays(n_cells, rng, count):
    """Rays (local unit-cube coordinates) on the faces, edges and corners of
    a grid of ``n_cells`` cells per axis: axis-parallel along cell edges,
    inside face planes, from cell corners, grazing the bounding box and its
    top faces (outside: half-open), with direction components of 0 and 1e-30."""
    k = lambda *shape: rng.integers(0, n_cells + 1, shape) / n_cells   # noqa: E731
    o, d = [], []
    # along z on cell edges (x, y on grid planes), incl. the box faces and edges
    m = count // 5
    o.append(np.column_stack([k(m), k(m), np.full(m, -0.25)]))
    d.append(np.tile([0.0, 0.0, 1.0], (m, 1)))
    # inside an x face plane, oblique in y/z
    o.append(np.column_stack([k(m), rng.random(m), np.full(m, -0.25)]))
    d.append(np.tile([0.0, 0.37, 1.0], (m, 1)))
    # from interior cell corners, axis-parallel (both signs) or diagonal
    c = rng.integers(1, n_cells, (m, 3)) / n_cells
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                     [1, 1, 1], [-1, 1, -1], [1, -1, 0], [0, 1, -1]], dtype=np.float64)
    o.append(c)
    d.append(dirs[rng.integers(0, len(dirs), m)])
    # on face planes with 1e-30 components (the ray stays on the plane in float32)
    o.append(np.column_stack([k(m), k(m), np.full(m, -0.25)]))
    d.append(np.tile([1e-30, 1e-30, 1.0], (m, 1)))
    # grazing the bounding box: on its lower faces (inside) and upper faces (outside)
    rest = count - 4 * m
    face = rng.integers(0, 2, rest).astype(np.float64)
    o.append(np.column_stack([face, rng.random(rest), np.full(rest, -0.25)]))
    d.append(np.tile([0.0, 0.2, 1.0], (rest, 1)))
    d = np.concatenate(d)
    return np.concatenate(o), d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("traversal,sampling", [("grid", "hash"), ("brick", "brick"),
                                                ("abr", "abr"), ("kdtree", "hash")])
def test07_rays_on_faces_edges_and_corners(llvm, traversal, sampling, stress_size):
    """Rays along the faces, edges and corners of cells, bricks, regions and
    macrocells (grid of 8 aligned to level-1 cells) and grazing the bounding
    box: ratio-tracking transmittance equals the exact exp(-optical depth)
    of the piecewise-constant (nearest) field, with half-open cells, per ray
    within 5 standard errors."""
    from conftest import random_amr
    cells = random_amr(seed=4, n=16, levels=3)          # 16 finest cells per axis
    med = mi.load_dict({"type": "amr", "data": cells, "reconstruction": "nearest",
                        "transfer_function": "ramp", "density_scale": 3.0, "grid_resolution": 8,
                        "traversal": traversal, "sampling": sampling, "brick_size": 4})
    rng = np.random.default_rng(5)
    n_rays, replicas = (300, 256) if stress_size == "small" else (3000, 1024)
    o, d = face_rays(16, rng, n_rays)
    sigma = 3.0 * med.tf(cells.value)[:, 3].astype(np.float64)
    d_oracle = np.where(np.abs(d) < 1e-12, 0.0, d)       # flushed, as the medium does
    expected = np.exp(-optical_depth_nearest(cells, sigma, o, d_oracle))
    T, counts = ratio_tracking(med, o, d, replicas)
    assert counts.capped.numpy().sum() == 0
    assert_transmittance(T, expected)
    # the upper faces of the box are outside (half-open): no extinction at all
    outside = (o[:, 0] == 1.0) & (d[:, 0] == 0.0)
    assert outside.any() and (T[outside] == 1.0).all()


@pytest.mark.parametrize("reconstruction", ["nearest", "tent"])
@pytest.mark.parametrize("traversal,sampling", [("grid", "hash"), ("brick", "brick")])
def test08_finest_coordinates_up_to_2_pow_24(llvm, reconstruction, traversal, sampling):
    """A domain 2^24 finest cells wide (level-0 blocks at both far corners,
    level-20 cells between): look-ups at exactly representable points equal
    the float64 oracle, also at the far end, where float32 has no fraction
    bits left (the domain is normalised and stencil weights are computed
    from small fractions)."""
    E = 1 << 24
    blk = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pos = np.concatenate([blk, blk + (E - 4), [[1 << 20, 0, 0], [0, 1 << 20, 0], [E - (1 << 20), 0, 0]]])
    lev = np.r_[np.zeros(2 * len(blk), int), 20, 20, 20]
    val = np.random.default_rng(0).random(len(pos))
    cells = mi_amr.AMRCells(pos, lev, val)
    med = mi.load_dict({"type": "amr", "data": cells, "reconstruction": reconstruction,
                        "transfer_function": "ramp", "traversal": traversal, "sampling": sampling})
    # points: cell centres near the origin, cell corners (integers) at the far end
    near = blk[:32] + 0.5
    far = (blk + (E - 4)).astype(np.float64)
    coarse = np.array([[1 << 20, 0, 0], [0, 1 << 20, 0]]) + 0.5 * (1 << 20)
    x = np.concatenate([near, far, coarse])
    u = (x / E).astype(np.float32)
    assert np.array_equal(u.astype(np.float64) * E, x)            # exact in float32
    _, sigma = med.eval_local(mi.Vector3f(u.T.copy()), True)
    ref, found = brute_force(cells, x, reconstruction)
    expected = np.where(found, med.tf(ref)[:, 3], 0.0)
    np.testing.assert_allclose(sigma.numpy(), expected, rtol=2e-5, atol=2e-6)
    assert found.all()


def test09_loop_bounds_trigger_finite_and_reported(llvm):
    """The tracking loop stops at `max_iterations` (counted as capped, the
    estimate stays finite and in [0, 1]); the ray-majorant walk stops at its
    step bound with a conservative span (to the end, global majorant); an
    amrvolpath render with a tiny bound stays finite and reports the caps.
    The other loops are bounded by their data: reconstruction by levels x
    longest probe, kd descent by the tree depth, brick lists by the longest
    list, the shadow walk by 4096 surfaces."""
    from conftest import volume_scene
    from mi_amr.device.tracking import span_majorant
    from mi_amr.device.ray import intersect_unit_cube, safe_rcp
    cells = constant_cells(16)
    med = mi.load_dict({"type": "amr", "data": cells, "transfer_function": "constant", "density_scale": 0.5,
                        "grid_resolution": 16, "max_iterations": 4})
    n = 1000
    rng = np.random.default_rng(0)
    o = np.column_stack([rng.random(n), rng.random(n), np.full(n, -1.0)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    T, counts = ratio_tracking(med, o, d, 1)
    assert np.isfinite(T).all() and ((T >= 0) & (T <= 1)).all()
    capped = counts.capped.numpy()
    assert capped.sum() > n // 2                     # 16 macrocells to cross, 4 iterations
    assert counts.steps.numpy().max() <= 4
    # the ray-majorant walk: a bound of 2 steps over 16 macrocells
    ray_o = mi.Vector3f(o.T.astype(np.float32))
    ray_d = mi.Vector3f(d.T.astype(np.float32))
    hit, t0, t1 = intersect_unit_cube(ray_o, safe_rcp(ray_d))
    seg = med.structures.segments()
    found, t_first, t_last, mu, cap = span_majorant(seg, ray_o, ray_d, dr.maximum(t0, 0.0), t1, hit, 2,
                                                    mi.Float(med.global_majorant))
    assert cap.numpy().all() and found.numpy().all()
    np.testing.assert_allclose(t_last.numpy(), t1.numpy())
    np.testing.assert_allclose(mu.numpy(), med.global_majorant)
    # a whole render with the tiny bound
    scene = mi.load_dict(dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "constant",
                                            "density_scale": 0.5, "grid_resolution": 16, "max_iterations": 4},
                                           res=8, integrator="amrvolpath", emitters="env"),
                              integrator={"type": "amrvolpath", "counters": True}))
    img = np.array(mi.render(scene, spp=4))
    assert np.isfinite(img).all()
    assert scene.integrator().counters()["capped"] > 0


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


def spiky_cells():
    """Random 3-level data whose values are multiples of 1/4."""
    from conftest import random_amr
    return random_amr(seed=7, n=16, levels=3, quantize=4)


def single_entry_tf(value, n=65, domain=(0.0, 1.0)):
    """Opacity 1 in the one table entry at ``value``, 0 elsewhere."""
    rgba = np.zeros((n, 4))
    rgba[:, :3] = 0.8
    k = int(round((value - domain[0]) / (domain[1] - domain[0]) * (n - 1)))
    rgba[k, 3] = 1.0
    return mi_amr.TransferFunction(rgba, domain)


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


def level_jump_cells(jump, seed=0):
    """A level-``jump`` cell beside level-0 cells: the cell fills
    [0, 2^J)^3; beside it (x in [2^J, 2^(J+1))) one branch refines towards
    the shared face, level by level down to 0."""
    rng = np.random.default_rng(seed)
    pos, lev = [[0, 0, 0]], [jump]
    corner = np.array([1 << jump, 0, 0])
    for L in range(jump - 1, -1, -1):
        kids = corner + (np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)]) << L)
        keep = kids if L == 0 else kids[1:]          # child 0 (touching the cell) refines on
        pos += keep.tolist()
        lev += [L] * len(keep)
    if jump == 0:
        pos, lev = [[0, 0, 0], [1, 0, 0]], [0, 0]
    return mi_amr.AMRCells(pos, lev, rng.random(len(pos)))


@pytest.mark.parametrize("jump", range(0, 9))
def test12_level_jumps_between_neighbours(llvm, jump):
    """Level jumps of 0 (one level only) to 8 between face neighbours:
    nearest transmittance equals the exact one through the jump; tent values
    equal the brute-force oracle and stay below the macrocell majorants."""
    cells = level_jump_cells(jump)
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    med = mi.load_dict({"type": "amr", "data": cells, "reconstruction": "nearest",
                        "transfer_function": "ramp", "density_scale": 3.0})
    rng = np.random.default_rng(jump)
    # rays along x through the shared face, near the refined corner
    m = 120
    o = np.column_stack([np.full(m, -0.25), rng.random(m) ** 3, rng.random(m) ** 3])
    d = np.column_stack([np.ones(m), rng.normal(0, 0.05, (m, 2))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sigma = 3.0 * med.tf(cells.value)[:, 3].astype(np.float64)
    T, _ = ratio_tracking(med, o, d, 256)
    assert_transmittance(T, np.exp(-optical_depth_nearest(cells, sigma, o, d)))
    tent = mi.load_dict({"type": "amr", "data": cells, "transfer_function": "ramp", "density_scale": 3.0})
    u = np.column_stack([0.5 + 0.5 * (rng.random(4000) - 0.5) ** 3, rng.random((4000, 2)) ** 3])
    u = u.astype(np.float32)
    _, s = tent.eval_local(mi.Vector3f(u.T.copy()), True)
    ref, found = brute_force(cells, lo + u.astype(np.float64) * ext, "tent")
    expected = np.where(found, 3.0 * tent.tf(ref)[:, 3], 0.0)
    np.testing.assert_allclose(s.numpy(), expected, rtol=1e-4, atol=1e-5)
    mu = grid_majorant_at(tent, u)
    assert (s.numpy() <= mu * (1 + 1e-6)).all()


@pytest.mark.parametrize("scale,shift", [(1e-20, 1e-17), (1e-6, 1e-3), (1.0, 0.0), (1.0, 1e3),
                                         (1e6, 1e9), (1e20, 1e23), ((1e2, 1.0, 1e-2), 10.0)])
def test13_to_world_with_large_translations_and_scales(llvm, scale, shift):
    """Constant medium placed by ``translate(shift) @ scale(scale)`` with
    density_scale chosen for the same optical depth: transmittance along
    world rays equals exp(-sigma * world length) from 1e-20 to 1e20 world
    units (unit local directions keep the traversal's float maths in range)."""
    T4 = mi.ScalarTransform4f
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    to_world = T4().translate([shift] * 3) @ T4().scale(s.tolist())
    tau = 2.0                                    # per local unit along x
    med = mi.load_dict({"type": "amr", "data": constant_cells(), "transfer_function": "constant",
                        "density_scale": tau / s[0], "to_world": to_world})
    rng = np.random.default_rng(3)
    m = 64
    o_local = np.column_stack([np.full(m, -0.5), rng.random(m), rng.random(m)])
    d_local = np.column_stack([np.ones(m), rng.normal(0, 0.1, (m, 2))])
    o_world = (o_local * s + shift).astype(np.float32)
    d_world = d_local * s
    d_world = (d_world / np.linalg.norm(d_world, axis=1, keepdims=True)).astype(np.float32)
    # the exact answer for the float32 rays that are actually traced
    o_back = (o_world.astype(np.float64) - shift) / s
    d_back = d_world.astype(np.float64) / s
    # box_lengths: local length; divided by the local length per world unit
    length_world = box_lengths(o_back, d_back, np.zeros((1, 3)), np.ones((1, 3)))[:, 0] / np.linalg.norm(
        d_back, axis=1)
    expected = np.exp(-(tau / s[0]) * length_world)
    assert (expected < 0.9).mean() > 0.8 and (expected > 1e-3).all()
    T, counts = ratio_tracking(med, o_world, d_world, 256)
    assert counts.capped.numpy().sum() == 0
    assert_transmittance(T, expected)


def test13b_scaled_scene_renders_the_same_image(llvm):
    """The same scene placed at scale 1e6 and offset 1e7 (density / 1e6)
    renders the same image as at unit scale, within Monte Carlo noise.
    (Larger offsets relative to the scale meet Mitsuba's own limit: surface
    rays are spawned about 5e-6 |p| beyond the surface, so at an offset of
    1e3 x the scale 0.5% of the medium is skipped at each crossing.)"""
    from conftest import random_amr, volume_scene
    cells = random_amr(seed=2)
    T4 = mi.ScalarTransform4f
    imgs = []
    for s, shift in ((1.0, 0.0), (1e6, 1e7)):
        d = volume_scene({"type": "amr", "data": cells, "transfer_function": "ramp",
                          "density_scale": 8.0 / s,
                          "to_world": T4().translate([shift] * 3) @ T4().scale(s)},
                         res=16, integrator="amrvolpath", emitters="env",
                         to_world=T4().translate([shift] * 3) @ T4().scale(s))
        d["sensor"].update(near_clip=1e-2 * s, far_clip=1e2 * s)     # the camera's clip range too
        scene = mi.load_dict(d)
        passes = np.stack([np.array(mi.render(scene, spp=16, seed=k)) for k in range(8)])
        assert np.isfinite(passes).all()
        imgs.append(passes)
    a, b = imgs[0].mean(axis=(1, 2, 3)), imgs[1].mean(axis=(1, 2, 3))    # per-pass image means
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    assert abs(a.mean() - b.mean()) < 4 * se + 1e-4, (a.mean(), b.mean(), se)


def test14_many_tiny_cells_beside_one_huge_cell(llvm, stress_size):
    """N^3 level-0 cells (32^3 = 32768; 128^3 = 2.1 million with
    --stress-size large) beside one cell of level log2(N) as large as all of
    them: structures build, transmittance is exact through both, and both
    integrators render finite images."""
    from conftest import volume_scene
    N = 32 if stress_size == "small" else 128
    L = int(np.log2(N))
    fine = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1).reshape(-1, 3)
    cells = mi_amr.AMRCells(np.concatenate([fine, [[N, 0, 0]]]), np.r_[np.zeros(len(fine), int), L],
                            np.r_[np.full(len(fine), 0.3), 0.9])
    for traversal, sampling in (("grid", "hash"), ("brick", "brick")):
        med = mi.load_dict({"type": "amr", "data": cells, "reconstruction": "nearest",
                            "transfer_function": "ramp", "density_scale": 2.0,
                            "traversal": traversal, "sampling": sampling})
        tf_alpha = med.tf(np.array([0.3, 0.9]))[:, 3].astype(np.float64)
        rng = np.random.default_rng(1)
        m = 100
        o = np.column_stack([np.full(m, -0.25), rng.random(m), rng.random(m)])
        d = np.column_stack([np.ones(m), rng.normal(0, 0.2, (m, 2))])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        boxes_lo = np.array([[0.0, 0, 0], [0.5, 0, 0]])
        boxes_hi = np.array([[0.5, 1, 1], [1.0, 1, 1]])
        depth = box_lengths(o, d, boxes_lo, boxes_hi) @ (2.0 * tf_alpha)
        T, counts = ratio_tracking(med, o, d, 128)
        assert counts.capped.numpy().sum() == 0
        assert_transmittance(T, np.exp(-depth))
    for integrator in ("volpath", "amrvolpath"):
        scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "ramp",
                                           "density_scale": 4.0}, res=16, integrator=integrator))
        img = np.array(mi.render(scene, spp=4))
        assert np.isfinite(img).all() and img.max() > 0


@pytest.mark.parametrize("params,message", [
    ({"colour": 1.0}, "unknown parameter 'colour'"),
    ({"density_scale": "2"}, "density_scale must be a number"),
    ({"density_scale": float("nan")}, "density_scale must be finite"),
    ({"density_scale": -1.0}, "density_scale must be >= 0"),
    ({"grid_resolution": 2.5}, "grid_resolution must be an integer"),
    ({"grid_resolution": "16"}, "grid_resolution must be an integer"),
    ({"grid_resolution": 0}, "grid_resolution must be >= 1"),
    ({"traversal": "octree"}, "unknown traversal 'octree'"),
    ({"traversal": 3}, "traversal must be a string"),
    ({"sampling": True}, "sampling must be a string"),
    ({"reconstruction": "cubic"}, "unknown reconstruction 'cubic'"),
    ({"majorant": "local"}, "unknown majorant 'local'"),
    ({"brick_size": 0}, "brick_size must be >= 1"),
    ({"kdtree_leaves": 1.5}, "kdtree_leaves must be an integer"),
    ({"max_iterations": 0}, "max_iterations must be >= 1"),
    ({"tf_min": 2.0, "tf_max": 1.0}, "tf_min must be below tf_max"),
    ({"tf_min": "low"}, "tf_min must be a number"),
    ({"transfer_function": 3}, "transfer_function must be a preset name"),
    ({"transfer_function": "no-such-map"}, "no-such-map"),
    ({"to_world": "identity"}, "to_world must be a transform"),
    ({"to_world": "SINGULAR"}, "to_world is singular"),
    ({"overlap": "coarsest"}, "unknown overlap 'coarsest'"),
    ({"memory_limit": -5.0}, "memory_limit must be > 0"),
    ({"data": "cells.npz"}, "'data' must be an mi_amr.AMRCells"),
    ({"sample_emitters": "yes"}, "sample_emitters"),
])
def test15_wrong_scene_parameters_give_clear_errors(llvm, params, message):
    base = {"type": "amr", "data": constant_cells(2)}
    if params.get("to_world") == "SINGULAR":
        params = {"to_world": mi.ScalarTransform4f().scale([1.0, 1.0, 0.0])}
    with pytest.raises(Exception, match=re.escape(message)):
        mi.load_dict({**base, **params})


@pytest.mark.parametrize("params,message", [
    ({"max_depth": "8"}, "max_depth must be an integer"),
    ({"max_depth": -2}, "max_depth must be -1"),
    ({"rr_depth": 0}, "rr_depth must be >= 1"),
    ({"counters": 1}, "counters must be true or false"),
    ({"hide_emitters": "no"}, "hide_emitters"),          # Mitsuba's own check
    ({"samples": 4}, "unknown parameter 'samples'"),
])
def test15b_wrong_integrator_parameters_give_clear_errors(llvm, params, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "amrvolpath", **params})


# ---- Memory pre-checks -------------------------------------------------------
def test16_structures_that_do_not_fit_fail_before_allocating(llvm, tmp_path, monkeypatch):
    """A macrocell grid of 10^12 cells, structures above a small memory limit
    and a 100 GiB (sparse) .cells file give a clear error at once, before
    any large allocation."""
    import time
    from mi_amr.memory import MemoryLimitError, parse_bytes
    cells = constant_cells(4)
    t0 = time.perf_counter()
    with pytest.raises(Exception, match=r"macrocell grid of 10000x10000x10000 cells needs about .* TiB"):
        mi.load_dict({"type": "amr", "data": cells, "grid_resolution": 10000})
    with pytest.raises(Exception, match=r"the hash structure .* needs about .*memory limit of 1.0 KiB"):
        mi.load_dict({"type": "amr", "data": cells, "grid_resolution": 2, "memory_limit": 1024.0})
    monkeypatch.setenv("MI_AMR_MEMORY_LIMIT", "2K")
    assert parse_bytes("2K") == 2048
    with pytest.raises(Exception, match="memory limit of 2.0 KiB"):
        mi.load_dict({"type": "amr", "data": cells, "traversal": "brick", "sampling": "brick",
                      "grid_resolution": 2})
    monkeypatch.delenv("MI_AMR_MEMORY_LIMIT")
    # a damaged file claiming 100 GiB of cells: refused from its size alone
    big = tmp_path / "big.cells"
    with open(big, "wb") as f:
        f.truncate(100 << 30)
    with open(tmp_path / "big.scalars", "wb") as f:
        f.truncate(25 << 30)
    with pytest.raises(MemoryLimitError, match="big.cells"):
        read_exabricks(big)
    # an .npz whose header claims 10^12 values
    npz = tmp_path / "huge.npz"
    import zipfile
    with zipfile.ZipFile(npz, "w") as z:
        for name, shape in (("pos", (10**12, 3)), ("level", (10**12,)), ("value", (10**12,))):
            header = {"descr": "<i4", "fortran_order": False, "shape": shape}
            with z.open(f"{name}.npy", "w") as f:
                np.lib.format.write_array_header_1_0(f, header)
    with pytest.raises(MemoryLimitError, match="huge.npz"):
        mi_amr.load_cells(npz)
    assert time.perf_counter() - t0 < 30


# ---- Loader fuzzing (hypothesis) ----------------------------------------------
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _check_loaded_or_clear_error(load, names):
    """``load()`` returns valid cells or raises ValueError/MemoryError naming a file."""
    try:
        c = load()
    except (ValueError, MemoryError) as e:
        assert any(n in str(e) for n in names), str(e)
        return None
    assert len(c) > 0 and np.isfinite(c.value).all() and (c.level >= 0).all()
    assert (c.pos % c.width[:, None] == 0).all()
    return c


@FUZZ
@given(cells_bytes=st.binary(max_size=400), scalars_bytes=st.binary(max_size=200))
def test17_fuzz_random_bytes(tmp_path_factory, cells_bytes, scalars_bytes):
    d = tmp_path_factory.mktemp("fuzz")
    (d / "f.cells").write_bytes(cells_bytes)
    (d / "f.scalars").write_bytes(scalars_bytes)
    _check_loaded_or_clear_error(lambda: read_exabricks(d / "f.cells"), ["f.cells", "f.scalars"])


records = st.lists(st.tuples(st.integers(-2**31, 2**31 - 1), st.integers(-2**31, 2**31 - 1),
                             st.integers(-2**31, 2**31 - 1), st.integers(-40, 40)),
                   min_size=0, max_size=30)
small_records = st.lists(st.tuples(st.integers(0, 7), st.integers(0, 7), st.integers(0, 7),
                                   st.integers(0, 3)), min_size=1, max_size=30)
values = st.floats(allow_nan=True, allow_infinity=True, width=32)


@FUZZ
@given(rec=st.one_of(records, small_records), vals=st.lists(values, max_size=35),
       cut=st.integers(0, 20), overlap=st.sampled_from(["error", "finest"]))
def test17b_fuzz_structured_records(tmp_path_factory, rec, vals, cut, overlap):
    """Well-formed records with absurd levels and coordinates, NaN/Inf values,
    inconsistent counts and truncation: valid cells (which then render-ready
    structures accept) or a clear error."""
    d = tmp_path_factory.mktemp("fuzz")
    cells_bytes = np.asarray(rec, dtype="<i4").reshape(-1, 4).tobytes()
    (d / "f.cells").write_bytes(cells_bytes[: max(0, len(cells_bytes) - cut)])
    (d / "f.scalars").write_bytes(np.asarray(vals, dtype="<f4").tobytes())
    c = _check_loaded_or_clear_error(lambda: read_exabricks(d / "f.cells", overlap=overlap),
                                     ["f.cells", "f.scalars"])
    if c is not None:
        from mi_amr.structures.cell_hash import CellHash
        h = CellHash(c)                               # point location accepts every valid data set
        lo, hi = c.bounds
        assert (hi - lo).max() < 2**31


@FUZZ
@given(pos=st.lists(st.tuples(st.integers(-100, 100), st.integers(-100, 100), st.integers(-100, 100)),
                    max_size=20),
       level=st.lists(st.integers(-3, 40), max_size=20), value=st.lists(values, max_size=20),
       pos_dtype=st.sampled_from(["<i4", "<i8", "<f4"]), junk=st.binary(max_size=64))
def test17c_fuzz_npz(tmp_path_factory, pos, level, value, pos_dtype, junk):
    d = tmp_path_factory.mktemp("fuzz")
    p = d / "f.npz"
    np.savez(p, pos=np.asarray(pos, dtype=pos_dtype).reshape(-1, 3), level=np.asarray(level, dtype="<i4"),
             value=np.asarray(value, dtype="<f4"))
    if junk:                                      # damage the archive
        data = bytearray(p.read_bytes())
        at = len(junk) * 7 % max(len(data), 1)
        data[at:at + len(junk)] = junk
        p.write_bytes(bytes(data))
    _check_loaded_or_clear_error(lambda: mi_amr.load_cells(p), ["f.npz"])


def test09b_shadow_ray_bound_blocks_and_reports(llvm, monkeypatch):
    """A shadow ray that would cross more surfaces than the bound counts as
    blocked (no light leaks) and is reported in the counters; here a bound
    of 1 stops every shadow ray at the medium's boundary."""
    import mi_amr.plugins.integrator as integ
    from conftest import random_amr, volume_scene
    cells = random_amr(seed=1)
    means = []
    for bound in (integ.MAX_SHADOW_CROSSINGS, 1):
        monkeypatch.setattr(integ, "MAX_SHADOW_CROSSINGS", bound)
        d = volume_scene({"type": "amr", "data": cells, "transfer_function": "ramp", "density_scale": 4.0},
                         res=12, integrator="amrvolpath", emitters="sun")
        d["integrator"]["counters"] = True
        scene = mi.load_dict(d)
        img = np.array(mi.render(scene, spp=16, seed=1))
        assert np.isfinite(img).all()
        means.append(img.mean())
        capped = scene.integrator().counters()["shadow_capped"]
        assert (capped > 0) == (bound == 1)
    # sun light reaches the medium only through shadow rays: blocked -> black
    assert means[0] > 1e-3 and means[1] == 0.0


def test15c_bad_updates_are_refused_and_undone(llvm):
    """density_scale of NaN or 1e38 (whose float32 reciprocal flushes to 0
    and would make the medium clear) and NaN TF entries through
    mi.traverse: a clear error, and the medium keeps rendering its last
    valid state."""
    from conftest import volume_scene
    with pytest.raises(Exception, match=r"density_scale must be <= 1e\+30"):
        mi.load_dict({"type": "amr", "data": constant_cells(2), "density_scale": 1e38})
    scene = mi.load_dict(volume_scene({"type": "amr", "data": constant_cells(2), "transfer_function": "ramp",
                                       "density_scale": 3.0}, res=8, integrator="amrvolpath"))
    before = np.array(mi.render(scene, spp=4, seed=0))
    params = mi.traverse(scene)
    k_scale = [k for k in params.keys() if k.endswith("density_scale")][0]
    k_rgba = [k for k in params.keys() if k.endswith("tf_rgba")][0]
    for key, bad in ((k_scale, float("nan")), (k_scale, 1e38), (k_rgba, mi.Float([np.nan] * 8))):
        params[key] = bad
        with pytest.raises(ValueError, match="density_scale|NaN"):
            params.update()
        after = np.array(mi.render(scene, spp=4, seed=0))
        np.testing.assert_array_equal(after, before)


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
