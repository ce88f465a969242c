"""Stress tests of geometry (marker ``stress``): rays on cell faces, edges
and corners, cameras inside the medium, extreme level jumps, coordinates
up to 2^24 and large transforms."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.testing import brute_force

from stress_oracles import constant_cells, box_lengths, optical_depth_nearest, ratio_tracking, grid_majorant_at, assert_transmittance, face_rays, level_jump_cells

pytestmark = pytest.mark.stress


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

