"""The analytic radial field on AMR levels (mi_amr.data.radial_example): its
leaf cells, yt's reading of its Enzo output, and the exact ray-sphere hit."""

import numpy as np
import pytest

from mi_amr.data.enzo_example import EnzoGrid, write_enzo_grids
from mi_amr.data.radial_example import (boundary_distance, radial_cells, ray_sphere, write_enzo_radial)


def _sorted(cells):
    order = np.lexsort((cells.pos[:, 2], cells.pos[:, 1], cells.pos[:, 0], cells.level))
    return cells.pos[order], cells.level[order], cells.values[order]


@pytest.mark.parametrize("levels", [2, 3])
def test01_leaves_tile_the_cube_with_the_field_at_their_centres(levels):
    cells = radial_cells(levels, root=16)
    n = 16 << (levels - 1)
    assert (8.0 ** cells.level).sum() == n ** 3                     # non-overlapping (validated) and complete
    centres = (cells.pos + 0.5 * cells.width[:, None]) / n
    np.testing.assert_allclose(cells.values, np.linalg.norm(centres - 0.5, axis=1), rtol=1e-6)
    assert sorted(np.unique(cells.level)) == list(range(levels))
    # the level boundaries cut every sphere R in [0.2, 0.35]: cells of every level touch it
    for radius in (0.2, 0.27, 0.35):
        half_diagonal = np.sqrt(3) / 2 * cells.width / n
        touching = np.abs(np.linalg.norm(centres - 0.5, axis=1) - radius) < half_diagonal
        assert set(np.unique(cells.level[touching])) == set(range(levels)), radius


def test02_yt_reads_the_same_leaf_cells_from_the_enzo_output(tmp_path):
    yt = pytest.importorskip("yt")
    from mi_amr.data.yt_import import from_yt
    for levels in (2, 3):
        ds = yt.load(str(write_enzo_radial(tmp_path / f"radial{levels}", levels)))
        assert ds.index.max_level == levels - 1
        ours, theirs = _sorted(radial_cells(levels)), _sorted(from_yt(ds, "density"))
        np.testing.assert_array_equal(ours[0], theirs[0])
        np.testing.assert_array_equal(ours[1], theirs[1])
        np.testing.assert_allclose(ours[2], theirs[2], rtol=1e-7)


def test03_a_tree_with_siblings_and_a_grandchild_is_numbered_as_yt_reads_it(tmp_path):
    """Grid ids follow yt's pointer discovery (sibling before child): two
    level-1 grids, the second with a level-2 grid; yt's leaves tile the cube."""
    yt = pytest.importorskip("yt")
    grids = [EnzoGrid(0, (0, 0, 0), np.zeros((8, 8, 8)), None),
             EnzoGrid(1, (0, 0, 0), np.ones((4, 4, 4)), 0),
             EnzoGrid(1, (8, 8, 8), np.full((6, 6, 6), 2.0), 0),
             EnzoGrid(2, (18, 18, 18), np.full((4, 4, 4), 3.0), 2)]
    ds = yt.load(str(write_enzo_grids(tmp_path / "tree", "tree", grids)))
    levels = sorted((int(g.Level), tuple(g.ActiveDimensions)) for g in ds.index.grids)
    assert levels == [(0, (8, 8, 8)), (1, (4, 4, 4)), (1, (6, 6, 6)), (2, (4, 4, 4))]
    ad = ds.all_data()
    volume = np.asarray(ad["index", "cell_volume"].d).sum()
    assert volume == pytest.approx(1.0, rel=1e-12)
    values, counts = np.unique(np.asarray(ad["gas", "density"].d), return_counts=True)
    np.testing.assert_array_equal(values, [0.0, 1.0, 2.0, 3.0])
    # leaves: 512 - 8 - 27 root cells, 64 + 216 - 8 level-1, 64 level-2
    np.testing.assert_array_equal(counts, [477, 64, 208, 64])


def test04_ray_sphere_is_the_first_crossing():
    rng = np.random.default_rng(4)
    centre, radius = np.array([0.5, 0.5, 0.5]), 0.3
    o = rng.uniform(-1.0, 2.0, (1000, 3))
    d = rng.normal(size=(1000, 3)) * rng.uniform(0.1, 3.0, (1000, 1))      # not unit
    t = ray_sphere(o, d, centre, radius)
    hit = np.isfinite(t)
    assert 0 < hit.sum() < len(t)
    x = o[hit] + t[hit, None] * d[hit]
    np.testing.assert_allclose(np.linalg.norm(x - centre, axis=1), radius, rtol=1e-9)
    # no earlier crossing: the segment before the hit stays on the side of its origin
    inside = np.linalg.norm(o - centre, axis=1) < radius
    for f in (0.25, 0.5, 0.99):
        y = o[hit] + f * t[hit, None] * d[hit]
        assert np.all((np.linalg.norm(y - centre, axis=1) < radius) == inside[hit])
    # the misses: the line's closest point to the centre is outside, or the sphere is behind
    miss = ~hit & ~inside
    s = np.sum((centre - o[miss]) * d[miss], axis=1) / np.sum(d[miss] ** 2, axis=1)
    closest = o[miss] + np.maximum(s, 0.0)[:, None] * d[miss]
    assert np.all(np.linalg.norm(closest - centre, axis=1) > radius)


def test05_boundary_distance_and_bad_input():
    # level 1's face x = 0.375 (y, z inside its rectangle) and the domain's face x = 1 (not a boundary)
    assert boundary_distance(np.array([0.4, 0.7, 0.1]), 2) == pytest.approx(0.025)
    assert boundary_distance(np.array([0.99, 0.99, 0.5]), 2) == pytest.approx(0.615)
    with pytest.raises(ValueError, match="cell corners"):
        radial_cells(2, refine_box=[((0.3, 0.0, 0.0), (1.0, 1.0, 1.0))])
    with pytest.raises(ValueError, match="inside level 1"):
        radial_cells(3, refine_box=[((0.5, 0.5, 0.5), (1.0, 1.0, 1.0)), ((0.25, 0.5, 0.5), (0.75, 1.0, 1.0))])
    with pytest.raises(ValueError, match="field"):
        radial_cells(2, field="density")
