"""yt data sets (grids, octrees, one level) -> AMRCells, and one line for
what yt lacks (needs the optional yt extra)."""

import sys

import numpy as np
import pytest

import mi_amr
from mi_amr.structures.host_reconstruction import HostReconstruction
from mi_amr.data.volume import as_method, as_volume

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
    val, found = HostReconstruction(as_volume(cells))(centres, as_method("nearest"))
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
    """2D grids and particle-only data give an error naming what is not
    supported (octrees load: test07)."""
    from mi_amr.data.yt_import import from_yt_blocks
    flat = yt.load_uniform_grid({"density": np.ones((8, 8, 1))}, [8, 8, 1])
    flat.dimensionality = 2
    with pytest.raises(ValueError, match="a 2-D output"):
        from_yt_blocks(flat, ("stream", "density"))
    particles = yt.load_particles({("io", "particle_position_x"): np.random.random(50),
                                   ("io", "particle_position_y"): np.random.random(50),
                                   ("io", "particle_position_z"): np.random.random(50),
                                   ("io", "particle_mass"): np.ones(50)})
    with pytest.raises(ValueError, match="particle-only"):
        from_yt_blocks(particles, ("io", "particle_mass"))


# ---- Octrees (RAMSES, ART, yt.load_octree) ---------------------------------
def random_octree(seed=1, depth=4, bbox=((-1.0, 1.0), (0.0, 1.0), (0.0, 0.5))):
    """``(ds, pos, level, value)``: an octree refined at random to ``depth``
    (root always refined) over ``bbox`` (cells of aspect 4 : 2 : 1), loaded
    with yt's own loader, and its leaves as built (mi-amr units, yt's
    order), each with a distinct value."""
    from amr_formats import octree
    rng = np.random.default_rng(seed)
    mask, pos, level = octree(depth, lambda c, d: rng.random(len(c)) < (1.0 if d == 0 else 0.35))
    value = 1.0 + np.arange(len(pos), dtype=np.float64) / 7.0
    ds = yt.load_octree(octree_mask=mask, data={("gas", "density"): value[:, None]}, bbox=np.array(bbox),
                        num_zones=1, partial_coverage=0)
    return ds, pos, level, value


def test07_octree_leaves_exact():
    """Every leaf of an octree built with yt.load_octree: position (finest
    units from the domain's left edge), level (0 = finest) and value as
    built; the count; coverage (volumes add up to the domain's, no
    overlap); the blocks hold the same cells."""
    from mi_amr.data.yt_import import from_yt_blocks
    ds, pos, level, value = random_octree()
    assert sorted(set(level.tolist())) == [0, 1, 2, 3]          # four levels of leaves
    cells = mi_amr.from_yt(ds, ("gas", "density"))
    assert len(cells.value) == len(pos)
    built = {(*p, int(L)): np.float32(v) for p, L, v in zip(pos.tolist(), level, value)}
    got = {(*p, int(L)): v for p, L, v in zip(cells.pos.tolist(), cells.level, cells.value)}
    assert got == built
    finest = 2 ** 4                                          # leaves of depths 1..4
    assert cells.bounds[0].tolist() == [0, 0, 0] and cells.bounds[1].tolist() == [finest] * 3
    assert int((cells.width.astype(np.int64) ** 3).sum()) == finest ** 3
    assert cells.meta["domain_cells"] == [finest] * 3 and cells.meta["domain_right_edge"] == [1.0, 1.0, 0.5]
    vol = from_yt_blocks(ds, ("gas", "density"), fields=[("gas", "density")])
    back = vol.to_cells()
    assert vol.covers_bounds and vol.n_cells == len(pos)
    assert {(*p, int(L)): v for p, L, v in zip(back.pos.tolist(), back.level, back.value)} == built
    np.testing.assert_array_equal(vol.fields["density"], vol.values)     # a further field on the same cells


def test08_yt_fake_octree_two_zones_partial_coverage():
    """yt's test octree (two cells per oct side, partial refinement, as
    RAMSES octs): the leaves cover the domain once, in four levels."""
    from yt.testing import fake_octree_ds
    ds = fake_octree_ds(prng=np.random.RandomState(7))
    cells = mi_amr.from_yt(ds, ("gas", "density"))
    finest = np.asarray(ds.domain_dimensions) * 2 ** int(ds.max_level)
    assert cells.bounds[1].tolist() == finest.tolist()
    assert int((cells.width.astype(np.int64) ** 3).sum()) == int(np.prod(finest))
    assert len(cells.value) == ds.all_data()["index", "ones"].size
    assert len(cells.levels) > 1


