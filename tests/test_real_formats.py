"""Simulation outputs in their codes' own formats (AMReX plotfile, Enzo
packed HDF5, Athena++ athdf, RAMSES Fortran records), written by the tests
(tests/amr_formats.py) and read through yt as a user's data would be:
coverage, every leaf value against what was written, shape, a render
against the gridvolume reference, and the one-command render; one-level
outputs of each grid code, and RAMSES's octree."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.autoscene import plan_scene
from mi_amr.scene_writer import scene_for
from mi_amr.testing import block_z_scores, render_passes
from mi_amr.reference import reference_medium

from amr_formats import write_amrex_plotfile, write_athena_pp, write_enzo
from conftest import render_cli

yt = pytest.importorskip("yt")


#: Per format: the field name in yt, the domain's right edge and the root cells.
FORMATS = {"amrex": (("boxlib", "density"), [1.0, 0.62, 1.0], [16, 16, 8]),
           "enzo": (("enzo", "Density"), [1.0, 1.0, 1.0], [16, 16, 16]),
           "athena_pp": (("athena_pp", "rho"), [2.0, 1.0, 1.0], [16, 16, 16])}


#: The renders of the AMReX and Athena++ outputs run with marker ``slow``
#: (the default suite renders the Enzo output; every format is read and
#: checked cell by cell in test01).
SLOW_CASES = {f"{test}[{fmt}]" for fmt in ("amrex", "athena_pp")
              for test in ("test02_render_matches_the_gridvolume_reference",
                           "test03_render_an_output_in_one_command")}


@pytest.fixture(scope="module", params=sorted(FORMATS))
def written(request, tmp_path_factory):
    """``(path, levels, format)``: an output written in a code's own format.
    AMReX: a plotfile of 16 x 16 x 8 root cells over 1 x 0.62 x 1 (cells of
    aspect 1 : 0.62 : 2) in two root boxes and one refined box of 8^3 fine
    cells. Enzo: a 16^3 root grid over the unit cube and two level-1 grids.
    Athena++: 8^3 mesh blocks over 2 x 1 x 1 (cells of aspect 2 : 1 : 1),
    one root block refined into eight (only leaves are written).
    ``levels``: per level, the ``(first cell index, values [i, j, k])`` boxes."""
    rng = np.random.default_rng(0)
    root = tmp_path_factory.mktemp(request.param)
    if request.param == "amrex":
        x, y, z = np.meshgrid(np.arange(8), np.arange(16), np.arange(8), indexing="ij")
        blob = np.exp(-((x - 6) ** 2 + (y - 8) ** 2 + (z - 4) ** 2) / 20.0)
        coarse = [((0, 0, 0), 1.0 + 4.0 * blob + 0.1 * rng.random(blob.shape)),
                  ((8, 0, 0), 1.0 + 4.0 * blob[::-1] + 0.1 * rng.random(blob.shape))]
        fine = [((12, 12, 4), 3.0 + 2.0 * rng.random((8, 8, 8)))]
        levels = [coarse, fine]
        return write_amrex_plotfile(root / "plt00010", levels, [0.0, 0.0, 0.0], FORMATS["amrex"][1]), \
            levels, "amrex"
    if request.param == "athena_pp":
        coarse = [((i, j, k), 1.0 + rng.random((8, 8, 8))) for i in (0, 8) for j in (0, 8) for k in (0, 8)
                  if (i, j, k) != (8, 8, 0)]
        fine = [((16 + i, 16 + j, k), 3.0 + rng.random((8, 8, 8))) for i in (0, 8) for j in (0, 8) for k in (0, 8)]
        levels = [coarse, fine]
        return write_athena_pp(root / "blast.out1.00010.athdf", levels, [16, 16, 16], (2.0, 1.0, 1.0)), \
            levels, "athena_pp"
    x, y, z = np.meshgrid(*[np.arange(16)] * 3, indexing="ij")
    top = 1.0 + 4.0 * np.exp(-((x - 9) ** 2 + (y - 7) ** 2 + (z - 8) ** 2) / 30.0) + 0.1 * rng.random((16, 16, 16))
    children = [((8, 8, 8), 3.0 + 2.0 * rng.random((8, 8, 8))), ((16, 8, 8), 2.0 + rng.random((8, 6, 4)))]
    path = write_enzo(root / "DD0003", "DD0003", top, children)
    return path, [[((0, 0, 0), top)], children], "enzo"


@pytest.fixture(scope="module")
def plotfile(written):
    return written[0]


def expected_leaf_cells(levels):
    """{(x, y, z, level): value} of the written boxes in finest units
    (level 1: root cells, minus those a fine box covers)."""
    out = {}
    for amr_level, boxes in ((1, levels[0]), (0, levels[1])):
        for lo, data in boxes:
            for ijk in np.ndindex(*data.shape):
                p = (np.asarray(lo) + ijk) << amr_level
                out[(*p.tolist(), amr_level)] = np.float32(data[ijk])
    for flo, fdata in levels[1]:
        fhi = np.asarray(flo) + fdata.shape
        for key in [k for k in out if k[3] == 1]:
            if np.all(np.asarray(key[:3]) >= flo) and np.all(np.asarray(key[:3]) < fhi):
                del out[key]
    return out


def test01_cells_cover_the_domain_with_the_written_values(llvm, written):
    plotfile, levels, fmt = written
    field, right, root_cells = FORMATS[fmt]
    from mi_amr.data.yt_import import from_yt_blocks
    ds = yt.load(str(plotfile))
    assert type(ds).__name__.endswith("Dataset") and ds.index.max_level == 1
    vol = from_yt_blocks(ds, field)
    cells = vol.to_cells()
    finest = np.asarray(ds.domain_dimensions) * 2
    lo, hi = cells.bounds
    assert lo.tolist() == [0, 0, 0] and hi.tolist() == finest.tolist()
    assert int((cells.width.astype(np.int64) ** 3).sum()) == int(np.prod(finest))     # once each
    assert vol.covers_bounds
    # every leaf cell and its value, against the boxes written to the file
    got = {(*p.tolist(), int(L)): v for p, L, v in zip(cells.pos, cells.level, cells.value)}
    assert got == expected_leaf_cells(levels)
    # shape: anisotropic cells keep the domain's aspect
    assert vol.meta["domain_right_edge"] == right and vol.meta["domain_cells"] == [2 * n for n in root_cells]
    np.testing.assert_allclose(plan_scene(ds, ",".join(field)).extent, np.asarray(right) / max(right))


def test02_render_matches_the_gridvolume_reference(llvm, plotfile):
    """The scene made from the output, rendered with the amr medium and
    with Mitsuba's heterogeneous medium on the same field (nearest): 32
    passes each, |z| < 4.5 per 4x4 block."""
    ds = yt.load(str(plotfile))
    plan = plan_scene(ds, "density", log=False)
    scene = scene_for(plan, res=24, spp=8)
    scene["volume"]["interior"]["reconstruction"] = "nearest"
    tf = mi_amr.TransferFunction.load(plan.tf, plan.tf_range)
    ref = dict(scene)
    ref["volume"] = dict(scene["volume"], interior=reference_medium(
        plan.data.to_cells(), tf, plan.density_scale, "nearest", to_world=scene["volume"]["interior"]["to_world"]))
    ref["integrator"] = {"type": "volpath", "max_depth": 64}
    a = render_passes(mi.load_dict(scene), 32, 8, seed0=0)
    b = render_passes(mi.load_dict(ref), 32, 8, seed0=50_000)
    assert np.abs(block_z_scores(a, b, 4)).max() < 4.5
    assert a.mean(axis=0).std() > 0.01


def test03_render_an_output_in_one_command(llvm, plotfile, tmp_path):
    out = tmp_path / "plt.exr"
    r = render_cli([plotfile, "--field", "density", "-o", out, "--spp", "4", "--res", "24"])
    assert r.returncode == 0, r.stderr
    assert out.is_file() and out.with_suffix(".xml").is_file() and out.with_suffix(".cells").is_file()
    img = np.array(mi.Bitmap(str(out)))
    assert np.isfinite(img).all() and img.std() > 0


# ---- One level: a uniform grid in each code's format ----------------------------
@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test04_one_level_outputs_load_exactly_and_render(llvm, fmt, tmp_path):
    """An output with one level (AMReX: two boxes, no refinement; Enzo: the
    root grid alone; Athena++: two mesh blocks at the root level): every cell
    and value as written, at the domain's aspect, and a tiny render."""
    rng = np.random.default_rng(1)
    if fmt == "amrex":
        boxes = [((0, 0, 0), rng.random((4, 8, 4))), ((4, 0, 0), rng.random((4, 8, 4)))]
        path = write_amrex_plotfile(tmp_path / "plt00000", [boxes], [0.0] * 3, [1.0, 2.0, 1.0])
        extent = [1.0, 2.0, 1.0]
    elif fmt == "enzo":
        boxes = [((0, 0, 0), rng.random((8, 8, 8)))]
        path = write_enzo(tmp_path / "DD0000", "DD0000", boxes[0][1], [])
        extent = [1.0, 1.0, 1.0]
    else:
        boxes = [((0, 0, 0), rng.random((4, 4, 4))), ((4, 0, 0), rng.random((4, 4, 4)))]
        path = write_athena_pp(tmp_path / "a.out1.00000.athdf", [boxes], [8, 4, 4], (2.0, 1.0, 1.0))
        extent = [2.0, 1.0, 1.0]
    ds = yt.load(str(path))
    assert ds.index.max_level == 0
    cells = mi_amr.from_yt(ds, FORMATS[fmt][0])
    written = {(*(np.asarray(lo) + ijk).tolist(), 0): np.float32(d[ijk])
               for lo, d in boxes for ijk in np.ndindex(*d.shape)}
    assert {(*p, int(L)): v for p, L, v in zip(cells.pos.tolist(), cells.level, cells.value)} == written
    plan = plan_scene(ds, ",".join(FORMATS[fmt][0]))
    np.testing.assert_allclose(plan.extent, np.asarray(extent) / max(extent))
    img = np.array(mi.render(mi.load_dict(scene_for(plan, res=16, spp=4))))
    assert np.isfinite(img).all() and img.std() > 0


