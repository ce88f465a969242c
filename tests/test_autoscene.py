"""A scene from the data alone: `mi_amr.scene_for` and
``mi-amr render DATA --field NAME``; value transforms (log10)."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.autoscene import plan_scene
from mi_amr.scene_writer import scene_for
from mi_amr.data.statistics import weighted_percentiles
from mi_amr.data.io import write_exabricks

from conftest import random_amr


def cosmology_like(shape=(16, 8, 4), seed=0):
    """Two levels over an anisotropic box, values from 3e-31 to 3e-26 with
    some exact zeros: only a log scale makes sense."""
    rng = np.random.default_rng(seed)
    dense = 10.0 ** rng.uniform(-30.5, -25.5, size=shape[::-1]).astype(np.float64)
    dense[0, 0, :3] = 0.0
    return mi_amr.dense_to_amr(dense.astype(np.float32), 0.0, 1)


def test01_log10_transform_floors_non_positive_values(llvm):
    """value_transform=log10: log10 of each value, zero and negative ones
    raised to the smallest positive value first; never NaN; the TF domain
    is in log units; data without a positive value are refused by name."""
    cells = random_amr(0, 8, 2)
    v = cells.value.astype(np.float64).copy()
    v[:4] = 0.0
    v[4] = -2.0
    data = mi_amr.AMRCells(cells.pos, cells.level, v, source="mine")
    med = mi.load_dict({"type": "amr", "data": data, "value_transform": "log10"})
    floor = v[v > 0].min()
    assert med.volume.value_range == pytest.approx((np.log10(floor), np.log10(v.max())), rel=1e-6)
    assert med.tf.domain == pytest.approx(med.volume.value_range)
    vals = med.volume.values[~np.isnan(med.volume.values)]
    assert np.isfinite(vals).all() and vals.size == len(v)
    assert np.all(np.sort(vals) == np.sort(np.log10(np.maximum(v, floor)).astype(np.float32)))
    bad = mi_amr.AMRCells(cells.pos, cells.level, np.zeros(len(v)), source="all-zero.cells")
    with pytest.raises(RuntimeError, match="all-zero.cells.*positive"):
        mi.load_dict({"type": "amr", "data": bad, "value_transform": "log10"})
    with pytest.raises(RuntimeError, match="value_transform"):
        mi.load_dict({"type": "amr", "data": data, "value_transform": "ln"})


def test02_plan_reads_aspect_percentiles_and_scale(llvm):
    """The plan keeps the domain's aspect (16:8:4 cells -> 1 : 0.5 : 0.25),
    chooses log10 for values spanning five decades and places the TF over
    their 1st-99.9th volume-weighted percentiles; linear data stay linear."""
    plan = plan_scene(cosmology_like())
    np.testing.assert_allclose(plan.extent, [1.0, 0.5, 0.25])
    assert plan.transform == "log10"
    lo, hi = plan.value_range
    assert -31 < lo < -30 and -26 < hi < -25.4
    # the default layers span the values the picture's pixels reach, within that range
    assert lo <= plan.tf_range[0] < plan.tf_range[1] <= hi
    # the histogram percentiles against numpy's, weighted by cell volume
    cells = random_amr(1, 16, 3)
    w = np.exp2(3.0 * cells.level)
    order = np.argsort(cells.value)
    cdf = np.cumsum(w[order]) / w.sum()
    for q in (1.0, 50.0, 99.9):
        exact = cells.value[order][np.searchsorted(cdf, q / 100)]
        got = weighted_percentiles(cells, [q])[0]
        assert abs(got - exact) <= (cells.value.max() - cells.value.min()) / 4096 * 1.01 + 1e-12
    linear = plan_scene(cells)
    assert linear.transform == "none" and linear.density_scale > 0


def test03_scene_for_renders_the_data(llvm):
    """`scene_for` gives a scene dictionary that loads and renders a finite
    image in which the volume is visible (the image differs from the same
    scene with the medium made clear)."""
    scene = scene_for(cosmology_like(), res=24, spp=8)
    img = np.array(mi.render(mi.load_dict(scene), spp=8, seed=1))
    assert np.isfinite(img).all()
    clear = dict(scene)
    clear["volume"] = dict(scene["volume"], interior=dict(scene["volume"]["interior"], density_scale=0.0))
    empty = np.array(mi.render(mi.load_dict(clear), spp=8, seed=1))
    assert np.abs(img - empty).mean() > 0.02 * empty.mean()


def test04_cli_renders_a_data_file_and_writes_its_scene(llvm, tmp_path):
    """``mi-amr render DATA.cells`` writes EXR, PNG and the XML scene it
    used; the XML loads on its own, with the planned log10 transform and TF
    range, and renders the same image for the same seed."""
    from conftest import render_cli
    data = tmp_path / "cosmo.cells"
    write_exabricks(cosmology_like(), data)
    out = tmp_path / "out" / "cosmo.exr"
    r = render_cli([str(data), "-o", str(out), "--spp", "4", "--res", "20", "--tf", "spiky"])
    assert r.returncode == 0, r.stderr
    assert out.is_file() and out.with_suffix(".png").is_file()
    xml = out.with_suffix(".xml")
    text = xml.read_text()
    assert 'name="value_transform" value="log10"' in text and 'value="spiky"' in text
    scene = mi.load_file(str(xml))
    med = mi_amr.amr_media(scene)[0]
    assert med.tf.domain[0] < -30 and med.volume.value_range[1] < -25
    again = tmp_path / "again.exr"
    assert render_cli([str(xml), "-o", str(again), "--spp", "4"]).returncode == 0
    a = np.array(mi.Bitmap(str(out)))
    b = np.array(mi.Bitmap(str(again)))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test05_cli_data_options_are_checked(llvm, tmp_path):
    from conftest import render_cli
    data = tmp_path / "d.cells"
    write_exabricks(random_amr(0, 8, 2), data)
    r = render_cli([str(data), "-o", str(tmp_path / "o.exr"), "--tf", "nosuch", "--spp", "1", "--res", "8"])
    assert r.returncode != 0 and "nosuch" in r.stderr
    r = render_cli([str(data), "-o", str(tmp_path / "o.exr"), "--range", "2", "1", "--spp", "1", "--res", "8"])
    assert r.returncode == 2 and "LO must be below HI" in r.stderr and r.stderr.count("\n") == 1
    r = render_cli([str(tmp_path / "missing.plt"), "-o", str(tmp_path / "o.exr"), "--field", "density"])
    assert r.returncode != 0 and "missing.plt" in r.stderr
    xml_scene = tmp_path / "s.xml"
    xml_scene.write_text("<scene version='3.0.0'/>")
    r = render_cli([str(xml_scene), "-o", str(tmp_path / "o.exr"), "--field", "density"])
    assert r.returncode != 0 and "for data files" in r.stderr


def test06_yt_dataset_keeps_its_domain_shape(llvm):
    """A yt dataset on an anisotropic domain (2 : 1 : 1 code units, square
    cells) gets a scene at that aspect."""
    ds = domain_2x1x1([16, 8, 8], seed=2)
    plan = plan_scene(ds, "density")
    np.testing.assert_allclose(plan.extent, [1.0, 0.5, 0.5])
    scene = mi.load_dict(scene_for(plan, res=16, spp=4))
    assert np.isfinite(np.array(mi.render(scene, spp=4))).all()
    with pytest.raises(ValueError, match="field"):
        plan_scene(ds)


def test07_missing_reader_dependency_names_the_package(llvm, tmp_path, monkeypatch):
    """yt imports a format's reader dependency lazily: its absence gives an
    error naming the package and the install command."""
    yt = pytest.importorskip("yt")

    def load(path):
        raise ModuleNotFoundError("No module named 'h5py'", name="h5py")
    monkeypatch.setattr(yt, "load", load)
    (tmp_path / "DD0018").write_text("")
    with pytest.raises(ImportError, match=r"'h5py'.*pip install 'mi-amr\[yt\]'"):
        plan_scene(tmp_path / "DD0018", "density")


def test08_convert_log_writes_log10_values(llvm, tmp_path):
    from mi_amr.tools.cli import main
    src = tmp_path / "c.cells"
    write_exabricks(cosmology_like(), src)
    assert main(["convert", str(src), str(tmp_path / "l.npz"), "--log"]) == 0
    cells = mi_amr.load_cells(tmp_path / "l.npz")
    raw = mi_amr.load_cells(src)
    floor = raw.value[raw.value > 0].min()
    order_a, order_b = np.lexsort(cells.pos.T), np.lexsort(raw.pos.T)
    np.testing.assert_allclose(cells.value[order_a], np.log10(np.maximum(raw.value[order_b], floor)), rtol=1e-6)


def domain_2x1x1(root, seed):
    """A yt dataset over 2 x 1 x 1 code units with ``root`` root cells per
    axis (16, 16, 16: cells of aspect 2 : 1 : 1, as AMReX may write them)
    and one refined patch."""
    yt = pytest.importorskip("yt")
    rng = np.random.default_rng(seed)
    fine = [r // 2 for r in root]
    grids = [dict(left_edge=[0.0, 0.0, 0.0], right_edge=[2.0, 1.0, 1.0], level=0, dimensions=list(root),
                  density=rng.random(tuple(root)) + 0.1),
             dict(left_edge=[0.5, 0.25, 0.25], right_edge=[1.0, 0.5, 0.5], level=1, dimensions=fine,
                  density=rng.random(tuple(fine)) + 0.1)]
    return yt.load_amr_grids(grids, list(root), bbox=np.array([[0.0, 2.0], [0.0, 1.0], [0.0, 1.0]]))


@pytest.mark.parametrize("suffix", [".npz", ".cells"])
def test09_metadata_travels_with_converted_data(llvm, tmp_path, suffix):
    """Cells from yt keep their physical domain (anisotropic cells), field
    and code through a file of either format; a medium loaded from that file
    with no to_world is placed on the domain, and the scene planned from the
    file has the shape of the one planned through yt. A log10 conversion is
    recorded (and not applied twice). Files without metadata keep the unit
    cube."""
    ds = domain_2x1x1([16, 16, 16], seed=3)
    cells = mi_amr.from_yt(ds, ("stream", "density"))
    assert cells.meta["domain_right_edge"] == [2.0, 1.0, 1.0] and cells.meta["domain_cells"] == [32, 32, 32]
    path = mi_amr.save_cells(cells, tmp_path / f"plt{suffix}")
    again = mi_amr.load_cells(path)
    assert again.meta == cells.meta
    med = mi.load_dict({"type": "amr", "filename": str(path)})
    m = np.array(med.options.to_world.matrix)
    np.testing.assert_allclose(np.diag(m)[:3], [2.0, 1.0, 1.0], rtol=1e-6)
    np.testing.assert_allclose(plan_scene(path).extent, plan_scene(ds, "stream,density").extent)
    np.testing.assert_allclose(plan_scene(path).extent, [1.0, 0.5, 0.5])
    logged = mi.load_dict({"type": "amr", "filename": str(path), "value_transform": "log10"})
    assert logged.volume.meta["value_transform"] == "log10" and logged.volume.meta["log_floor"] > 0
    from mi_amr.data.transform import apply_value_transform
    log_cells, _ = apply_value_transform(cells, "log10")
    with pytest.raises(ValueError, match="already log10"):
        apply_value_transform(log_cells, "log10")
    plain = tmp_path / f"plain{suffix}"
    mi_amr.save_cells(random_amr(0, 8, 2), plain)
    np.testing.assert_allclose(np.array(mi.load_dict({"type": "amr", "filename": str(plain)}).options.to_world.matrix),
                               np.eye(4))


def test10_bad_metadata_is_refused_by_name(llvm, tmp_path):
    path = tmp_path / "d.cells"
    write_exabricks(random_amr(0, 8, 2), path)
    side = tmp_path / "d.cells.json"
    side.write_text("{not json")
    with pytest.raises(ValueError, match="d.cells.json"):
        mi_amr.load_cells(path)
    side.write_text('{"domain_left_edge": [0, 0, 0], "domain_right_edge": [1, 1, 0], "domain_cells": [8, 8, 8]}')
    with pytest.raises(ValueError, match="left < right"):
        mi_amr.load_cells(path)


# ---- Fields that are not positive, narrow ranges, bounded density scales --------
def signed_field(n=32, seed=4):
    """``n^3`` values: 0 where x < 20 (62.5% of the volume, merged into
    coarse cells), negative in a corner column (3.1%), a log-normal tail
    (10^-3 to 10^3) elsewhere."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*[np.arange(n)] * 3, indexing="ij")
    v = 10.0 ** rng.normal(0.0, 1.0, (n, n, n))
    v[x < 20] = 0.0
    v[(x >= 28) & (y < 8)] = -0.5
    return mi_amr.dense_to_amr(v.astype(np.float32), 0.0, 2, source="signed")


