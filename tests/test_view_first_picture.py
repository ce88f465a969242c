"""What a planned scene and the viewer read of the values, stored in an
``.amrb`` file when it is written (`mi_amr.autoscene.file_stats`,
docs/performance/view.md "The first picture"): read back, it equals what the
values give when computed, so the plan, the first picture's TF and scale and
the editor's histogram are those of a file without it; older files (none
stored) still load and plan the same, by computing."""

import struct

import numpy as np
import pytest

from mi_amr.autoscene import DEFAULT_TF, _mean_alpha, _value_scale, file_stats, plan_scene
from mi_amr.data.statistics import (fine_histogram, stored_fine_histogram, stored_stats, value_stats,
                                    weighted_percentiles)
from mi_amr.data.amrb import PREAMBLE, read_amrb, read_header, write_amrb
from mi_amr.data.blocks import BlockVolume
from mi_amr.data.datasets import make_dataset
from mi_amr.data.transform import apply_value_transform
from mi_amr.native_file import save_native
from mi_amr.structures.cost_model import CANDIDATES, GridPlan, _pool, _uniform_cost, auto_grid, file_grids
from mi_amr.structures.macrocell_grid import MacrocellGrid
from mi_amr.transfer.function import TransferFunction, range_majorants_host
from mi_amr.view.scene import load_scene

PLAN_FIELDS = ("transform", "tf", "tf_range", "density_scale", "optical_depth", "peak_depth", "notes")


def positive_volume():
    """Octree-like cells, every value above 0, spanning decades: the plan
    chooses log10, the viewer stores log10 values."""
    v = BlockVolume.from_cells(make_dataset("cosmo", cells=3000, seed=3))
    assert v.value_range[0] > 0
    return v


def zero_volume():
    """The cloud: much of the volume is 0, so linear values."""
    return BlockVolume.from_cells(make_dataset("cloud", cells=3000, seed=1))


def old_file(volume, path, version=2):
    """``volume`` written as mi-amr wrote it before the statistics: its
    grids, no ``stats``, the preamble's version ``version``."""
    write_amrb(volume, path, grids=file_grids(volume))
    with open(path, "r+b") as f:
        magic, _, n, crc = PREAMBLE.unpack(f.read(PREAMBLE.size))
        f.seek(0)
        f.write(PREAMBLE.pack(magic, version, n, crc))
    return path


@pytest.fixture(params=["positive", "zeros"])
def files(request, tmp_path):
    volume = positive_volume() if request.param == "positive" else zero_volume()
    return volume, save_native(volume, tmp_path / "new.amrb"), old_file(volume, tmp_path / "old.amrb")


def test01_stored_statistics_equal_the_computed_ones(llvm, files):
    """Read back, the statistics are what the values give: `value_stats`,
    the percentiles under log10 and linear, the default TF's mean opacity
    over the planned range, the editor's fine histograms."""
    volume, new, old = files
    stored, plain = read_amrb(new), read_amrb(old)
    assert stored_stats(stored) is not None and plain.stored_stats == {} and stored_stats(plain) is None
    assert read_header(new)["stats"] is not None and read_header(old)["stats"] is None
    assert value_stats(stored) == value_stats(plain) == value_stats(volume)
    for log in (False, True):
        qs = [1.0, 50.0, 99.9]
        if log and not value_stats(volume).has_positive:
            continue
        assert weighted_percentiles(stored, qs, log=log) == weighted_percentiles(plain, qs, log=log)
    log, value_range, _, _ = _value_scale(plain, None, None, None)
    assert stored.stored_stats["mean_alpha"][0]["value"] == _mean_alpha(plain, DEFAULT_TF, value_range, log)
    assert _mean_alpha(stored, DEFAULT_TF, value_range, log) == _mean_alpha(plain, DEFAULT_TF, value_range, log)
    # another TF or range is computed, not taken from the file
    other = (value_range[0], value_range[1] * 0.5 + value_range[0] * 0.5)
    assert _mean_alpha(stored, "dust", other, log) == _mean_alpha(plain, "dust", other, log)
    # the editor's histogram of the medium's values, linear and (where the viewer stores them so) log10
    edges, cdf = stored_fine_histogram(stored, stored)
    e2, c2 = fine_histogram(plain)
    np.testing.assert_array_equal(edges, e2)
    np.testing.assert_array_equal(cdf, c2)
    if "view_log10" in stored.stored_stats:
        logged, _ = apply_value_transform(stored, "log10")
        edges, cdf = stored_fine_histogram(stored, logged)
        e2, c2 = fine_histogram(apply_value_transform(plain, "log10")[0])
        np.testing.assert_array_equal(edges, e2)
        np.testing.assert_array_equal(cdf, c2)


