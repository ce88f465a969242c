"""The mi-amr command line, the reference builder and the comparison statistics."""

import json
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.tools.cli import main
from mi_amr.images import read_exr, write_exr
from mi_amr.data.io import write_exabricks
from mi_amr.testing import block_z_scores, render_passes
from mi_amr.reference import reference_medium, resample_dense

from conftest import cloud_scene_xml, random_amr, render_cli, volume_scene

ROOT = Path(__file__).resolve().parents[1]


def test01_info_reports_levels(tmp_path, capsys):
    c = random_amr(1, levels=3)
    write_exabricks(c, tmp_path / "a.cells")
    assert main(["info", str(tmp_path / "a.cells"), "--json"]) == 0
    out = capsys.readouterr().out
    info = json.loads(out.strip().splitlines()[-1])
    assert info["cells"] == len(c)
    assert sum(info["levels"].values()) == len(c)
    assert info["bounds"] == [[0, 0, 0], [16, 16, 16]]


def test02_convert_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    vol = np.round(rng.random((8, 8, 8)) * 2).astype(np.float32) / 2
    vol[:4, :4, :4] = 1.0
    np.save(tmp_path / "v.npy", vol)
    vol.tofile(tmp_path / "v.raw")
    assert main(["convert", str(tmp_path / "v.npy"), str(tmp_path / "a.npz")]) == 0
    assert main(["convert", str(tmp_path / "a.npz"), str(tmp_path / "b.cells")]) == 0
    assert main(["convert", str(tmp_path / "v.raw"), str(tmp_path / "c.cells"), "--shape", "8", "8", "8"]) == 0
    for name in ("a.npz", "b.cells", "c.cells"):
        cells = mi_amr.load_cells(tmp_path / name)
        val, found = resample_dense(cells, "nearest")
        assert found.all()
        np.testing.assert_array_equal(val, vol)
    # wrong .raw shape: a clear error, not a silent truncation
    with pytest.raises(SystemExit, match="needs"):
        main(["convert", str(tmp_path / "v.raw"), str(tmp_path / "d.cells"), "--shape", "8", "8", "9"])