def nearly_constant(n=32, seed=5):
    """1.0 in all but 16 of the ``n^3`` cells, those log-uniform in 1..10."""
    rng = np.random.default_rng(seed)
    v = np.ones(n ** 3)
    v[rng.choice(n ** 3, 16, replace=False)] = 10.0 ** rng.uniform(0, 1, 16)
    return mi_amr.dense_to_amr(v.reshape(n, n, n).astype(np.float32), 0.0, 2, source="nearly-constant")


def dense_values(cells):
    """The cells as a dense ``[z, y, x]`` array of the finest level (host)."""
    lo, hi = cells.bounds
    assert not lo.any()
    out = np.full(tuple(int(n) for n in hi[::-1]), np.nan)
    for (x, y, z), level, v in zip(cells.pos, cells.level, cells.value):
        w = 1 << int(level)
        out[z:z + w, y:y + w, x:x + w] = v
    assert not np.isnan(out).any()
    return out


def column_depths(plan, cells):
    """Optical depths along x (the longest side, world length 1) through
    every finest column of the data, by the plan's TF, range and scale,
    computed from the cells with numpy: log10 of values <= 0 raised to the
    smallest positive value, as the medium does."""
    from mi_amr.transfer.function import TransferFunction
    v = dense_values(cells)
    if plan.transform == "log10":
        v = np.log10(np.maximum(v, v[v > 0].min()))
    alpha = TransferFunction.load(plan.tf, plan.tf_range)(v)[..., 3].astype(np.float64)
    return plan.density_scale * alpha.sum(axis=2) / v.shape[2]


