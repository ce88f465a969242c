"""Value masks of the macrocell grid (docs/design.md section 4): they hold
every bin the reconstruction takes, and the majorants they give bound the
extinction and never exceed the range majorants."""

import mitsuba as mi
import numpy as np
import pytest

from mi_amr.data.blocks import BlockVolume
from mi_amr.structures.host_reconstruction import HostReconstruction
from mi_amr.structures.macrocell_grid import MacrocellGrid
from mi_amr.structures.value_masks import ValueBins, byte_tables, mask_max_alpha_host, value_masks
from mi_amr.transfer.function import TransferFunction
from mi_amr.data.volume import as_method, as_volume

from conftest import random_amr

N_POINTS = 100_000


def _points(cells, n=N_POINTS, seed=1):
    lo, hi = cells.bounds
    x = lo + np.random.default_rng(seed).random((n, 3)) * (hi - lo)
    x[: n // 10] = np.round(x[: n // 10] * 2) / 2               # cell faces and centres
    return x


def _macrocell(grid, x):
    r = grid.res
    i = np.minimum(np.floor((x - grid.lo) / grid.extent * r).astype(np.int64), r - 1)
    return i[:, 0] + r[0] * (i[:, 1] + r[1] * i[:, 2])


@pytest.mark.parametrize("method", ["nearest", "tent"])
@pytest.mark.parametrize("seed", [0, 1])
def test01_masks_hold_every_reconstructed_bin(llvm, method, seed):
    """At 10^5 random points (a tenth on cell faces and centres), the bin of
    the reconstructed value is set in the mask of the point's macrocell
    (tent: in every macrocell one level reaches; the others do not use
    their mask). Odd and even resolutions, so macrocell faces fall inside
    and on cell faces."""
    cells = random_amr(seed, n=16, levels=3, quantize=32)
    volume = BlockVolume.from_cells(cells, method=method)
    x = _points(cells, seed=seed)
    value, found = HostReconstruction(volume)(x, as_method(method))
    bins = ValueBins.of(volume)
    for res in (7, 16):
        grid = MacrocellGrid(volume, res, support=as_method(method))
        masks = value_masks(volume, grid, as_method(method), bins)
        m = _macrocell(grid, x)
        applies = found.copy()
        if method == "tent":
            applies &= np.array([bin(int(b)).count("1") <= 1 for b in grid.level_bits])[m]
        assert applies.sum() > N_POINTS // 4
        held = (masks[m] >> bins.index(value).astype(np.uint64)) & np.uint64(1)
        assert np.all(held[applies] == 1), f"{int((held[applies] == 0).sum())} points outside their mask"


def test02_byte_tables_give_the_max_over_set_bins():
    rng = np.random.default_rng(0)
    alpha = rng.random(64).astype(np.float32)
    masks = rng.integers(0, 2**63, 1000).astype(np.uint64) >> rng.integers(0, 64, 1000).astype(np.uint64)
    masks[:3] = [0, np.uint64(1) << np.uint64(63), np.uint64(0xFFFFFFFFFFFFFFFF)]
    bits = (masks[:, None] >> np.arange(64, dtype=np.uint64)[None]) & np.uint64(1)
    brute = np.where(bits == 1, alpha[None], 0.0).max(axis=1)
    np.testing.assert_array_equal(mask_max_alpha_host(alpha, masks), brute)
    assert byte_tables(alpha).shape == (8, 256)


def test03_bins_and_their_edges():
    bins = ValueBins(-1.0, 3.0)
    v = np.array([-1.0, -0.9375, 0.0, 2.999, 3.0, 5.0, -7.0])
    np.testing.assert_array_equal(bins.index(v), [0, 1, 16, 63, 63, 63, 0])
    lo, hi = bins.edges()
    inside = (lo[bins.index(v[:5])] <= v[:5].astype(np.float32)) & (v[:5].astype(np.float32) <= hi[bins.index(v[:5])])
    assert inside.all()
    b = bins.bits(np.array([0.0, 1.0, 2.0]), np.array([0.1, 0.0, 3.0]))
    assert b[0] == (np.uint64(1) << np.uint64(16)) | (np.uint64(1) << np.uint64(17))
    assert b[1] == 0                                      # empty range
    assert b[2] == ~((np.uint64(1) << np.uint64(48)) - np.uint64(1))


@pytest.mark.parametrize("tf_name", ["spiky", "random"])
def test04_medium_majorants_bound_the_extinction(llvm, tf_name):
    """The ``amr`` medium with ``nearest`` and value masks: every macrocell
    majorant is at most the range majorant, at least the extinction at 10^5
    random points of it, and the masks lower the total for a spiky TF."""
    cells = random_amr(3, n=16, levels=3, quantize=32)
    lo, hi = cells.value_range
    if tf_name == "random":
        rgba = np.random.default_rng(5).random((37, 4)) ** 3
        tf = TransferFunction(rgba, (lo + 0.1 * (hi - lo), hi - 0.2 * (hi - lo)))
    else:
        tf = TransferFunction.preset("spiky", (lo, hi))
    media = {vm: mi.load_dict({"type": "amr", "data": cells, "reconstruction": "nearest", "grid_resolution": 16,
                               "transfer_function": tf, "density_scale": 7.0, "value_masks": vm})
             for vm in (False, True)}
    plain, masked = (media[vm].majorant_grid.ravel() for vm in (False, True))
    grid = media[True].structures.device["grid"].host
    assert grid.masks is not None and media[False].structures.device["grid"].host.masks is None
    assert np.all(masked <= plain)
    if tf_name == "spiky":
        assert masked.sum() < 0.9 * plain.sum()
    x = _points(cells)
    value, found = HostReconstruction(as_volume(cells))(x, as_method("nearest"))
    sigma = 7.0 * tf(value)[:, 3]
    m = _macrocell(grid, x)
    assert np.all(masked[m][found] >= sigma[found] * (1 - 1e-6))


def test05_tent_grids_carry_no_masks(llvm):
    """A tent field is continuous: inside a macrocell it takes every value of
    an interval, so bins cannot beat the range and are not built."""
    m = mi.load_dict({"type": "amr", "data": random_amr(1), "reconstruction": "tent"})
    assert m.structures.device["grid"].host.masks is None
    m = mi.load_dict({"type": "amr", "data": random_amr(1), "reconstruction": "nearest"})
    assert m.structures.device["grid"].host.masks is not None
