"""Slices (mi_amr/slicing.py): the field on an axis-aligned plane through the
medium's own reconstruction, read from the cells the plane crosses: equal
to the ``amr`` medium's device sampler at the same points, to yt's slice of
a real AMReX output, with the AMR level of the cell under each pixel right
at level boundaries."""

import mitsuba as mi
import numpy as np
import pytest

from mi_amr import AMRCells
from mi_amr.data.blocks import BlockVolume
from mi_amr.slicing import IMAGE_AXES, Slicer, slice_volume
from mi_amr.transfer.function import TransferFunction

from conftest import random_amr


def unit_points(s, lo, hi, volume):
    """The unit-cube points of a slice's pixel centres (H*W, 3)."""
    h, w = s.values.shape
    u0, u1, v0, v1 = s.window
    a, (ha, va) = s.axis, IMAGE_AXES[s.axis]
    u = np.empty((h, w, 3))
    u[..., a] = s.position
    u[..., ha] = (u0 + (np.arange(w) + 0.5) / w * (u1 - u0))[None, :]
    u[..., va] = (v1 - (np.arange(h) + 0.5) / h * (v1 - v0))[:, None]
    return u.reshape(-1, 3)


@pytest.mark.parametrize("method", ["tent", "nearest"])
def test01_slice_is_the_medium_reconstruction(llvm, method):
    """Slices along x, y and z of 3-level data: every pixel's value is the
    ``amr`` medium's own (device) reconstruction at the pixel centre within
    float32 rounding (2e-6 relative to the value range), and found exactly
    where the medium finds a value."""
    cells = random_amr(5, n=16, levels=3)
    med = mi.load_dict({"type": "amr", "data": cells, "reconstruction": method})
    vol = med.volume
    span = float(np.ptp(cells.values))
    slicer = Slicer(vol)
    for axis, pos, res in ((0, 0.37, 24), (1, 0.5, 20), (2, 0.8125, (18, 13))):
        s = slicer.slice(axis, pos, res, method)
        if np.ndim(res) == 0:
            assert max(s.values.shape) == res
        u = unit_points(s, *vol.bounds, vol)
        value, _ = med.value_local(mi.Vector3f(u.T.astype(np.float32).copy()), True)
        device = np.asarray(value, np.float64)
        ours = s.values.ravel()
        assert np.all(np.isfinite(ours))                       # these data fill their bounds
        np.testing.assert_allclose(ours, device, atol=2e-6 * span)


def two_levels(n=16, fine=(6, 10)):
    """Level-1 cells over [0, n)^3 finest units except x in ``fine``, where
    level-0 cells are: value = the level."""
    pos, lev = [], []
    g = np.stack(np.meshgrid(*[np.arange(0, n, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    coarse = g[(g[:, 0] + 2 <= fine[0]) | (g[:, 0] >= fine[1])]
    f = np.stack(np.meshgrid(np.arange(*fine), np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 3)
    pos = np.concatenate([coarse, f])
    lev = np.concatenate([np.ones(len(coarse), int), np.zeros(len(f), int)])
    return AMRCells(pos, lev, lev.astype(np.float32) + 1.0)


def test02_level_per_pixel_at_the_boundaries():
    """Refined in the slab 6 <= x < 10 (of 16): with the nearest
    reconstruction a pixel shows level 0 exactly where its centre's x lies
    in the slab, level 1 elsewhere, values the cells' (level + 1); the
    boundary pixels are the columns on either side of x = 6 and x = 10."""
    vol = BlockVolume.from_cells(two_levels(), block=2)
    s = slice_volume(vol, "z", 0.5, (64, 8), method="nearest")
    xc = (np.arange(64) + 0.5) / 64 * 16
    expected = np.where((xc >= 6) & (xc < 10), 0, 1)
    assert np.array_equal(s.level, np.broadcast_to(expected, (8, 64)))
    assert np.array_equal(s.values, s.level + 1.0)
    cols = np.nonzero(s.boundaries()[0])[0]
    assert cols.tolist() == [23, 39]                          # x = 6 between columns 23 and 24, x = 10: 39 | 40
    img = s.image(TransferFunction.load("viridis", (0.5, 2.5)))
    assert img.shape == (8, 64, 3) and img.dtype == np.uint8
    # tent: continuous across the boundary, yet the level is the containing cell's
    t = slice_volume(vol, "z", 0.5, (64, 8), method="tent")
    assert np.array_equal(t.level, s.level)
    assert np.abs(np.diff(t.values[0])).max() < 0.5 and t.values.min() >= 1.0 and t.values.max() <= 2.0


def test03_bad_input_is_one_clear_error():
    vol = BlockVolume.from_cells(two_levels(), block=2)
    with pytest.raises(ValueError, match="slice axis"):
        slice_volume(vol, "w", 0.5)
    with pytest.raises(ValueError, match="slice position"):
        slice_volume(vol, 2, 1.5)
    with pytest.raises(ValueError, match="slice position"):
        slice_volume(vol, 2, float("nan"))
    with pytest.raises(ValueError, match="resolution"):
        slice_volume(vol, 2, 0.5, (0, 10))
    with pytest.raises(ValueError, match="no field"):
        slice_volume(vol, 2, 0.5, field="temperature")


def test04_slice_equals_yts_slice_of_an_amrex_output(tmp_path):
    """The ``collapse`` AMReX output of the gallery (3 levels): our nearest
    slice through z = 0.53 at 64^2 equals yt's fixed resolution buffer of
    ``ds.slice`` (its nearest-cell pixels) within float32 rounding (1e-6
    relative), and the level per pixel is yt's ``grid_level``."""
    yt = pytest.importorskip("yt")
    from gallery_outputs import collapse
    from mi_amr.data.opening import open_data
    path, field = collapse(tmp_path)
    ds = yt.load(str(path))
    vol, _, _ = open_data(ds, field)
    if not isinstance(vol, BlockVolume):
        vol = BlockVolume.from_cells(vol)
    z = 0.53
    s = slice_volume(vol, "z", z, 64, method="nearest")
    sl = ds.slice("z", z)
    frb = sl.to_frb(width=(1.0, "code_length"), resolution=64, center=[0.5, 0.5, z])
    key = [f for f in ds.field_list if f[1].lower() == "density"][0]
    ref = np.asarray(frb[key], np.float64)[::-1]              # yt's row 0 is the bottom
    np.testing.assert_allclose(s.values, ref, rtol=1e-6)
    level = np.asarray(frb[("index", "grid_level")], np.int64)[::-1]
    lmax = int(level.max())
    assert np.array_equal(s.level, lmax - level)              # ours count from the finest level (0)