def test11_zeros_and_negatives_under_log10(llvm):
    """--log on a field 62.5% zero and 3.1% negative by volume: the notes
    name both shares (as numpy counts them), the TF range runs from the 1st
    volume percentile of the positive values' log10 to the higher of their
    99.9th volume and mass (volume times value) percentiles, zeros and negatives
    sit at the TF's bottom in the medium, and a render has no NaN, with a
    finite majorant within the bound. Without --log the values stay linear
    and the note says why."""
    from mi_amr.autoscene import MAX_DEPTH
    cells = signed_field()
    w = np.exp2(3.0 * cells.level)
    zero, neg = (w[cells.value == 0].sum() / w.sum(), w[cells.value < 0].sum() / w.sum())
    assert 0.6 < zero < 0.65 and 0.02 < neg < 0.04
    plan = plan_scene(cells, log=True)
    notes = "\n".join(plan.notes)
    assert f"{100 * zero:.3g}% of the volume" in notes and f"{100 * neg:.3g}% of the volume" in notes, notes
    assert "zeros and negatives take the TF's bottom" in notes
    pos = cells.value > 0
    lv, pw = np.log10(cells.value[pos].astype(np.float64)), w[pos]
    order = np.argsort(lv)
    cdf = np.cumsum(pw[order]) / pw.sum()
    mass_cdf = np.cumsum((pw * 10.0 ** lv)[order]) / (pw * 10.0 ** lv).sum()
    bin_width = (lv.max() - lv.min()) / 4096
    expected = (lv[order][np.searchsorted(cdf, 0.01)],
                max(lv[order][np.searchsorted(cdf, 0.999)], lv[order][np.searchsorted(mass_cdf, 0.999)]))
    for want, got in zip(expected, plan.value_range):
        assert abs(got - want) <= 1.01 * bin_width + 1e-9
    assert plan.value_range[0] <= plan.tf_range[0] < plan.tf_range[1] <= plan.value_range[1]
    scene = mi.load_dict(scene_for(plan, res=16, spp=4))
    med = mi_amr.amr_media(scene)[0]
    assert med.volume.meta["log_floor"] == pytest.approx(cells.value[pos].min())
    assert np.log10(med.volume.meta["log_floor"]) <= plan.tf_range[0]          # zeros: the TF's bottom
    assert np.isfinite(med.global_majorant) and med.global_majorant <= MAX_DEPTH * (1 + 1e-5)
    assert np.isfinite(np.array(mi.render(scene, spp=4))).all()
    linear = plan_scene(cells)
    assert linear.transform == "none"
    assert any("only" in n and "positive" in n for n in linear.notes), linear.notes
    with pytest.raises(ValueError, match="needs positive values"):
        plan_scene(mi_amr.AMRCells(cells.pos, cells.level, -np.abs(cells.value) - 1, source="neg"), log=True)


