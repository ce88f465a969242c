"""Stress tests (marker ``stress``): extinction extremes, degenerate rays,
determinism and fuzzed loaders. ``--stress-size large`` runs bigger cases."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.io import read_exabricks

pytestmark = pytest.mark.stress


def constant_cells(n=4):
    """n^3 level-0 cells of value 1: with the `constant` TF, sigma_t = scale."""
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return mi_amr.AMRCells(g, np.zeros(len(g), int), np.ones(len(g)))


@pytest.mark.parametrize("traversal", ["grid", "brick"])
@pytest.mark.parametrize("tau", [1e-6, 1e-2, 1.0, 5.0, 30.0])
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
    ray = mi.Ray3f(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f(d.T.astype(np.float32)))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(3, n)
    T, counts = med.transmittance(ray, mi.Float(np.inf), sampler, mi.Bool(True))
    T = T.numpy()
    # exact path length inside the unit cube
    t0 = np.max(np.minimum((0 - o) / np.where(d == 0, 1e-30, d), (1 - o) / np.where(d == 0, 1e-30, d)), axis=1)
    t1 = np.min(np.maximum((0 - o) / np.where(d == 0, 1e-30, d), (1 - o) / np.where(d == 0, 1e-30, d)), axis=1)
    length = np.clip(t1 - np.maximum(t0, 0), 0, None)
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
    cells = mi_amr.datasets.make_dataset("cloud", cells=2000, seed=3)
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


def test06_domain_too_large_for_the_hash_is_a_clear_error(llvm):
    cells = mi_amr.AMRCells([[0, 0, 0], [1 << 22, 0, 0]], [0, 0], [1.0, 2.0])
    with pytest.raises(Exception, match="at most 2097152 are supported"):
        mi.load_dict({"type": "amr", "data": cells})
