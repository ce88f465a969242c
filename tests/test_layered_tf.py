"""Layered transfer functions (mi_amr/transfer/layers.py,
docs/manual/transfer-functions.md "Layers"): the preset by name, options and file, the colour-layer
measure of a picture (`mi_amr.visibility.colour_layers`) on images whose
answer is known, and the default picture of deep hierarchies (an
eight-level AMReX collapse, a five-decade Enzo cosmology) against yt's
``create_scene`` default on the same outputs."""

import json

import mitsuba as mi
import numpy as np
import pytest

from mi_amr.transfer.function import TransferFunction
from mi_amr.transfer.layers import Layers
from mi_amr.visibility import colour_layers

from conftest import HANG_S, wait_until


def test01_layers_by_name_options_and_file(llvm, tmp_path):
    """``layers`` and ``layers:n=..,width=..,colormap=..,low=..`` give the
    same table from Python, a TF file and an XML scene: n peaks at the
    layers' centres in their colormap's colours, opacity rising from
    ``low`` to 1 (the last layer holding it above its centre), about 0
    between layers; bad options are one line naming the option."""
    spec = "layers:n=5,width=0.15,colormap=plasma,low=0.01"
    layers = Layers.parse(spec)
    assert (layers.n, layers.width, layers.colormap, layers.low) == (5, 0.15, "plasma", 0.01)
    assert Layers.parse(layers.spec()) == layers and Layers.parse("layers") == Layers()
    tf = TransferFunction.preset(spec, (2.0, 7.0), n=1001)
    u = np.linspace(0, 1, 1001)
    import matplotlib
    for k, c in enumerate(layers.centres()):
        i = int(round(c * 1000))
        assert tf.rgba[i, 3] == pytest.approx(0.01 ** (1 - k / 4), rel=1e-3)
        np.testing.assert_allclose(tf.rgba[i, :3], matplotlib.colormaps["plasma"](k / 4)[:3], atol=2e-3)
    peaks = np.flatnonzero((tf.rgba[1:-1, 3] > tf.rgba[:-2, 3]) & (tf.rgba[1:-1, 3] >= tf.rgba[2:, 3])) + 1
    assert len(peaks) == 5
    between = int(round(0.5 * (layers.centres()[1] + layers.centres()[2]) * 1000))
    assert tf.rgba[between, 3] < 0.01 * tf.rgba[int(round(layers.centres()[2] * 1000)), 3]
    assert np.all(tf.rgba[u >= layers.centres()[-1], 3] == pytest.approx(1.0))
    # the same TF by name through load, from a .json file of layers, and in an XML scene
    by_name = TransferFunction.load(spec, (2.0, 7.0))
    path = tmp_path / "layers.json"
    path.write_text(json.dumps({"layers": {"n": 5, "width": 0.15, "colormap": "plasma", "low": 0.01}}))
    by_file = TransferFunction.load(str(path), (2.0, 7.0))
    np.testing.assert_allclose(by_file.rgba, by_name.rgba, atol=1e-7)
    assert by_file.domain == (2.0, 7.0) == by_name.domain
    import mi_amr
    cells = mi_amr.dense_to_amr(np.linspace(2, 7, 512, dtype=np.float32).reshape(8, 8, 8), 0.0, 1)
    medium = mi.load_dict({"type": "amr", "data": cells, "transfer_function": spec, "tf_min": 2.0, "tf_max": 7.0})
    np.testing.assert_allclose(medium.tf.rgba, by_name.rgba, atol=1e-7)
    for bad, word in (("layers:n=0", "n must"), ("layers:width=9", "width"), ("layers:colormap=nope", "colormap"),
                      ("layers:low=0", "low"), ("layers:size=3", "keys"), ("layers:n=2.5", "integer")):
        with pytest.raises(ValueError, match=word) as e:
            TransferFunction.load(bad, (0, 1))
        assert "\n" not in str(e.value)
    with pytest.raises(Exception, match="transfer_function.*width"):
        mi.load_dict({"type": "amr", "data": cells, "transfer_function": "layers:width=-1"})


