"""Transfer functions: interpolation, clamping, presets, ParaView and
matplotlib colour maps, and range majorants against brute force."""

import json
import re

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.transfer.function import PRESETS, TransferFunction
from mi_amr.transfer.device import DeviceTransferFunction


def test01_tf_interpolation_and_clamping():
    tf = TransferFunction([[0, 0, 0, 0], [1, 0.5, 0, 1], [0, 0, 1, 0.5]], (10, 20))
    np.testing.assert_allclose(tf([10, 12.5, 15, 17.5, 20]),
                               [[0, 0, 0, 0], [0.5, 0.25, 0, 0.5], [1, 0.5, 0, 1],
                                [0.5, 0.25, 0.5, 0.75], [0, 0, 1, 0.5]], atol=1e-6)
    np.testing.assert_allclose(tf([-100, 100])[:, 3], [0, 0.5])   # clamped
    for bad in ([[0, 0, 0, 2], [0, 0, 0, 0]], [[0, 0, 0, np.nan], [0, 0, 0, 0]], [[0, 0, 0, 0]]):
        with pytest.raises(ValueError):
            TransferFunction(bad, (0, 1))
    with pytest.raises(ValueError, match="domain"):
        TransferFunction([[0, 0, 0, 0]] * 2, (1, 1))


def test02_presets_json_and_colormap(tmp_path):
    for name in PRESETS:
        tf = TransferFunction.preset(name, (0, 2))
        assert tf.domain == (0, 2) and len(tf) == 256
    spiky, foggy = TransferFunction.preset("spiky"), TransferFunction.preset("foggy")
    assert spiky.rgba[:, 3].max() == pytest.approx(1.0) and (spiky.rgba[:, 3] == 0).mean() > 0.5
    assert foggy.rgba[:, 3].max() < 0.2 and (foggy.rgba[:, 3] > 0).mean() > 0.9
    with pytest.raises(ValueError, match="unknown transfer function preset"):
        TransferFunction.preset("nope")
    tf = TransferFunction.from_colormap("magma", [(0, 0), (0.5, 1), (1, 0.2)], (-1, 1), n=64)
    assert tf.rgba[32, 3] == pytest.approx(1.0, abs=0.02)
    p = tmp_path / "tf.json"
    tf.to_json(p)
    d = json.loads(p.read_text())
    assert d["domain"] == [-1, 1] and len(d["rgba"]) == 64
    back = TransferFunction.from_json(p)
    np.testing.assert_allclose(back.rgba, tf.rgba, atol=1e-6)
    p.write_text('{"domain": [0, 1]}')
    with pytest.raises(ValueError, match="tf.json"):
        TransferFunction.from_json(p)


def test03_range_majorant_matches_brute_force(variant):
    rng = np.random.default_rng(1)
    for name, n in (("spiky", 256), ("foggy", 100), ("ramp", 7)):
        tf = TransferFunction.preset(name, (-1, 3), n=n)
        dev = DeviceTransferFunction(tf)
        a = rng.uniform(-2, 4, 2000)
        b = a + rng.exponential(0.4, 2000)
        ref = tf.max_alpha(a, b)
        got = dev.range_max_alpha(mi.Float(a), mi.Float(b)).numpy()
        np.testing.assert_array_equal(got, ref)
        empty = dev.range_max_alpha(mi.Float([1.0]), mi.Float([0.5])).numpy()
        assert empty[0] == 0.0
        # the range maximum bounds the interpolated TF everywhere inside the range
        v = a + rng.random(2000) * (b - a)
        assert np.all(tf(v)[:, 3] <= ref + 1e-6)
        rgb, alpha = dev.eval(mi.Float(v))
        np.testing.assert_allclose(alpha.numpy(), tf(v)[:, 3], atol=1e-5)
        np.testing.assert_allclose(np.array(rgb).T if np.array(rgb).shape[0] == 3 else np.array(rgb),
                                   tf(v)[:, :3], atol=1e-5)


