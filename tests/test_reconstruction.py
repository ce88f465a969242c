"""Reconstruction (nearest, tent) against brute force, and the macrocell
value ranges that bound it."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.structures.macrocell_grid import MacrocellGrid
from mi_amr.device.hash_sampler import DeviceReconstruction
from mi_amr.structures.host_reconstruction import HostReconstruction
from mi_amr.testing import brute_force

from conftest import random_amr


@pytest.mark.parametrize("method", ["tent", "nearest"])
def test04_reconstruction_matches_brute_force(variant, method):
    cells = random_amr(7, n=16, levels=4)
    assert len(cells.levels) >= 3
    host = HostReconstruction(cells)
    dev = DeviceReconstruction(cells, method)
    rng = np.random.default_rng(2)
    x = rng.uniform(-2, 18, (3000, 3))
    # also exact cell corners and centres, where ties are decided
    x[:500] = np.round(x[:500] * 2) / 2
    ref, ref_found = brute_force(cells, x, method)
    val, found = host(x, method)
    np.testing.assert_array_equal(found, ref_found)
    np.testing.assert_allclose(val, ref, atol=1e-9)
    xr = (x - dev.origin).astype(np.float32)
    dval, dfound = dev.eval(mi.Vector3f(xr.T), mi.UInt32(sum(1 << int(L) for L in cells.levels)))
    np.testing.assert_array_equal(dfound.numpy(), ref_found)
    np.testing.assert_allclose(dval.numpy(), ref, atol=2e-6)


def test05_tent_is_trilinear_inside_single_level():
    rng = np.random.default_rng(3)
    v = rng.random((6, 5, 4)).astype(np.float32)
    cells = mi_amr.dense_to_amr(v, 0.0, 0)
    from scipy.interpolate import RegularGridInterpolator
    interp = RegularGridInterpolator([np.arange(n) + 0.5 for n in (4, 5, 6)], v.transpose(2, 1, 0))
    x = rng.uniform(0.5, 1, (500, 3)) * np.array([3, 4, 5])
    val, found = HostReconstruction(cells)(x, "tent")
    assert found.all()
    np.testing.assert_allclose(val, interp(x), atol=1e-6)


@pytest.mark.parametrize("method", ["tent", "nearest"])
def test06_macrocell_ranges_contain_reconstructed_values(method):
    cells = random_amr(11, n=16, levels=4)
    grid = MacrocellGrid(cells, resolution=5, support=method)
    lo, hi = cells.bounds
    rng = np.random.default_rng(4)
    u = rng.random((20000, 3))
    u[:2000] = np.round(u[:2000] * 10) / 10        # on macrocell faces
    x = lo + u * (hi - lo)
    val, found = HostReconstruction(cells)(x, method)
    idx = np.clip(np.floor(u * grid.res), 0, grid.res - 1).astype(int)
    flat = idx[:, 0] + grid.res[0] * (idx[:, 1] + grid.res[1] * idx[:, 2])
    assert np.all(grid.vmin[flat[found]] <= val[found] + 1e-6)
    assert np.all(grid.vmax[flat[found]] >= val[found] - 1e-6)
    # and every level that contributes is in the macrocell's level mask
    assert np.all(grid.level_bits[flat] != 0)

