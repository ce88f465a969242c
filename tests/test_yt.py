"""yt grid hierarchies -> AMRCells (needs the optional yt extra)."""

import numpy as np
import pytest

import mi_amr
from mi_amr.structures.host_reconstruction import HostReconstruction

yt = pytest.importorskip("yt")


def _check_against_yt(ds, field, cells, n_points=1500):
    # no overlap (validated by AMRCells), full coverage of the domain
    finest = np.asarray(ds.domain_dimensions) * 2 ** ds.index.max_level
    lo, hi = cells.bounds
    assert lo.tolist() == [0, 0, 0] and hi.tolist() == finest.tolist()
    assert (cells.width ** 3).sum() == np.prod(finest)
    # the nearest reconstruction at cell centres equals yt's own value there
    # (every cell of small data, a random subset of large data: yt's point
    # look-up is slow)
    centres = cells.pos + 0.5 * cells.width[:, None]
    if len(centres) > n_points:
        centres = centres[np.random.default_rng(0).choice(len(centres), n_points, replace=False)]
    val, found = HostReconstruction(cells)(centres, "nearest")
    assert found.all()
    dle = ds.domain_left_edge.d
    dx = (ds.domain_right_edge.d - dle) / finest
    pts = ds.arr(dle + centres * dx, "code_length")
    ref = ds.find_field_values_at_points(field, pts)
    np.testing.assert_allclose(val, np.asarray(ref), rtol=1e-6)


def test01_fake_amr_ds():
    from yt.testing import fake_amr_ds
    ds = fake_amr_ds(fields=("Density",), units=("g/cm**3",))
    cells = mi_amr.from_yt(ds, ("stream", "Density"))
    # cells per level: each grid's uncovered cells, levels inverted
    expected = {}
    for g in ds.index.grids:
        L = ds.index.max_level - int(g.Level)
        expected[L] = expected.get(L, 0) + int(g.child_mask.sum())
    got = {int(L): int((cells.level == L).sum()) for L in cells.levels}
    assert got == {k: v for k, v in expected.items() if v}
    _check_against_yt(ds, ("stream", "Density"), cells)


def test02_hand_checkable_load_amr_grids(llvm):
    """Level 0: 8^3 cells on [0,1]^3; level 1: 8^3 cells on [0.25,0.75]^3."""
    x = np.arange(8)
    coarse = np.broadcast_to(x[:, None, None] + 10 * x[None, :, None] + 100 * x[None, None, :], (8, 8, 8)).astype(float)
    fine = 1000.0 + np.arange(512, dtype=float).reshape(8, 8, 8)
    grids = [dict(left_edge=[0.0] * 3, right_edge=[1.0] * 3, level=0, dimensions=[8, 8, 8], density=coarse),
             dict(left_edge=[0.25] * 3, right_edge=[0.75] * 3, level=1, dimensions=[8, 8, 8], density=fine)]
    ds = yt.load_amr_grids(grids, [8, 8, 8])
    cells = mi_amr.from_yt(ds, ("stream", "density"))
    assert int((cells.level == 1).sum()) == 512 - 64      # coarse cells outside the refined box
    assert int((cells.level == 0).sum()) == 512
    assert cells.bounds[1].tolist() == [16, 16, 16]
    # a coarse corner cell and a fine cell, by hand
    i = np.nonzero(np.all(cells.pos == [2, 0, 0], axis=1) & (cells.level == 1))[0][0]
    assert cells.value[i] == 1.0                            # coarse (1, 0, 0) -> 1 + 0 + 0
    j = np.nonzero(np.all(cells.pos == [4, 4, 5], axis=1))[0][0]
    assert cells.value[j] == 1000.0 + fine.shape[1] * fine.shape[2] * 0 + 1
    _check_against_yt(ds, ("stream", "density"), cells)
    tw = mi_amr.world_transform(ds)
    assert np.allclose(np.array(tw.matrix)[:3, 3], 0.0)


def test03_refine_by_other_than_two_is_refused():
    from yt.testing import fake_amr_ds
    ds = fake_amr_ds(fields=("Density",), units=("g/cm**3",))
    ds.refine_by = 4
    with pytest.raises(ValueError, match="refine_by = 4"):
        mi_amr.from_yt(ds, ("stream", "Density"))


def test04_convert_cli_reads_yt_datasets(tmp_path, monkeypatch):
    """`mi-amr convert FILE out.cells --field ...` goes through yt.load (here a
    stand-in returning yt's fake AMR dataset) and writes ExaBricks files."""
    from yt.testing import fake_amr_ds

    from mi_amr.tools.cli import main
    ds = fake_amr_ds(fields=("Density",), units=("g/cm**3",))
    monkeypatch.setattr(yt, "load", lambda path: ds)
    out = tmp_path / "sim.cells"
    assert main(["convert", str(tmp_path / "plt00100"), str(out), "--field", "stream,Density"]) == 0
    back = mi_amr.load_cells(out)
    ref = mi_amr.from_yt(ds, ("stream", "Density"))
    a, b = np.lexsort(back.pos.T), np.lexsort(ref.pos.T)       # the same cells, in block order
    np.testing.assert_array_equal(back.pos[a], ref.pos[b])
    np.testing.assert_array_equal(back.value[a], ref.value[b])
    assert back.meta == ref.meta


def test05_blocks_straight_from_yt_equal_the_cells():
    """`from_yt_blocks` streams yt's grids into the compact form: the same
    cells and values as `from_yt`, and the same metadata."""
    from yt.testing import fake_amr_ds
    from mi_amr.data.yt_import import from_yt_blocks
    ds = fake_amr_ds(fields=("Density",), units=("g/cm**3",))
    cells = mi_amr.from_yt(ds, ("stream", "Density"))
    vol = from_yt_blocks(ds, ("stream", "Density"))
    back = vol.to_cells()
    a, b = np.lexsort(np.c_[cells.pos, cells.level].T), np.lexsort(np.c_[back.pos, back.level].T)
    np.testing.assert_array_equal(cells.pos[a], back.pos[b])
    np.testing.assert_array_equal(cells.level[a], back.level[b])
    np.testing.assert_array_equal(cells.value[a], back.value[b])
    assert vol.meta == cells.meta and vol.meta["code"]


def test06_unsupported_yt_data_are_named():
    """2D grids, octree AMR (as RAMSES writes) and particle-only data give
    an error naming what is not supported."""
    from mi_amr.data.yt_import import from_yt_blocks
    flat = yt.load_uniform_grid({"density": np.ones((8, 8, 1))}, [8, 8, 1])
    flat.dimensionality = 2
    with pytest.raises(ValueError, match="2D data"):
        from_yt_blocks(flat, ("stream", "density"))
    octree = yt.load_octree(octree_mask=np.array([8, 0, 0, 0, 0, 0, 0, 0, 0], dtype=np.uint8),
                            data={("gas", "density"): np.ones(15)}, partial_coverage=0)
    with pytest.raises(ValueError, match="octree"):
        from_yt_blocks(octree, ("gas", "density"))
    particles = yt.load_particles({("io", "particle_position_x"): np.random.random(50),
                                   ("io", "particle_position_y"): np.random.random(50),
                                   ("io", "particle_position_z"): np.random.random(50),
                                   ("io", "particle_mass"): np.ones(50)})
    with pytest.raises(ValueError, match="particle-only"):
        from_yt_blocks(particles, ("io", "particle_mass"))