def test12_a_nearly_constant_field_gets_the_range_its_mass_spans(llvm):
    """A field that is 1.0 but for 16 cells (0.2% of the mass): its volume
    percentiles are one value, and the TF range reaches from it to the
    mass's 99.9th percentile (as numpy computes it, within a histogram
    bin), inside the values' span: never widened into values the data do
    not hold. A field of one value gets a range centred on it."""
    cells = nearly_constant()
    plan = plan_scene(cells)
    assert plan.transform == "none"
    lo, hi = plan.tf_range
    v = cells.value.astype(np.float64)
    w = np.exp2(3.0 * cells.level)
    order = np.argsort(v)
    mass_cdf = np.cumsum((w * v)[order]) / (w * v).sum()
    bin_width = (v.max() - v.min()) / 4096
    assert abs(lo - 1.0) <= 1.01 * bin_width
    assert abs(hi - v[order][np.searchsorted(mass_cdf, 0.999)]) <= 1.01 * bin_width
    assert lo >= v.min() and hi <= v.max() + 1e-6 and hi > 1.5
    flat = mi_amr.dense_to_amr(np.full((8, 8, 8), 3.0, np.float32), 0.0, 1, source="flat")
    plan = plan_scene(flat)
    assert plan.tf_range[0] < 3.0 < plan.tf_range[1] and any("one value" in n for n in plan.notes)