def test07_paraview_preset_loads_and_renders(variant, tmp_path):
    """A preset in ParaView's documented JSON format (RGBPoints: x r g b,
    Points: x opacity midpoint sharpness) loads and renders."""
    preset = [{"Name": "Cool to Warm", "ColorSpace": "Diverging",
               "RGBPoints": [0.0, 0.23, 0.299, 0.754, 0.5, 0.865, 0.865, 0.865, 1.0, 0.706, 0.016, 0.15]},
              {"Name": "Blob", "RGBPoints": [-1.0, 0, 0, 1, 3.0, 1, 0, 0],
               "Points": [-1.0, 0.0, 0.5, 0.0, 1.0, 0.8, 0.5, 0.0, 3.0, 0.1, 0.5, 0.0]}]
    p = tmp_path / "presets.json"
    p.write_text(json.dumps(preset))
    cool = TransferFunction.from_paraview(p)
    assert cool.domain == (0.0, 1.0)
    np.testing.assert_allclose(cool(0.5)[:3], [0.865, 0.865, 0.865], atol=1e-2)
    np.testing.assert_allclose(cool([0.0, 1.0])[:, 3], [0.0, 1.0], atol=1e-6)    # no Points: a ramp
    blob = TransferFunction.from_paraview(p, name="Blob")
    assert blob.domain == (-1.0, 3.0)
    np.testing.assert_allclose(blob([1.0])[0, 3], 0.8, atol=1e-2)
    with pytest.raises(ValueError, match="no preset named"):
        TransferFunction.from_paraview(p, name="Nope")
    single = tmp_path / "single.json"
    single.write_text(json.dumps(preset[1]))
    assert TransferFunction.from_json(single).domain == (-1.0, 3.0)   # recognised by RGBPoints
    from conftest import random_amr, volume_scene
    cells = random_amr(2)
    scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": str(single),
                                       "density_scale": 20.0}, res=16))
    img = np.array(mi.render(scene, spp=4))
    assert np.isfinite(img).all() and img[..., 0].std() > 0.005


def test08_matplotlib_colormap_by_name():
    tf = TransferFunction.load("magma", (2.0, 4.0))
    assert tf.domain == (2.0, 4.0)
    np.testing.assert_allclose(tf([2.0, 3.0, 4.0])[:, 3], [0.0, 0.5, 1.0], atol=1e-2)
    import matplotlib
    np.testing.assert_allclose(tf([4.0])[0, :3], matplotlib.colormaps["magma"](1.0)[:3], atol=1e-6)
    with pytest.raises(ValueError, match="matplotlib colormap name"):
        TransferFunction.load("not-a-colormap")



@pytest.mark.parametrize("tf", ["ramp", "two-entry"])
@pytest.mark.parametrize("method", ["nearest", "tent"])
def test09_zero_opacity_regions_get_zero_majorants(llvm, tf, method):
    """A range ending exactly on a table entry does not take the next entry:
    with the ramp preset (alpha 0 at the lowest value, rising at once) or a
    2-entry 0 -> 1 table, macrocells that only see zero values get a zero
    majorant, and a ray through only such macrocells costs no look-up and
    keeps transmittance 1."""
    import mi_amr
    from stress_oracles import ratio_tracking
    g = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    value = np.where(g[:, 0] >= 4, 0.25 + 0.75 * np.random.default_rng(0).random(len(g)), 0.0)
    cells = mi_amr.AMRCells(g, np.zeros(len(g), int), value)
    table = "ramp" if tf == "ramp" else TransferFunction([[1, 1, 1, 0], [1, 1, 1, 1]], (0.0, 1.0))
    med = mi.load_dict({"type": "amr", "data": cells, "transfer_function": table, "tf_min": 0.0, "tf_max": 1.0,
                        "density_scale": 10.0, "reconstruction": method, "grid_resolution": 8})
    maj = med.majorant_grid                                   # [z, y, x]
    clear = 4 if method == "nearest" else 3                   # tent supports reach half a cell further
    assert (maj[:, :, :clear] == 0).all()
    assert (maj[:, :, 4:] > 0).all()
    rng = np.random.default_rng(1)
    n = 2000
    o = np.column_stack([rng.uniform(0.01, clear / 8 - 0.01, n), np.full(n, -0.5), rng.random(n)])
    d = np.tile([0.0, 1.0, 0.0], (n, 1))
    T, counts = ratio_tracking(med, o, d, 1)
    assert (T == 1.0).all() and counts.lookups.numpy().sum() == 0


# ---- .json files rescaled as ParaView applies a preset -----------------------------
#: A [0, 1] preset as ParaView stores its own: blue to red, opacity 0 -> 1.
BLUE_RED = {"Name": "Blue to Red", "RGBPoints": [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0],
            "Points": [0.0, 0.0, 0.5, 0.0, 1.0, 1.0, 0.5, 0.0]}
#: Densities of a tenuous gas, in g/cm^3: far from the preset's [0, 1].
TINY = (1e-30, 1e-26)


