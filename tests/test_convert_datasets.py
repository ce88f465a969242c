"""Dense -> AMR coarsening and the synthetic data sets."""

import numpy as np
import pytest

import mi_amr
from mi_amr.data.datasets import NAMES, make_dataset, uniform_dataset
from mi_amr.reference import resample_dense


def test01_dense_to_amr_is_exact_with_zero_threshold():
    rng = np.random.default_rng(0)
    v = np.round(rng.random((12, 10, 8)) * 2) / 2     # [z, y, x], non-cubic
    v[:8, :8, :8] = 0.25                              # a constant block merges
    c = mi_amr.dense_to_amr(v, 0.0, 3)
    lo, hi = c.bounds
    assert hi.tolist() == [8, 10, 12]
    assert (c.width ** 3).sum() == v.size             # covers every voxel once
    assert c.levels.max() >= 2
    val, found = resample_dense(c, "nearest")
    assert found.all()
    np.testing.assert_array_equal(val, v)


def test02_threshold_merges_within_spread():
    v = np.zeros((8, 8, 8), np.float32)
    v[::2] = 0.05
    coarse = mi_amr.dense_to_amr(v, 0.1, 3)
    exact = mi_amr.dense_to_amr(v, 0.0, 3)
    assert len(coarse) == 1 and coarse.level[0] == 3
    assert abs(coarse.value[0] - 0.025) < 1e-6
    assert len(exact) == 512


def test03_dense_to_amr_rejects_nan():
    v = np.zeros((4, 4, 4))
    v[1, 1, 1] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        mi_amr.dense_to_amr(v)


# cosmo: 8^3 blocks on a power-of-two domain make at least 32,768 cells; its own
# checks are in tests/test_resample_bench.py
@pytest.mark.parametrize("name", [n for n in NAMES if n != "cosmo"])
def test04_datasets_deterministic_and_multilevel(name):
    a = make_dataset(name, cells=3000, seed=5)
    b = make_dataset(name, cells=3000, seed=5)
    c = make_dataset(name, cells=3000, seed=6)
    np.testing.assert_array_equal(a.pos, b.pos)
    np.testing.assert_array_equal(a.value, b.value)
    assert not np.array_equal(a.value, c.value)
    assert len(a.levels) >= 4
    assert 0.5 * 3000 < len(a) < 1.5 * 3000
    lo, hi = a.bounds
    assert (a.width ** 3).sum() == np.prod(hi - lo)     # tiles the domain
    mi_amr.AMRCells(a.pos, a.level, a.value)             # passes full validation
    assert a.value.max() > 0.5                            # the feature is resolved


def test04b_sparse_is_one_uniform_level_mostly_empty():
    """``sparse``: the cloud field on a uniform n^3 grid, one level, most
    cells 0; deterministic; ``cells`` picks n."""
    a = make_dataset("sparse", cells=32 ** 3, seed=5)
    np.testing.assert_array_equal(a.value, uniform_dataset("sparse", 32 ** 3, seed=5).value)
    assert not np.array_equal(a.value, make_dataset("sparse", cells=32 ** 3, seed=6).value)
    assert len(a) == 32 ** 3 and list(a.levels) == [0]
    lo, hi = a.bounds
    assert list(lo) == [0, 0, 0] and list(hi) == [32, 32, 32]
    mi_amr.AMRCells(a.pos, a.level, a.value)             # passes full validation
    assert 0.5 < (a.value == 0).mean() < 0.95 and a.value.max() > 0.5
    assert len(make_dataset("sparse", cells=30000)) == 31 ** 3
    with pytest.raises(ValueError, match="unknown"):
        make_dataset("sparser")


def test05_dataset_size_scales():
    small = make_dataset("cloud", cells=2000)
    large = make_dataset("cloud", cells=40000)
    assert 15 < len(large) / len(small) < 25