# ---- RAMSES: octree AMR read by yt's RAMSES reader ----------------------------
def ramses_value(level, ijk):
    """The hydro variables of a RAMSES cell (level, integer coordinates at
    that level): density distinct per cell, velocities 0, pressure density/10."""
    rho = 1.0 + level + (ijk[:, 0] + 32 * ijk[:, 1] + 1024 * ijk[:, 2]) / 4096.0
    zero = np.zeros_like(rho)
    return np.stack([rho, zero, zero, zero, rho / 10], axis=1)


def _rows_in(a, b):
    """Which rows of ``a`` (m, 3) are rows of ``b``."""
    return (a[:, None, :] == b[None]).all(axis=2).any(axis=1)


@pytest.fixture(scope="module")
def ramses_output(tmp_path_factory):
    """``(info file, {(x, y, z, level): density})``: a RAMSES output of 4^3
    root cells (levelmin 2), about a third of them refined and a third of
    those refined again (RAMSES levels 2-4: 16^3 finest cells), and its leaf
    cells in mi-amr's units (level 0 = RAMSES level 4)."""
    from amr_formats import write_ramses
    rng = np.random.default_rng(2)
    child = np.array([(i & 1, i >> 1 & 1, i >> 2 & 1) for i in range(8)])
    r2 = np.argwhere(rng.random((4, 4, 4)) < 0.35)
    r3 = (2 * r2[:, None, :] + child[None]).reshape(-1, 3)
    r3 = r3[rng.random(len(r3)) < 0.35]
    info = write_ramses(tmp_path_factory.mktemp("ramses"), 2, [r2, r3], ramses_value)
    leaves, parents = {}, None
    for L, refined in ((2, r2), (3, r3), (4, np.zeros((0, 3), int))):
        ijk = np.argwhere(np.ones((2 ** L,) * 3, bool))
        if parents is not None:                       # the cells of the octs below refined cells
            ijk = ijk[_rows_in(ijk // 2, parents)]
        ijk = ijk[~_rows_in(ijk, refined)]
        for c, rho in zip(ijk << (4 - L), ramses_value(L, ijk)[:, 0]):
            leaves[(*c.tolist(), 4 - L)] = np.float32(rho)
        parents = refined
    return info, leaves


def test05_ramses_leaves_exact(llvm, ramses_output):
    """Every leaf cell of a RAMSES output read by yt's RAMSES reader:
    position, level and value as written; coverage of the domain."""
    from mi_amr.data.yt_import import from_yt_blocks
    info, leaves = ramses_output
    ds = yt.load(str(info))
    assert type(ds).__name__ == "RAMSESDataset" and ds.index.max_level == 2
    vol = from_yt_blocks(ds, ("ramses", "Density"))
    cells = vol.to_cells()
    assert {(*p, int(L)): v for p, L, v in zip(cells.pos.tolist(), cells.level, cells.value)} == leaves
    assert sorted({k[3] for k in leaves}) == [0, 1, 2] and vol.covers_bounds
    assert int((cells.width.astype(np.int64) ** 3).sum()) == 16 ** 3
    assert vol.meta["domain_cells"] == [16, 16, 16] and vol.meta["code"] == "ramses"


@pytest.mark.slow   # default-suite budget: the path is covered by faster tests
def test06_ramses_in_one_command(llvm, ramses_output, tmp_path, capsys):
    """``mi-amr render`` and ``mi-amr info`` on a RAMSES output."""
    from mi_amr.tools.cli import main
    info, leaves = ramses_output
    assert main(["info", str(info), "--field", "density", "--json"]) == 0
    import json
    described = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert described["cells"] == len(leaves)
    out = tmp_path / "ramses.exr"
    r = render_cli([info, "--field", "density", "-o", out, "--spp", "4", "--res", "16"])
    assert r.returncode == 0, r.stderr
    img = np.array(mi.Bitmap(str(out)))
    assert np.isfinite(img).all() and img.std() > 0