def _patches(hues, shape=(120, 160), chroma=50.0, seed=0):
    """An sRGB uint8 image: a grey ground (bottom), a pale sky (top band),
    black at the left, and one vertical band per hue (degrees in CIELAB's
    (a*, b*)), each shaded from dark to light and from full to a third of
    ``chroma`` (the same layer, seen through less of it), plus noise."""
    from mi_amr.visibility import srgb_to_lab
    h, w = shape
    lab = np.zeros((h, w, 3))
    lab[..., 0] = 60.0 + np.random.default_rng(seed).normal(0, 1.0, (h, w))     # grey, L* 60
    lab[: h // 6, :, 0] = 97.0                                                 # pale sky
    lab[: h // 6, :, 2] = -3.0
    lab[:, : w // 8] = 0.0                                                      # black
    x0, band = w // 8, (w - w // 8) // max(len(hues), 1)
    for k, hue in enumerate(hues):
        rows = slice(h // 6, h - h // 6)
        cols = slice(x0 + k * band, x0 + (k + 1) * band)
        n_r, n_c = rows.stop - rows.start, cols.stop - cols.start
        shade = np.linspace(30, 80, n_r)[:, None] * np.ones((1, n_c))
        c = chroma * np.linspace(1.0, 0.35, n_c)[None, :] * np.ones((n_r, 1))
        lab[rows, cols, 0] = shade
        lab[rows, cols, 1] = c * np.cos(np.radians(hue))
        lab[rows, cols, 2] = c * np.sin(np.radians(hue))
    # CIELAB -> sRGB by inverting srgb_to_lab on a lookup: solve per pixel with a few Newton-free steps
    return _lab_to_srgb8(lab, srgb_to_lab)


def _lab_to_srgb8(lab, forward):
    """CIELAB -> sRGB uint8 (the closed-form inverse of `srgb_to_lab`),
    checked against it."""
    fy = (lab[..., 0] + 16) / 116
    f = np.stack([fy + lab[..., 1] / 500, fy, fy - lab[..., 2] / 200], axis=-1)
    xyz = np.where(f > 6 / 29, f ** 3, 3 * (6 / 29) ** 2 * (f - 4 / 29)) * np.array([0.95047, 1.0, 1.08883])
    m = np.array([[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750],
                  [0.0193339, 0.1191920, 0.9503041]])
    lin = np.clip(xyz @ np.linalg.inv(m).T, 0, 1)
    srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    out = np.round(255 * srgb).astype(np.uint8)
    inside = (xyz @ np.linalg.inv(m).T >= -1e-9).all(-1) & (xyz @ np.linalg.inv(m).T <= 1 + 1e-9).all(-1)
    back = forward(out)
    assert np.abs(back[inside][:, 1:] - lab[inside][:, 1:]).max() < 3.0        # the inverse is the forward's
    return out


@pytest.mark.parametrize("hues", [(320.0, 260.0, 190.0, 140.0, 95.0), (40.0, 200.0, 300.0),
                                  (0.0, 50.0, 100.0, 150.0, 200.0, 250.0, 300.0)])
def test02_colour_layers_counts_the_hues_an_eye_tells_apart(hues):
    """Synthetic pictures with a known number of colour layers (bands of
    distinct hues, each shaded in lightness and chroma) on a grey ground,
    under a pale sky, beside black: the measure counts exactly the bands
    (3, 5 and 7: a count that differs gives that count); the ground, sky
    and black add none, and a further hue on 1% of the coloured pixels is
    no layer (the measure's 3%), on 10% it is one."""
    img = _patches(hues)
    got = colour_layers(img)
    assert got.count == len(hues), (got, got.hues, got.shares)
    d = np.abs((np.sort(got.hues)[:, None] - np.sort(hues)[None, :] + 180) % 360 - 180)
    assert d.min(axis=1).max() <= 20.0
    assert colour_layers(_patches(())).count == 0                              # ground, sky and black only
    # pixels of a further hue (in the widest gap between the bands') on 1% of the coloured pixels are not a
    # layer; on 10% they are
    from mi_amr.visibility import srgb_to_lab
    sh = np.sort(np.asarray(hues) % 360)
    gaps = np.diff(np.append(sh, sh[0] + 360))
    new = (sh[gaps.argmax()] + gaps.max() / 2) % 360
    pixel = _lab_to_srgb8(np.array([[[60.0, 35 * np.cos(np.radians(new)), 35 * np.sin(np.radians(new))]]]),
                          srgb_to_lab)[0, 0]
    ground = np.flatnonzero((np.arange(img.shape[0]) >= img.shape[0] - img.shape[0] // 6)[:, None].repeat(
        img.shape[1], 1).ravel() & (np.arange(img.size // 3) % img.shape[1] >= img.shape[1] // 8))
    for share, more in ((0.01, 0), (0.10, 1)):
        flat = img.copy().reshape(-1, 3)
        n = int(share * got.coloured)
        assert n <= len(ground)
        flat[ground[:n]] = pixel
        assert colour_layers(flat.reshape(img.shape)).count == len(hues) + more


def _yt_default_picture(path, field, res):
    """yt's ``create_scene`` default picture of an output (sRGB uint8), as
    ``sc.save`` writes it."""
    import matplotlib.image as mpimg
    import tempfile
    from pathlib import Path
    yt_ = pytest.importorskip("yt")
    ds = yt_.load(str(path))
    sc = yt_.create_scene(ds, ("gas", field) if ("gas", field) in ds.derived_field_list else field)
    sc.camera.resolution = (res, res)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "yt.png"
        sc.save(str(out), render=True)
        return np.round(mpimg.imread(str(out))[..., :3] * 255).astype(np.uint8)


def _deep_pictures(tmp_path, case, res, spp):
    """The default plan of a gallery output, its colour layers in ``multi``,
    ``emission_absorption`` and ``ray_march`` (``res`` pixels a side,
    ``spp``) and yt's
    ``create_scene`` default's (128 pixels a side)."""
    import gallery_outputs
    from mi_amr.autoscene import plan_scene
    from mi_amr.images import srgb8
    from mi_amr.scene_writer import scene_for
    path, field = gallery_outputs.CASES[case](tmp_path)
    plan = plan_scene(str(path), field)
    ours = {}
    for mode in ("multi", "emission_absorption", "ray_march"):
        scene = mi.load_dict(scene_for(plan, res=res, spp=spp, mode=mode))
        ours[mode] = colour_layers(srgb8(np.array(mi.render(scene, spp=spp, seed=0))))
        del scene
    return plan, ours, colour_layers(_yt_default_picture(path, field, 128)).count


def _check_deep(plan, ours, yt_count, case):
    assert plan.tf.startswith("layers") and plan.layers is not None
    assert len(plan.layers.seen) >= 5 and any(f"predicted {plan.layers}" in n for n in plan.notes), plan.notes
    for mode, got in ours.items():
        assert got.count >= max(5, yt_count - 2), (case, mode, str(got), yt_count, plan.notes)


def test03_an_eight_level_collapse_shows_five_colour_layers(llvm, tmp_path):
    """On an eight-level AMReX collapse (tests/gallery_outputs.py ``deep``,
    read by yt) the default plan predicts at least five layers seen (its
    notes say which), and its picture in ``multi``, ``emission_absorption``
    and ``ray_march`` (64 x 64, 64 spp) shows at least five colour
    layers by `colour_layers`, and never fewer than yt's ``create_scene``
    default on the same output minus two (the fast sibling of test04)."""
    _check_deep(*_deep_pictures(tmp_path, "deep", 64, 64), "deep")


@pytest.mark.slow
@pytest.mark.parametrize("case", ["deep", "cosmology"])
def test04_deep_hierarchies_show_five_colour_layers(llvm, tmp_path, case):
    """test03 on the eight-level collapse and the five-decade Enzo
    cosmology at 128 x 128 (the haloes and filaments of the cosmology
    take a few pixels each)."""
    _check_deep(*_deep_pictures(tmp_path, case, 128, 64), case)


def test05_the_editor_adds_layers_in_one_action(llvm, tmp_path, browser):
    """The viewer's TF editor (the widget's is the same page code): 'add
    layers' with N = 5 puts five layers over the range shown as
    `layer_points` builds them (peaks at (k + 1/2) / 5, opacity rising to
    1, each in its colormap colour), drawn over the histogram, and the view
    renders with them; a viewer of a data file starts from the planned
    layers."""
    pytest.importorskip("starlette")
    from test_view_editor import GROUND_SCENE, _open, _serve, _the_view
    from mi_amr.data.datasets import make_dataset
    from mi_amr.data.io import save_cells
    from mi_amr.view.engine import ViewEngine
    from mi_amr.view.tf_spec import hex_rgb, layer_points
    save_cells(make_dataset("cloud", cells=4000, seed=2), tmp_path / "d.cells")
    (tmp_path / "s.xml").write_text(GROUND_SCENE)
    engine = ViewEngine(tmp_path / "s.xml", res=32, max_spp=2, preview_scale=1.0)
    server = _serve(engine, tmp_path / "out")
    try:
        page, errors = _open(browser, server)
        view = _the_view(engine)
        page.get_by_test_id("colormap").select_option("viridis")
        page.get_by_test_id("layers-n").fill("5")
        page.get_by_test_id("add-layers").click()
        want = layer_points(Layers(n=5))
        wait_until(lambda: len(view.spec.points) == len(want), "the added layers in the view's TF")
        got = view.spec.points
        assert len(got) == len(want), got
        np.testing.assert_allclose([p[:2] for p in got], [p[:2] for p in want], atol=1e-9)
        colours = [(hex_rgb([p[2]])[0], hex_rgb([q[2]])[0]) for p, q in zip(got, want) if len(q) > 2]
        assert max(np.abs(a - b).max() for a, b in colours) < 0.03        # the page's 9 colormap stops
        table = view.spec.table(False)
        peaks = np.flatnonzero((table.rgba[1:-1, 3] > table.rgba[:-2, 3]) & (table.rgba[1:-1, 3] >= table.rgba[2:, 3]))
        assert len(peaks) == 5
        page.wait_for_function("window.viewerStats.lastFrame && window.viewerStats.lastFrame.version >= 1",
                               timeout=HANG_S * 1000)
        assert not errors, errors
        page.close()
    finally:
        server.stop()
        engine.stop()

