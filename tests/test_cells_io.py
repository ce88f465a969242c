"""AMRCells validation and the .cells/.scalars and .npz readers/writers."""

import numpy as np
import pytest

import mi_amr
from mi_amr.data.io import read_exabricks, read_npz, write_exabricks, write_npz

from conftest import random_amr


def test01_validation_rejects_bad_cells():
    pos = np.array([[0, 0, 0], [2, 0, 0]])
    with pytest.raises(ValueError, match="negative level"):
        mi_amr.AMRCells(pos, [0, -1], [1, 2])
    with pytest.raises(ValueError, match="not aligned"):
        mi_amr.AMRCells([[0, 0, 0], [1, 0, 0]], [0, 1], [1, 2])
    with pytest.raises(ValueError, match="non-finite"):
        mi_amr.AMRCells(pos, [0, 0], [1, np.nan])
    with pytest.raises(ValueError, match="inconsistent sizes"):
        mi_amr.AMRCells(pos, [0], [1, 2])
    with pytest.raises(ValueError, match="no cells"):
        mi_amr.AMRCells(np.zeros((0, 3)), [], [])


def test02_overlap_error_or_finest_wins():
    # a level-1 cell at the origin covering the level-0 cell at (1, 1, 1), and a duplicate
    pos = [[0, 0, 0], [1, 1, 1], [4, 0, 0], [4, 0, 0]]
    level = [1, 0, 0, 0]
    value = [1.0, 2.0, 3.0, 4.0]
    with pytest.raises(ValueError, match="overlap"):
        mi_amr.AMRCells(pos, level, value)
    c = mi_amr.AMRCells(pos, level, value, overlap="finest")
    assert len(c) == 2
    assert sorted(c.value.tolist()) == [2.0, 3.0]


def test03_exabricks_round_trip(tmp_path):
    c = random_amr(1)
    p, s = write_exabricks(c, tmp_path / "a.cells")
    assert p.stat().st_size == 16 * len(c) and s.stat().st_size == 4 * len(c)
    d = read_exabricks(p)
    np.testing.assert_array_equal(d.pos, c.pos)
    np.testing.assert_array_equal(d.level, c.level)
    np.testing.assert_array_equal(d.value, c.value)
    # explicit scalars file with another name
    (tmp_path / "a-density.scalars").write_bytes(s.read_bytes())
    d2 = mi_amr.load_cells(p, tmp_path / "a-density.scalars")
    np.testing.assert_array_equal(d2.value, c.value)


def test04_npz_round_trip(tmp_path):
    c = random_amr(2)
    d = read_npz(write_npz(c, tmp_path / "a.npz"))
    np.testing.assert_array_equal(d.pos, c.pos)
    np.testing.assert_array_equal(d.level, c.level)
    np.testing.assert_array_equal(d.value, c.value)


def test05_bad_files_name_file_and_problem(tmp_path):
    c = random_amr(3)
    p, s = write_exabricks(c, tmp_path / "a.cells")
    data = p.read_bytes()
    p.write_bytes(data[:-5])                       # truncated record
    with pytest.raises(ValueError, match=r"a\.cells.*multiple of 16"):
        read_exabricks(p)
    p.write_bytes(data[:-16])                      # one record short
    with pytest.raises(ValueError, match=r"a\.cells.*do not belong together"):
        read_exabricks(p)
    p.write_bytes(data)
    s.write_bytes(s.read_bytes()[:-2])
    with pytest.raises(ValueError, match=r"a\.scalars.*multiple of 4"):
        read_exabricks(p)
    vals = c.value.copy()
    vals[3] = np.nan
    vals.astype("<f4").tofile(s)
    with pytest.raises(ValueError, match=r"a\.cells.*non-finite"):
        read_exabricks(p)
    c.value.astype("<f4").tofile(s)
    rec = np.fromfile(p, dtype="<i4").reshape(-1, 4)
    rec[0, 3] = -2
    rec.tofile(p)
    with pytest.raises(ValueError, match=r"a\.cells.*negative level"):
        read_exabricks(p)
    rec[0, 3] = 1
    rec[0, 0] = 1
    rec.tofile(p)
    with pytest.raises(ValueError, match=r"a\.cells.*not aligned"):
        read_exabricks(p)
    with pytest.raises(FileNotFoundError):
        read_exabricks(tmp_path / "missing.cells")


def test06_npz_refuses_pickles_and_missing_arrays(tmp_path):
    np.savez(tmp_path / "obj.npz", pos=np.array([object()]), level=np.zeros(1), value=np.zeros(1))
    with pytest.raises(ValueError, match="obj.npz"):
        read_npz(tmp_path / "obj.npz")
    np.savez(tmp_path / "miss.npz", pos=np.zeros((1, 3), int))
    with pytest.raises(ValueError, match="missing arrays"):
        read_npz(tmp_path / "miss.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz"):
        read_npz(tmp_path / "junk.npz")


def test07_summary_counts_levels():
    c = random_amr(4)
    s = c.summary()
    for L in c.levels:
        assert f"level {int(L):2d}" in s
    assert str(len(c)) in s