@pytest.mark.parametrize("make,capped", [(nearly_constant, True), (signed_field, True), (cosmology_like, False)])
def test13_density_scale_is_bounded(llvm, make, capped):
    """density_scale = TARGET_DEPTH / mean opacity, but at most MAX_DEPTH /
    the TF's highest opacity over the values (it binds where the mean
    opacity is tiny: the nearly constant field, and the signed one with
    its linear TF over a log-normal tail). From the cells, with numpy:
    the mean optical depth along an axis is the plan's (at most
    TARGET_DEPTH), no column exceeds MAX_DEPTH, and the medium's global
    majorant keeps within it; a tiny render is finite."""
    from mi_amr.autoscene import MAX_DEPTH, TARGET_DEPTH
    from mi_amr.transfer.function import TransferFunction
    cells = make()
    layered = plan_scene(cells)                 # the default: layers, their scale planned by the layers' check
    v = cells.value.astype(np.float64)
    if layered.transform == "log10":
        v = np.log10(np.maximum(v, v[v > 0].min()))
    peak = TransferFunction.load(layered.tf, layered.tf_range).max_alpha(v.min(), v.max())[0]
    assert layered.density_scale * peak <= MAX_DEPTH * (1 + 1e-6)
    assert column_depths(layered, cells).max() <= MAX_DEPTH * (1 + 1e-6)
    plan = plan_scene(cells, tf="spiky")        # a TF named: the mean-opacity rule
    tau = column_depths(plan, cells)
    assert tau.mean() == pytest.approx(plan.optical_depth, rel=1e-4, abs=1e-9)
    assert tau.mean() <= TARGET_DEPTH * (1 + 1e-6) and tau.max() <= MAX_DEPTH * (1 + 1e-6)
    v = cells.value.astype(np.float64)
    if plan.transform == "log10":
        v = np.log10(np.maximum(v, v[v > 0].min()))
    peak = TransferFunction.load(plan.tf, plan.tf_range).max_alpha(v.min(), v.max())[0]
    assert plan.density_scale * peak <= MAX_DEPTH * (1 + 1e-6)
    assert (TARGET_DEPTH / (tau.mean() / plan.density_scale) * peak > MAX_DEPTH) == capped
    if capped:
        assert plan.density_scale == pytest.approx(MAX_DEPTH / peak) and any("capped" in n for n in plan.notes)
    else:
        assert plan.optical_depth == pytest.approx(TARGET_DEPTH, rel=1e-6)
    scene = mi.load_dict(scene_for(plan, res=12, spp=2))
    assert mi_amr.amr_media(scene)[0].global_majorant <= MAX_DEPTH * (1 + 1e-5)
    assert np.isfinite(np.array(mi.render(scene, spp=2))).all()


