"""Reconstruction (nearest, tent) against brute force, the macrocell
value ranges that bound it, and the registry of methods."""

import re

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.structures.macrocell_grid import MacrocellGrid
from mi_amr.device.hash_sampler import DeviceReconstruction
from mi_amr.reconstruction import METHODS, reconstruction_method
from mi_amr.reconstruction.tent import Tent
from mi_amr.structures.host_reconstruction import HostReconstruction
from mi_amr.testing import brute_force
from mi_amr.data.volume import as_method, as_volume

from conftest import random_amr


@pytest.mark.parametrize("method", ["tent", "nearest"])
def test04_reconstruction_matches_brute_force(variant, method):
    cells = random_amr(7, n=16, levels=4)
    assert len(cells.levels) >= 3
    host = HostReconstruction(as_volume(cells))
    dev = DeviceReconstruction(as_volume(cells, method), as_method(method))
    rng = np.random.default_rng(2)
    x = rng.uniform(-2, 18, (3000, 3))
    # also exact cell corners and centres, where ties are decided
    x[:500] = np.round(x[:500] * 2) / 2
    ref, ref_found = brute_force(cells, x, method)
    val, found = host(x, as_method(method))
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
    val, found = HostReconstruction(as_volume(cells))(x, as_method("tent"))
    assert found.all()
    np.testing.assert_allclose(val, interp(x), atol=1e-6)


@pytest.mark.parametrize("method", ["tent", "nearest"])
def test06_macrocell_ranges_contain_reconstructed_values(method):
    cells = random_amr(11, n=16, levels=4)
    grid = MacrocellGrid(as_volume(cells, method), resolution=5, support=as_method(method))
    lo, hi = cells.bounds
    rng = np.random.default_rng(4)
    u = rng.random((20000, 3))
    u[:2000] = np.round(u[:2000] * 10) / 10        # on macrocell faces
    x = lo + u * (hi - lo)
    val, found = HostReconstruction(as_volume(cells))(x, as_method(method))
    idx = np.clip(np.floor(u * grid.res), 0, grid.res - 1).astype(int)
    flat = idx[:, 0] + grid.res[0] * (idx[:, 1] + grid.res[1] * idx[:, 2])
    assert np.all(grid.vmin[flat[found]] <= val[found] + 1e-6)
    assert np.all(grid.vmax[flat[found]] >= val[found] - 1e-6)
    # and every level that contributes is in the macrocell's level mask
    assert np.all(grid.level_bits[flat] != 0)


@pytest.mark.parametrize("name", list(METHODS))
def test07_support_box_matches_brute_force(name):
    """Every registered method: a cell gives a value only inside its
    support box (`Reconstruction.support_box`, which the macrocell grid, the
    region trees and the value masks splat), and up to its faces: points
    one step inside each face are found by the method's own oracle."""
    method = reconstruction_method(name)
    rng = np.random.default_rng(5)
    for L in (0, 1, 3):
        w = float(1 << L)
        lo = rng.integers(-8, 8, 3).astype(np.float64) * w
        a, b = method.support_box(lo, w)
        assert np.all(a <= lo) and np.all(b >= lo + w)           # a support holds its cell

        def found_at(x):
            return method.brute_force_chunk(lo[None], np.array([w]), np.array([1.0]), x[:, None, :])[1]
        step = w / 64
        t = -3 * w + step * np.arange(7 * 64 + 1)           # through the cell centre, well past the box
        for axis in range(3):
            x = np.tile(lo + 0.5 * w, (len(t), 1))
            x[:, axis] = lo[axis] + t
            f = found_at(x)
            assert f.any()
            assert np.all((x[f, axis] >= a[axis]) & (x[f, axis] <= b[axis])), (name, L, axis)
            assert x[f, axis].min() - a[axis] <= step and b[axis] - x[f, axis].max() <= step, (name, L, axis)
        x = lo + 0.5 * w + rng.uniform(-3 * w, 3 * w, (4000, 3))
        f = found_at(x)
        assert f.any() and np.all((x[f] >= a) & (x[f] <= b))


def test08_methods_are_resolved_once_from_their_names():
    """Each name resolves to its method object (an object passes through
    and prints as its name), an unknown name is a clear error at every
    entry point, and an object gives what its name gives."""
    for name, cls in METHODS.items():
        method = reconstruction_method(name)
        assert method.name == name and str(method) == name and method == cls()
        assert reconstruction_method(method) is method
    message = re.escape(f"unknown reconstruction 'cubic' (choose from {', '.join(METHODS)})")
    with pytest.raises(ValueError, match=message):
        reconstruction_method("cubic")
    with pytest.raises(ValueError, match="unknown reconstruction None"):
        reconstruction_method(None)
    cells = random_amr(11, n=8, levels=2)
    with pytest.raises(ValueError, match=message):
        MacrocellGrid(as_volume(cells), resolution=4, support=as_method("cubic"))
    with pytest.raises(ValueError, match=message):
        brute_force(cells, np.zeros((1, 3)), "cubic")
    x = np.random.default_rng(6).uniform(-1, 9, (500, 3))
    host = HostReconstruction(as_volume(cells))
    for name in METHODS:
        by_name, by_object = host(x, as_method(name)), host(x, reconstruction_method(name))
        np.testing.assert_array_equal(by_name[0], by_object[0])
        np.testing.assert_array_equal(by_name[1], by_object[1])
        grids = [MacrocellGrid(as_volume(cells), resolution=4, support=as_method(m)) for m in (name, reconstruction_method(name))]
        np.testing.assert_array_equal(grids[0].vmin, grids[1].vmin)
        np.testing.assert_array_equal(grids[0].level_bits, grids[1].level_bits)


class _Wide(Tent):
    """A method of wider support than tent's (1.5 cells), for the structures
    that splat supports: only its reach matters here."""
    name = "wide"
    support_radius = 1.5


@pytest.mark.parametrize("method", [*METHODS, _Wide()])
def test09_brick_domains_are_the_union_of_their_cells_supports(method):
    """`Bricks.domains` (what the ABRs and the brick lists cover) is, for
    every registered method and for a wider one, exactly the union of the
    support boxes of each brick's cells (brute force over the cells)."""
    from mi_amr.structures.bricks import Bricks
    cells = random_amr(12, n=12, levels=3)
    volume = as_volume(cells)
    bricks = Bricks(volume, 4)
    m = reconstruction_method(method)
    dlo, dhi = bricks.domains(m)
    for b in range(len(bricks)):
        w = float(bricks.width[b])
        idx = np.stack(np.meshgrid(*[np.arange(int(d)) for d in bricks.dims[b]], indexing="ij"), -1).reshape(-1, 3)
        lo_cells = bricks.lo[b] + w * idx
        a, c = m.support_box(lo_cells.astype(np.float64), w)
        np.testing.assert_array_equal(dlo[b], a.min(axis=0))
        np.testing.assert_array_equal(dhi[b], c.max(axis=0))