def test09_octree_cells_refuse_what_is_not_aligned():
    """Centres and widths that are not aligned cells of a power-of-two
    width name the cell."""
    from mi_amr.data.yt_import import octree_cells
    finest, left = np.array([0.25, 0.25, 0.25]), np.zeros(3)
    pos, level = octree_cells([[0.125, 0.125, 0.375], [0.75, 0.75, 0.25]], [[0.25] * 3, [0.5] * 3], left, finest, 2)
    assert pos.tolist() == [[0, 0, 1], [2, 2, 0]] and level.tolist() == [0, 1]
    for centre, width in (([0.5, 0.5, 0.5], [0.5] * 3),             # corner (1, 1, 1): not a multiple of 2
                          ([0.375, 0.375, 0.375], [0.75] * 3),      # 3 finest cells wide
                          ([0.125, 0.125, 0.125], [0.25, 0.25, 0.5]),   # not cubic in finest units
                          ([0.13, 0.125, 0.125], [0.25] * 3),       # off the grid
                          ([1.0, 1.0, 1.0], [2.0] * 3)):            # level 3 > 2
        with pytest.raises(ValueError, match=r"test octree: the cell with centre \[.*not an aligned cell"):
            octree_cells([[0.125, 0.125, 0.125], centre], [[0.25] * 3, width], left, finest, 2, "test octree")


def test10_octree_renders_from_a_plan(llvm):
    """An ``amr`` medium planned from octree data (open_data/plan_scene)
    renders: a tiny image, finite and not flat."""
    import mitsuba as mi
    from mi_amr.autoscene import plan_scene
    from mi_amr.scene_writer import scene_for
    ds, _, _, _ = random_octree(seed=3)
    plan = plan_scene(ds, "gas,density")
    np.testing.assert_allclose(plan.extent, [1.0, 0.5, 0.25])
    img = np.array(mi.render(mi.load_dict(scene_for(plan, res=16, spp=4))))
    assert np.isfinite(img).all() and img.std() > 0


# ---- One level ---------------------------------------------------------------
def test11_uniform_grid_is_one_level_of_amr():
    """yt.load_uniform_grid and a one-level yt.load_amr_grids with
    refine_by 1: every cell, its position and value exact."""
    rng = np.random.default_rng(0)
    d = rng.random((8, 6, 4))
    ds = yt.load_uniform_grid({"density": d}, [8, 6, 4], bbox=np.array([[0, 2.0], [0, 1.5], [0, 1.0]]))
    cells = mi_amr.from_yt(ds, ("stream", "density"))
    ijk = np.argwhere(np.ones(d.shape, bool))
    order = np.lexsort(cells.pos.T[::-1])
    np.testing.assert_array_equal(cells.pos[order], ijk[np.lexsort(ijk.T[::-1])])
    assert cells.levels.tolist() == [0]
    np.testing.assert_array_equal(cells.value, d[tuple(cells.pos.T)].astype(np.float32))
    grids = [dict(left_edge=[0.0] * 3, right_edge=[1.0] * 3, level=0, dimensions=[4, 4, 4],
                  density=np.arange(64.0).reshape(4, 4, 4))]
    ds = yt.load_amr_grids(grids, [4, 4, 4], refine_by=1)
    assert ds.refine_by == 1
    cells = mi_amr.from_yt(ds, ("stream", "density"))
    np.testing.assert_array_equal(cells.value, np.arange(64.0).reshape(4, 4, 4)[tuple(cells.pos.T)])


def test12_two_levels_refining_by_four_are_refused_in_one_line():
    grids = [dict(left_edge=[lo] * 3, right_edge=[hi] * 3, level=L, dimensions=[4, 4, 4], density=np.ones((4, 4, 4)))
             for L, lo, hi in ((0, 0.0, 1.0), (1, 0.25, 0.5))]
    ds = yt.load_amr_grids(grids, [4, 4, 4], refine_by=4)
    with pytest.raises(ValueError, match="refine_by = 4 with 2 levels") as e:
        mi_amr.from_yt(ds, ("stream", "density"))
    assert "\n" not in str(e.value)


# ---- Missing packages: one line, not yt's traceback -----------------------------
def _pretend_missing(monkeypatch, on_demand, attribute, package):
    """Make yt's on-demand import ``on_demand.attribute`` behave as it does
    when ``package`` is not installed: yt hands out a ``NotAModule`` that
    raises the original ModuleNotFoundError when used; the readers that
    ask for it first (``_load_requirements``) pass the data by."""
    import yt.data_objects.static_output as static_output
    from yt.utilities.on_demand_imports import NotAModule
    monkeypatch.setattr(type(on_demand), attribute, property(lambda self: NotAModule(
        package, ModuleNotFoundError(f"No module named '{package}'", name=package))))
    find_spec = static_output.find_spec
    monkeypatch.setattr(static_output, "find_spec", lambda name: None if name == package else find_spec(name))