def test10_json_files_are_rescaled_to_the_range_asked_for(tmp_path):
    """`TransferFunction.load` stretches a ParaView preset onto the range
    asked for, else onto the data's range; our own format onto the range
    asked for, else it keeps its stored domain; ``keep_range`` (the
    caller's, or the file's ``"keep_range": true``) keeps the file's own
    range. Colours follow: the preset's first colour at the bottom of the
    range, its last at the top, its middle in the middle (to 1e-6)."""
    pv = tmp_path / "pv.json"
    pv.write_text(json.dumps([BLUE_RED]))
    tf = TransferFunction.load(pv, data_range=TINY)
    assert tf.domain == TINY
    np.testing.assert_allclose(tf(np.array(TINY)), [[0, 0, 1, 0], [1, 0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(tf(np.mean(TINY)), [0.5, 0, 0.5, 0.5], atol=2e-3)   # a 256-entry table
    assert TransferFunction.load(pv, (2.0, 3.0), data_range=TINY).domain == (2.0, 3.0)
    assert TransferFunction.load(pv, (2.0, 3.0), keep_range=True).domain == (0.0, 1.0)
    assert TransferFunction.load(pv).domain == (0.0, 1.0)                      # no range: its own
    kept = tmp_path / "kept.json"
    kept.write_text(json.dumps(dict(BLUE_RED, keep_range=True)))
    assert TransferFunction.load(kept, (2.0, 3.0), data_range=TINY).domain == (0.0, 1.0)
    ours = tmp_path / "ours.json"
    TransferFunction.preset("ramp", (5.0, 7.0)).to_json(ours)
    assert TransferFunction.load(ours, (2.0, 3.0)).domain == (2.0, 3.0)
    assert TransferFunction.load(ours, data_range=TINY).domain == (5.0, 7.0)    # its stored domain
    ours.write_text(json.dumps(dict(json.loads(ours.read_text()), keep_range=True)))
    assert TransferFunction.load(ours, (2.0, 3.0)).domain == (5.0, 7.0)
    ours.write_text(json.dumps(dict(json.loads(ours.read_text()), keep_range="yes")))
    with pytest.raises(ValueError, match="keep_range"):
        TransferFunction.load(ours, (2.0, 3.0))


def test11_a_unit_preset_over_tiny_densities_shows_in_the_medium(variant, tmp_path):
    """A [0, 1] ParaView preset given as the ``amr`` medium's
    ``transfer_function`` over data in [1e-30, 1e-26], with no
    ``tf_min``/``tf_max``: the medium's TF spans the data's range and the
    gas shows where the ``ramp`` preset over that range (the same opacity,
    other colours) shows it: the shares of pixels that differ from the
    empty medium's image by more than 0.05 (above the noise of 4 spp in
    the background, which is exact) agree within 0.05 and exceed 0.1; with ``tf_keep_range`` the preset stays over
    [0, 1], every value sits at its transparent bottom and the image is
    the empty medium's (to 1e-5). ``tf_min``/``tf_max`` give the range."""
    from conftest import random_amr, volume_scene
    pv = tmp_path / "pv.json"
    pv.write_text(json.dumps([BLUE_RED]))
    base = random_amr(2)
    cells = type(base)(base.pos, base.level, TINY[0] + base.values * (TINY[1] - TINY[0]))

    def render(**extra):
        medium = dict({"type": "amr", "data": cells, "transfer_function": str(pv), "density_scale": 30.0}, **extra)
        scene = mi.load_dict(volume_scene(medium, res=16))
        return np.array(mi.render(scene, spp=4)), mi_amr.amr_media(scene)[0]

    shown, medium = render()
    lo, hi = cells.value_range
    np.testing.assert_allclose(medium.tf.domain, (lo, hi), rtol=1e-6)
    np.testing.assert_allclose(medium.tf(hi)[:3], [1, 0, 0], atol=1e-6)
    kept, kept_medium = render(tf_keep_range=True)
    assert kept_medium.tf.domain == (0.0, 1.0)
    empty, _ = render(density_scale=0.0)
    np.testing.assert_allclose(kept, empty, atol=1e-5)
    ramp, _ = render(transfer_function="ramp")
    shows = [(np.abs(img - empty).max(axis=-1) > 0.05).mean() for img in (shown, ramp)]
    assert shows[0] > 0.1 and abs(shows[0] - shows[1]) < 0.05, shows
    _, ranged = render(tf_min=2e-27, tf_max=4e-27)
    assert ranged.tf.domain == (2e-27, 4e-27)


def test12_a_relative_tf_path_in_a_scene_file_is_found_beside_it(variant, tmp_path, monkeypatch):
    """A scene file that names its TF by a path relative to itself loads
    from any working directory (Mitsuba's file resolver holds the scene's
    folder), and a missing TF file is refused in one line that names it."""
    from conftest import cloud_scene_xml, random_amr
    from mi_amr.params import plugin_error
    scene_dir = tmp_path / "scene"
    scene_dir.mkdir()
    xml = cloud_scene_xml(scene_dir, data=random_amr(2))
    (scene_dir / "pv.json").write_text(json.dumps([BLUE_RED]))
    text = xml.read_text()
    assert text.count('name="transfer_function"') == 1
    xml.write_text(re.sub(r'(name="transfer_function" value=)"[^"]*"', r'\1"pv.json"', text))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    medium = mi_amr.amr_media(mi.load_file(str(xml)))[0]
    np.testing.assert_allclose(medium.tf(medium.tf.domain[1])[:3], [1, 0, 0], atol=1e-6)
    (scene_dir / "pv.json").unlink()
    with pytest.raises(Exception) as info:
        mi.load_file(str(xml))
    line = plugin_error(str(info.value))
    assert "\n" not in line and "transfer_function" in line and "pv.json" in line, line