def test02_the_plan_from_a_file_is_the_plan_from_its_values(llvm, files):
    """`plan_scene` of the new file, of an old one (computed) and of the
    volume in memory agree in every number and note but the data's name."""
    volume, new, old = files
    a, b, c = plan_scene(read_amrb(new)), plan_scene(read_amrb(old)), plan_scene(volume)
    for name in PLAN_FIELDS:
        if name == "notes":
            assert a.notes[1:] == b.notes[1:] == c.notes[1:]
        else:
            assert getattr(a, name) == getattr(b, name) == getattr(c, name), name
    np.testing.assert_array_equal(a.origin, b.origin)


def test03_changed_values_are_planned_from_the_values(llvm, files):
    """Statistics that no longer describe the values (another count or
    range, another version of `file_stats`) are not used."""
    _, new, _ = files
    v = read_amrb(new)
    assert stored_stats(v) is not None and stored_stats(v, field="temperature") is None
    v.stored_stats = dict(v.stored_stats, version=-1)
    assert stored_stats(v) is None
    v = read_amrb(new)
    v.stored_stats = dict(v.stored_stats, value_range=[0.0, 1.0])
    assert stored_stats(v) is None
    assert stored_fine_histogram(v, v) is None


def test04_the_viewer_starts_the_same_from_old_and_new_files(llvm, files, tmp_path):
    """`load_scene` (what `mi-amr view` loads) of both files: the same
    camera, TF, density scale, log choice and editor histogram; a new file
    written of statistics computed by hand reads back the same."""
    volume, new, old = files
    a = load_scene(str(new), None, 32, lambda desc: None)
    b = load_scene(str(old), None, 32, lambda desc: None)
    assert a.initial_spec == b.initial_spec and a.initial_camera == b.initial_camera
    assert a.stored_log == b.stored_log
    assert a.shares(a.initial_spec) == b.shares(b.initial_spec)
    assert a.outside(a.initial_spec) == b.outside(b.initial_spec)
    assert a.histogram.cdf is not None
    again = write_amrb(volume, tmp_path / "again.amrb", grids=file_grids(volume), stats=file_stats(volume))
    st, st2 = read_amrb(again).stored_stats, read_amrb(new).stored_stats
    assert st.keys() == st2.keys()
    for k in st:
        if isinstance(st[k], np.ndarray):
            np.testing.assert_array_equal(st[k], st2[k])
        else:
            assert st[k] == st2[k], k



def test05_grid_plan_pools_each_candidate_from_the_next_finer(llvm):
    """`auto_grid` pools each candidate from the next finer one: for min,
    max and or over padded blocks that is pooling from the finest at once,
    array for array, so the plan and its costs are as before."""
    rng = np.random.default_rng(0)
    a = rng.random((13, 7, 29))
    m = rng.integers(0, 1 << 62, size=a.shape, dtype=np.uint64)
    for f, g in ((2, 2), (2, 4), (4, 2), (2, 8)):
        for arr, op, fill in ((a, np.minimum, np.inf), (a, np.maximum, -np.inf), (m, np.bitwise_or, np.uint64(0))):
            np.testing.assert_array_equal(_pool(_pool(arr, f, op, fill), g, op, fill), _pool(arr, f * g, op, fill))
    cells = zero_volume()
    tf = TransferFunction.load("spiky", cells.value_range)
    plan, costs = auto_grid(cells, tf, 50.0)
    lo, hi = cells.bounds
    finest = max(c for c in CANDIDATES if c <= max(int((hi - lo).max()), min(CANDIDATES)))
    g = MacrocellGrid(cells, finest)
    shape = tuple(g.res[::-1])
    for c in [c for c in CANDIDATES if c <= finest]:
        f = finest // c
        pmin, pmax = _pool(g.vmin.reshape(shape), f, np.minimum, np.inf), _pool(g.vmax.reshape(shape), f, np.maximum,
                                                                             -np.inf)
        mu = range_majorants_host(tf, pmin.ravel(), pmax.ravel(), 50.0).astype(np.float64).reshape(pmin.shape)
        assert costs[GridPlan(c)] == _uniform_cost(mu, c)