@pytest.fixture
def enzo_output(tmp_path):
    from amr_formats import write_enzo
    root = np.random.default_rng(0).random((8, 8, 8))
    return write_enzo(tmp_path / "DD0001", "DD0001", root, [((4, 4, 4), np.ones((4, 4, 4)))])


def _one_line_error(capsys, argv):
    """``mi-amr ARGV`` in this process: its exit code and the error it
    printed on stderr (asserted to be one line, with no traceback; yt's
    progress bars may come before it)."""
    from mi_amr.tools.cli import main
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:                 # what Python prints for a SystemExit with a message
        code = 1
        print(e.code, file=sys.stderr)
    err = capsys.readouterr().err
    ours = [line for line in err.splitlines() if line.startswith("mi-amr")]
    assert len(ours) == 1 and "Traceback" not in err, err
    return code, ours[0]


def test13_missing_package_while_reading_fields_is_one_line(monkeypatch, enzo_output, tmp_path, capsys):
    """h5py missing when yt reads an Enzo output's grids: the error names
    the package, the code and the extra, in one line (open_data, the CLI)."""
    from yt.utilities.on_demand_imports import _h5py

    from mi_amr.autoscene import open_data
    from mi_amr.data.yt_import import MissingDependency
    _pretend_missing(monkeypatch, _h5py, "File", "h5py")
    with pytest.raises(MissingDependency) as e:
        open_data(enzo_output, "density")          # yt.load reads text; the grids' fields need h5py
    msg = str(e.value)
    assert "reading this Enzo output needs the Python package 'h5py': pip install 'mi-amr[yt]'" in msg
    assert "\n" not in msg and isinstance(e.value, ValueError) and e.value.name == "h5py"
    import warnings

    import yt
    with warnings.catch_warnings():                              # yt's own warning of what it lacks
        warnings.simplefilter("ignore")
        ds = yt.load(enzo_output)                                # a data set loaded by the user's own yt.load
    with pytest.raises(MissingDependency, match="'h5py'"):
        open_data(ds, "density")
    code, err = _one_line_error(capsys, ["render", enzo_output, "--field", "density", "-o", tmp_path / "a.exr"])
    assert code == 2 and err.startswith("mi-amr render: error: ") and "'h5py'" in err and "mi-amr[yt]" in err


def test14_missing_package_while_loading_is_one_line(monkeypatch, enzo_output, tmp_path, capsys):
    """libconf missing when yt parses an Enzo 3 (libconfig) parameter file:
    one line naming it, from yt.load on (the CLI's render and convert)."""
    from yt.utilities.on_demand_imports import _libconf

    from mi_amr.data.yt_import import MissingDependency, load_dataset
    enzo_output.write_text("Internal:\n{\n};\n")        # what makes yt read the file with libconf
    _pretend_missing(monkeypatch, _libconf, "load", "libconf")
    with pytest.raises(MissingDependency, match=r"DD0001: reading this Enzo output needs the Python package "
                                                r"'libconf': pip install 'mi-amr\[yt\]'$"):
        load_dataset(enzo_output)
    for command in (["render", enzo_output, "--field", "density", "-o", tmp_path / "a.exr"],
                    ["convert", enzo_output, tmp_path / "a.cells", "--field", "density"]):
        code, err = _one_line_error(capsys, command)
        assert code != 0 and "'libconf'" in err and "mi-amr[yt]" in err


def test15_other_import_errors_and_unknown_formats(tmp_path):
    """A package outside mi-amr's extra is named with its own pip line; a
    file yt does not recognise is one line too."""
    from mi_amr.data.yt_import import MissingDependency, _reading, load_dataset
    with pytest.raises(MissingDependency, match=r"x: reading this data needs the Python package 'pyart': "
                                                r"pip install pyart$"):
        with _reading(None, "x"):
            raise ModuleNotFoundError("No module named 'pyart.io'", name="pyart.io")
    with pytest.raises(MissingDependency, match="'netCDF4'"):       # yt's own wording, without a name
        with _reading(None, "x"):
            raise ImportError("Something went wrong while trying to lazy-import netCDF4. Please make sure ...")
    junk = tmp_path / "notes.txt"
    junk.write_text("not simulation data\n")
    with pytest.raises(ValueError, match="notes.txt: yt does not recognise this") as e:
        load_dataset(junk)
    assert "\n" not in str(e.value)


def test16_the_yt_extra_brings_what_the_readers_import():
    """Every package the error messages send to ``mi-amr[yt]`` is in that
    extra, and in ``dev`` (tests, tools/setup.sh)."""
    import re
    import tomllib
    from pathlib import Path

    from mi_amr.data.yt_import import EXTRA_PACKAGES
    extras = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]

    def names(extra):
        return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower() for r in extras[extra]}
    for extra in ("yt", "dev"):
        assert {"yt", *(p.lower() for p in EXTRA_PACKAGES.values())} <= names(extra), extra