def test14_a_tf_file_named_relatively_renders_from_any_folder(llvm, tmp_path, monkeypatch):
    """``mi-amr render DATA --tf presets/cool.json`` (a path relative to
    where it runs) writes a scene that names the file absolutely: rendered
    from another folder, it finds the file and gives the same picture."""
    from mi_amr.images import read_exr
    from mi_amr.tools.cli import main
    (tmp_path / "presets").mkdir()
    mi_amr.TransferFunction.from_colormap("cool", [(0, 0), (1, 0.8)]).to_json(tmp_path / "presets" / "cool.json")
    data = tmp_path / "d.cells"
    write_exabricks(random_amr(0, 8, 2), data)
    monkeypatch.chdir(tmp_path)
    assert main(["render", str(data), "--tf", "presets/cool.json", "--res", "8", "--spp", "2",
                 "-o", str(tmp_path / "out" / "a.exr"), "-q"]) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["render", str(tmp_path / "out" / "a.xml"), "--spp", "2", "-o", str(tmp_path / "b.exr"), "-q"]) == 0
    np.testing.assert_array_equal(read_exr(tmp_path / "out" / "a.exr"), read_exr(tmp_path / "b.exr"))


def test15_the_written_scene_parses_whatever_the_notes_say(llvm, tmp_path):
    """The plan's notes go into an XML comment, which may not hold "--";
    a linear plan's notes name --log: the written scene is well-formed XML
    (Mitsuba's parser let it pass, Python's, on a cluster's workers, did
    not: --workers failed on every planned scene whose notes named a flag), and
    renders the image of the plan's own dictionary (same seed)."""
    from mi_amr.scene_writer import write_scene_xml
    from mi_amr.data.io import write_exabricks
    cells = random_amr(0, 8, 2)
    data = tmp_path / "d.cells"
    write_exabricks(cells, data)
    plan = plan_scene(str(data))
    assert any("--" in n for n in plan.notes), plan.notes
    xml = write_scene_xml(plan, data, tmp_path / "d.xml", res=8, spp=4)
    import xml.etree.ElementTree as ET
    ET.parse(xml)                        # well-formed: Python's parser (a cluster's workers) is strict
    from_xml = np.array(mi.render(mi.load_file(str(xml)), seed=1))
    from_dict = np.array(mi.render(mi.load_dict(scene_for(plan, res=8, spp=4)), seed=1))
    np.testing.assert_allclose(from_xml, from_dict, rtol=1e-5, atol=1e-6)