def test03_compare_reports_rmse_and_writes_difference(tmp_path, capsys):
    a = np.ones((4, 5, 3), np.float32)
    b = a.copy()
    b[0, 0] = [2, 1, 1]
    write_exr(tmp_path / "a.exr", a)
    write_exr(tmp_path / "b.exr", b)
    assert main(["compare", str(tmp_path / "a.exr"), str(tmp_path / "b.exr"),
                 "--diff", str(tmp_path / "d.exr"), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["rmse"] == pytest.approx(np.sqrt(1 / 60))
    assert stats["channels"][0]["max_abs"] == pytest.approx(1.0)
    d = read_exr(tmp_path / "d.exr")
    assert d.shape == (4, 5, 3) and d[0, 0, 0] == 1 and d.sum() == 1
    (tmp_path / "bad.exr").write_bytes(b"garbage")
    assert main(["compare", str(tmp_path / "bad.exr"), str(tmp_path / "b.exr")]) == 2


def _render_cli(scene, out, *extra):
    """``mi-amr render SCENE -o OUT -q EXTRA`` in a subprocess."""
    return render_cli([scene, "-o", out, *extra])


def test04_render_writes_exr_and_png(tmp_path):
    xml = cloud_scene_xml(tmp_path, data=random_amr(2, levels=3))
    r = _render_cli(xml, tmp_path / "o.exr", "--spp", "4", "-D", "res=24")
    assert r.returncode == 0, r.stderr
    img = read_exr(tmp_path / "o.exr")
    assert img.shape == (24, 24, 3) and np.isfinite(img).all() and img.std() > 0
    assert (tmp_path / "o.png").stat().st_size > 100


@pytest.mark.parametrize("name", ["demo", "cloud", "shell", "stadium"])
def test05_bundled_scenes_load(llvm, name):
    scene = mi.load_file(str(ROOT / "scenes" / f"{name}.xml"), res=8)
    img = np.array(mi.render(scene, spp=1))
    assert np.isfinite(img).all()


def test06_reference_refuses_oversized_grids():
    c = mi_amr.AMRCells([[0, 0, 0], [4096, 4096, 4096]], [12, 0], [1.0, 2.0])
    with pytest.raises(MemoryError, match="GiB"):
        resample_dense(c, "nearest")


def test07_block_test_detects_a_real_difference(llvm):
    """Power check: the 4-sigma block test flags a 15% density change."""
    cells = random_amr(21, n=16, levels=4, quantize=6)
    tf = mi_amr.TransferFunction.preset("foggy", cells.value_range)
    a = render_passes(mi.load_dict(volume_scene(reference_medium(cells, tf, 100.0, "nearest"))), 16, 16)
    b = render_passes(mi.load_dict(volume_scene(reference_medium(cells, tf, 115.0, "nearest"))), 16, 16, seed0=999)
    assert np.abs(block_z_scores(a, b, 4)).max() > 4.0


def test08_reference_scene_from_xml_matches_amr(llvm, tmp_path):
    """`reference_scene` swaps the amr medium for heterogeneous + gridvolume
    in an XML scene; with nearest reconstruction both agree in expectation."""
    from mi_amr.scene_xml import with_amr_parameters
    from mi_amr.reference import reference_scene
    c = random_amr(5, levels=3, quantize=5)
    write_exabricks(c, tmp_path / "cloud.cells")
    scene = (ROOT / "scenes" / "cloud.xml").read_text()
    (tmp_path / "s.xml").write_text(scene)
    (tmp_path / "data").mkdir()
    write_exabricks(c, tmp_path / "data" / "cloud.cells")
    ref, media = reference_scene(tmp_path / "s.xml", tmp_path / "work", res=24, reconstruction="nearest")
    assert len(media) == 1 and len(media[0].cells) == len(c)
    assert any(p.suffix == ".vol" for p in (tmp_path / "work").iterdir())
    amr = with_amr_parameters(tmp_path / "s.xml", {"majorant": "global"}, res=24, reconstruction="nearest")
    a = render_passes(amr, 16, 8)
    b = render_passes(ref, 16, 8, seed0=500)
    assert np.abs(block_z_scores(a, b, 4)).max() < 4.0
    assert a.mean(axis=0)[..., 0].std() > 0.01
    with pytest.raises(ValueError, match="no <medium"):
        (tmp_path / "empty.xml").write_text('<scene version="3.0.0"/>')
        reference_scene(tmp_path / "empty.xml", tmp_path / "w2")


@pytest.mark.slow
def test09_frametime_reports_three_configurations(tmp_path):
    c = random_amr(6, levels=3)
    (tmp_path / "data").mkdir()
    write_exabricks(c, tmp_path / "data" / "cloud.cells")
    (tmp_path / "s.xml").write_text((ROOT / "scenes" / "cloud.xml").read_text())
    r = subprocess.run([sys.executable, "-m", "mi_amr.tools.cli", "frametime", str(tmp_path / "s.xml"),
                        "--spp", "2", "--repeats", "1", "-D", "res=16", "--json", str(tmp_path / "t.json")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "t.json").read_text())
    assert [x["config"] for x in rows] == ["amr majorant=ray", "amr majorant=global", "heterogeneous reference"]
    assert all(x["frame_s"] > 0 and np.isfinite(x["mean"]) for x in rows)
    assert rows[-1]["speedup_vs_reference"] == pytest.approx(1.0)


def test10_commands_share_render_flags_and_end_help_with_an_example():
    import argparse
    from mi_amr.tools.cli import build_parser
    p = build_parser()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) >= {"render", "reference", "frametime", "info", "convert", "compare", "dataset", "bench"}
    for name, sp in list(sub.choices.items()) + [("mi-amr", p)]:
        lines = sp.format_help().rstrip().splitlines()
        assert lines[-2] == "example:" and lines[-1].strip().startswith(("mi-amr ", "python ")), name
    for name in ("render", "reference", "frametime"):
        out = ["-o", "x.exr"] if name != "frametime" else []
        args = p.parse_args([name, "s.xml", *out, "-q", "--spp", "3", "--seed", "2", "-D", "a=b",
                             "--variant", "llvm_ad_rgb"])
        assert args.quiet and args.spp == 3 and args.seed == 2 and args.define == ["a=b"], name


def test11_a_scene_that_fails_to_load_gives_one_error_line(tmp_path):
    """A scene whose data file is missing: exit code 2 and the plugin's
    error (file named), not a Python traceback."""
    xml = cloud_scene_xml(tmp_path, cells="missing.cells")
    r = _render_cli(xml, tmp_path / "o.exr", "--spp", "1", "-D", "res=8")
    assert r.returncode == 2, r.stderr
    assert "missing.cells: no such file" in r.stderr and "Traceback" not in r.stderr, r.stderr


def _expected_info(value, level):
    """What ``mi-amr info --json`` should say of cells with these values
    and levels, counted with numpy."""
    value, level = np.asarray(value, np.float32).astype(np.float64), np.asarray(level)
    w = np.exp2(3.0 * level)
    return {"levels": {str(L): int((level == L).sum()) for L in np.unique(level)},
            "min": value.min(), "max": value.max(),
            "zero_share_cells": np.mean(value == 0), "negative_share_cells": np.mean(value < 0),
            "zero_share_volume": w[value == 0].sum() / w.sum(), "negative_share_volume": w[value < 0].sum() / w.sum()}


def _check_info(info, expected, field):
    assert info["levels"] == expected["levels"]
    assert sum(r["cells"] for r in info["level_table"]) == info["cells"] == sum(expected["levels"].values())
    stats = info["fields"][field]
    for key in ("min", "max", "zero_share_cells", "negative_share_cells", "zero_share_volume",
                "negative_share_volume"):
        assert stats[key] == pytest.approx(expected[key], rel=1e-9, abs=1e-12), key
    assert info["value_range"] == pytest.approx([expected["min"], expected["max"]])


def test12_info_on_a_cells_file_counts_levels_zeros_and_negatives(llvm, tmp_path, capsys):
    """``mi-amr info DATA.cells --json``: one JSON object whose cells per
    level, range and shares of zeros and negatives (per cell and by volume)
    are numpy's; the medium's memory: data and point-location hash as a
    medium over the file holds them, its total within the stated range.
    The text form keeps the summary lines and adds the shares."""
    c = random_amr(3, levels=3)
    v = c.value.astype(np.float64).copy()
    v[::7] = -0.25
    c = mi_amr.AMRCells(c.pos, c.level, v)
    assert (v == 0).any() and (v < 0).any()
    path = tmp_path / "s.cells"
    write_exabricks(c, path)
    assert main(["info", str(path), "--json"]) == 0
    out = capsys.readouterr().out.strip()
    assert len(out.splitlines()) == 1
    info = json.loads(out)
    _check_info(info, _expected_info(v, c.level), "value")
    assert info["domain"] is None and info["bounds"] == [[0, 0, 0], [16, 16, 16]]
    med = mi.load_dict({"type": "amr", "filename": str(path)})
    m = info["medium_bytes"]
    assert m["data"] == med.volume.nbytes and m["hash"] == med.structures.device["hash"].nbytes
    assert m["total"][0] <= med.resident_bytes <= m["total"][1]
    assert main(["info", str(path)]) == 0
    text = capsys.readouterr().out
    for line in ("source       :", "cells        : " + str(len(c)), "value range  :", "cells per level:",
                 "zeros", "negatives", "amr medium   :"):
        assert line in text, line


def test13_info_on_an_enzo_output(llvm, tmp_path, capsys):
    """``mi-amr info OUTPUT --field density --json`` on an Enzo output
    (tests/amr_formats.py) with zeros and negatives: levels, counts, range
    and shares as numpy counts them from the written grids, the domain and
    cell sizes from the metadata, the field's units and the fields on disk;
    without --field the data set's levels (grids, cells, sizes) and fields
    with units, from the index."""
    pytest.importorskip("yt")
    pytest.importorskip("h5py")
    from amr_formats import write_enzo
    rng = np.random.default_rng(7)
    root = rng.lognormal(0.0, 1.0, (16, 16, 16))
    root[:4] = 0.0
    root[12:, :2] = -1.0
    child = rng.lognormal(1.0, 0.5, (8, 8, 8))
    path = write_enzo(tmp_path / "DD0003", "DD0003", root, [((8, 8, 8), child)])
    covered = np.zeros(root.shape, bool)
    covered[4:8, 4:8, 4:8] = True
    values = np.concatenate([root[~covered], child.ravel()])
    levels = np.r_[np.ones((~covered).sum(), int), np.zeros(child.size, int)]
    assert main(["info", str(path), "--field", "density", "--json"]) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    _check_info(info, _expected_info(values, levels), "density")
    assert info["domain"]["left"] == [0, 0, 0] and info["domain"]["right"] == [1, 1, 1]
    sizes = {r["level"]: r["cell_size"] for r in info["level_table"]}
    assert sizes == {0: [1 / 32] * 3, 1: [1 / 16] * 3}
    assert info["fields"]["density"]["units"] and "enzo,Density" in info["fields_on_disk"]
    assert main(["info", str(path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [(r["level"], r["grids"], r["cells"]) for r in summary["levels"]] == [(0, 1, 16 ** 3), (1, 1, 8 ** 3)]
    assert [r["cell_size"] for r in summary["levels"]] == [[1 / 16] * 3, [1 / 32] * 3]
    assert summary["fields_on_disk"] == {"enzo,Density": "code_mass / code_length**3"}
    assert summary["fields_derived"]["gas,density"] == "g/cm**3"


def test14_refusals_through_the_cli_are_one_line(tmp_path):
    """A refusal of ``mi-amr render`` (no -o and no --movie; --log on data
    with no positive value) is one line on stderr, exit status 2, no
    traceback."""
    data = tmp_path / "neg.npz"
    c = random_amr(0, 8, 2)
    mi_amr.save_cells(mi_amr.AMRCells(c.pos, c.level, -1.0 - c.value), data)
    for argv, words in [([data], "-o/--output is needed"),
                        ([data, "--log", "-o", tmp_path / "o.exr", "--res", "8", "--spp", "1"], "needs positive values")]:
        r = render_cli(argv)
        assert r.returncode == 2 and words in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
