"""``mi-amr view``: the editor's state and its checks, the server's token and
its answers to hostile messages, and the page in a real browser (Debian's
chromium driven by Playwright): it loads with the token and is refused
without, its image appears and refines, a drag in the TF editor and an
orbit change it, a snapshot's XML renders to the same picture, two tabs
keep their own views."""

import gc
import json
import struct
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from mi_amr.params import plugin_error
from mi_amr.view.camera import OrbitCamera
from mi_amr.view.protocol import safe_name
from mi_amr.view.tf_spec import TABLE_SIZE, TFSpec, spiky_points

from conftest import HANG_S, dataless_view, wait_until

pytest.importorskip("starlette")
#: Playwright's deadlines, in milliseconds: only a hang reaches them.
HANG_MS = HANG_S * 1000


# ---- the editor's state ------------------------------------------------------------
def test01_tf_spec_tables_and_refusals():
    """A log display over log-stored values is the table itself; a linear
    display over them puts each entry's opacity at 10^x; bad messages are
    refused with the field named and leave the spec as it was."""
    spec = TFSpec([(0.0, 0.0), (0.5, 1.0), (1.0, 0.0)], "viridis", True, (-2.0, 2.0), 5.0)
    tf = spec.table(stored_log=True)
    assert tf.domain == (-2.0, 2.0) and len(tf) == TABLE_SIZE
    u = np.linspace(0, 1, TABLE_SIZE)
    np.testing.assert_allclose(tf.rgba[:, 3], np.interp(u, [0, 0.5, 1], [0, 1, 0]), atol=1e-6)
    lin = TFSpec(spec.points, "viridis", False, (1.0, 100.0), 5.0).table(stored_log=True)
    assert lin.domain == pytest.approx((0.0, 2.0))
    x = np.linspace(0.0, 2.0, TABLE_SIZE)
    np.testing.assert_allclose(lin.rgba[:, 3], np.interp((10 ** x - 1) / 99, [0, 0.5, 1], [0, 1, 0]), atol=1e-6)
    bad = [{"points": [[0, 0]]}, {"points": [[0, 0], [1, float("nan")]]}, {"points": [[0, 0], [2, 1]]},
           {"points": "x"}, {"points": [[0, 0]] * 10000}, {"colormap": "../../etc"}, {"log": "yes"},
           {"range": [1, 1]}, {"range": [0, float("inf")]}, {"range": "a"}, {"density": -1},
           {"density": True}, {"density": "2"}]
    for msg in bad:
        with pytest.raises(ValueError):
            TFSpec.from_message(msg, spec, log_available=True)
    with pytest.raises(ValueError, match="log"):
        TFSpec.from_message({"log": True}, TFSpec(spiky_points(), "plasma", False, (0, 1), 1.0), log_available=False)
    ok = TFSpec.from_message({"points": [[1, 0.5], [0, 0.2]], "density": 3}, spec, log_available=True)
    assert ok.points == [(0.0, 0.2), (1.0, 0.5)] and ok.density == 3.0 and ok.range == spec.range


def test02_orbit_camera_round_trip_and_refusals():
    origin, target, up = np.array([1.5, 1.0, 0.35]), np.array([0.1, -0.2, 0.0]), (0.0, 0.0, 1.0)
    cam = OrbitCamera.looking(origin, target, up, 35.0)
    np.testing.assert_allclose(cam.origin, origin, atol=1e-9)
    moved = cam.from_message({"azimuth": cam.azimuth + 90, "distance": 2.0})
    assert np.linalg.norm(moved.origin - np.asarray(target)) == pytest.approx(2.0)
    assert moved.elevation == pytest.approx(cam.elevation)
    for msg in ({"azimuth": float("nan")}, {"azimuth": "1"}, {"distance": 0}, {"distance": True},
                {"target": [0, 0]}, {"target": ["a", 0, 0]}, {"elevation": 1e9}):
        with pytest.raises(ValueError):
            cam.from_message(msg)


def test03_snapshot_names_stay_in_the_folder():
    assert safe_name("cloud-1_v2.final") == "cloud-1_v2.final"
    for name in ("../x", "/etc/passwd", "a/b", "a\\b", "", ".hidden", "x" * 101, None, "nul\0", "é"):
        with pytest.raises(ValueError):
            safe_name(name)


# ---- a server on small data ----------------------------------------------------------
@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A viewer of a 20,000-cell cloud at 32x32 (16 spp at most: what the
    snapshot checks render again), on loopback, on its own thread."""
    from mi_amr.data.datasets import make_dataset
    from mi_amr.data.io import save_cells
    from mi_amr.view.engine import ViewEngine
    from mi_amr.view.server import ViewServer
    root = tmp_path_factory.mktemp("view")
    src = save_cells(make_dataset("cloud", cells=20000, seed=0), root / "cloud.cells")
    engine = ViewEngine(src, res=32, max_spp=16).start()
    server = ViewServer(engine, out_dir=root / "snapshots", quiet=True).start()
    assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
    yield server, root
    server.stop()
    engine.stop()


def _get(url):
    try:
        with urllib.request.urlopen(url, timeout=HANG_S) as r:
            return r.status, r.read().decode(errors="replace")
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode(errors="replace")


def _frame(ws, timeout=HANG_S):
    """The next binary frame's header (JSON replies before it are returned too)."""
    replies, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = ws.recv(timeout=deadline - time.monotonic())
        if isinstance(m, bytes):
            n = struct.unpack(">I", m[:4])[0]
            ws.send(json.dumps({"type": "ack"}))
            return json.loads(m[4:4 + n]), replies
        replies.append(json.loads(m))
    raise AssertionError("no frame")


def test04_every_request_needs_the_token(served):
    from websockets.exceptions import ConnectionClosed, InvalidStatus
    from websockets.sync.client import connect
    server, _ = served
    base = f"http://127.0.0.1:{server.port}"
    assert server.host == "127.0.0.1"
    assert _get(f"{base}/")[0] == 403
    assert _get(f"{base}/?token=wrong")[0] == 403
    assert _get(f"{base}/static/viewer.js")[0] == 200        # code, no data: public (the page carries the token)
    assert _get(f"{base}/static/index.html")[0] == 404       # the page only with its token
    status, body = _get(server.url)
    assert status == 200 and 'data-testid="view"' in body and f'content="{server.token}"' in body
    with pytest.raises((ConnectionClosed, InvalidStatus)):
        with connect(f"ws://127.0.0.1:{server.port}/ws?token=wrong") as ws:
            ws.recv(timeout=HANG_S)


def test05_hostile_messages_get_errors_and_the_server_goes_on(served):
    """Binary, not JSON, no object, unknown type, oversized, NaN camera,
    thousands of TF points, a snapshot name that leaves the folder: an
    error reply each, and the view still renders after a valid change."""
    from websockets.sync.client import connect
    server, root = served
    with connect(f"ws://127.0.0.1:{server.port}/ws?token={server.token}", max_size=2**24) as ws:
        header, replies = _frame(ws)
        hello = next(r for r in replies if r["type"] == "hello")
        assert hello["log_available"] in (True, False) and hello["size"] == [32, 32]
        assert hello["colormap_stops"]["viridis"][0] == "#440154"         # matplotlib's own colours
        hostile = [b"\x00\x01binary", "not json {", "[1, 2]", json.dumps({"type": "reboot"}), "x" * 100_000,
                   json.dumps({"type": "camera", "azimuth": "NaN"}), '{"type": "camera", "distance": NaN}',
                   json.dumps({"type": "tf", "points": [[0, 0]] * 5000}),
                   json.dumps({"type": "snapshot", "name": "../../escape"}),
                   json.dumps({"type": "snapshot", "name": "/tmp/abs"}), json.dumps({"type": "denoise", "on": 1})]
        for h in hostile:
            ws.send(h)
            while True:
                m = ws.recv(timeout=HANG_S)
                if isinstance(m, bytes):
                    ws.send(json.dumps({"type": "ack"}))
                    continue
                reply = json.loads(m)
                if reply["type"] == "error":
                    break
            assert reply["message"], h
        assert not (root / "escape.xml").exists() and not Path("/tmp/abs.xml").exists()
        version_before = header["version"]
        ws.send(json.dumps({"type": "camera", "azimuth": hello["camera"]["azimuth"] + 20}))
        newer = wait_until(lambda: [h for h in [_frame(ws)[0]] if h["version"] != version_before],
                           "frame of the new camera")
        assert newer[0]["version"] == version_before + 1


# ---- the page in a real browser ----------------------------------------------------------


def _canvas(page) -> np.ndarray:
    data = page.evaluate("""() => { const c = document.querySelector('[data-testid=view]');
        return Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data); }""")
    return np.array(data, np.float64).reshape(-1, 4)[:, :3]


def _stats(page):
    return page.evaluate("window.viewerStats")


def _changes(page, action):
    """Run ``action``; once a frame of the new state is on screen, how much
    the picture changed: mean |delta| in 8-bit units. (How soon it came is
    ``python -m mi_amr.bench --view``'s "change -> frame of it".)"""
    before, version0 = _canvas(page), _stats(page)["lastFrame"]["version"]
    action()
    page.wait_for_function(f"window.viewerStats.lastFrame.version > {version0}", timeout=HANG_MS)
    page.wait_for_timeout(50)
    return float(np.abs(_canvas(page) - before).mean())


def test06_the_page_in_a_browser(served, browser):
    """Refused without the token; with it an image appears and refines (the
    spp counter rises); a TF-editor drag and an orbit each bring a frame
    of the new state that changes the picture; a snapshot writes EXR, PNG and XML, and the XML
    renders to the same picture within noise."""
    server, root = served
    page = browser.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"http://127.0.0.1:{server.port}/")
    assert "403" in page.content()
    page.goto(server.url)
    page.wait_for_function("window.viewerStats && window.viewerStats.frames > 0", timeout=HANG_MS)
    assert _canvas(page).mean() > 1.0                      # not black: an image appeared
    page.wait_for_function("window.viewerStats.lastFrame.spp >= 8 && !window.viewerStats.lastFrame.preview",
                           timeout=HANG_MS)
    assert "spp" in page.get_by_test_id("spp").inner_text()
    for testid in ("tf-editor", "density", "colormap", "log", "snapshot"):
        assert page.get_by_test_id(testid).count() == 1

    editor = page.get_by_test_id("tf-editor").bounding_box()      # spiky: the tallest peak at u = 0.8

    def drag_tf_point():
        x = editor["x"] + 8 + 0.8 * (editor["width"] - 16)
        y_peak = editor["y"] + 8                          # alpha 1 at the top of the plot
        page.mouse.move(x, y_peak)
        page.mouse.down()
        page.mouse.move(x, y_peak + 0.6 * editor["height"], steps=5)
        page.mouse.up()
    delta = _changes(page, drag_tf_point)
    assert delta > 0.5, delta

    view = page.get_by_test_id("view").bounding_box()

    def orbit():
        page.mouse.move(view["x"] + 100, view["y"] + 100)
        page.mouse.down()
        page.mouse.move(view["x"] + 220, view["y"] + 120, steps=6)
        page.mouse.up()
    delta = _changes(page, orbit)
    assert delta > 0.5, delta

    page.wait_for_function("window.viewerStats.lastFrame.spp >= 16 && !window.viewerStats.lastFrame.preview",
                           timeout=HANG_MS)
    page.get_by_test_id("snapshot-name").fill("shot")
    page.get_by_test_id("snapshot").click()
    page.wait_for_function("window.viewerStats.snapshots.length > 0", timeout=HANG_MS)
    snap = _stats(page)["snapshots"][0]
    out = root / "snapshots"
    for ext in (".exr", ".png", ".xml", ".tf.json"):
        assert (out / f"shot{ext}").is_file()
    assert {Path(f).name for f in snap["files"]} == {"shot.exr", "shot.png", "shot.xml", "shot.tf.json"}
    assert errors == [] and _stats(page)["errors"] == []
    page.close()
    _same_picture(out / "shot.exr", out / "shot.xml", snap["spp"])


def _same_picture(exr, xml, spp, passes=16, block=8):
    """The snapshot's EXR (one image of ``spp`` samples) against ``passes``
    renders of its XML at the same spp: per 8x8 block, |z| < 6 with the
    pass-to-pass variance (Student's t with 15 degrees of freedom: P(|t| > 6)
    is 2.4e-5 per block, a false alarm about 0.2% over 64 blocks)."""
    import mitsuba as mi

    from mi_amr.testing import render_passes
    from mi_amr.images import read_exr
    mi.set_variant("llvm_ad_rgb")
    from mi_amr.view.engine import JIT_LOCK
    with JIT_LOCK:             # a viewer may be rendering on its thread
        scene = mi.load_file(str(xml))
        ref = render_passes(scene, passes, spp, seed0=1000)
        del scene              # collected here, not inside another thread's frozen pass
        gc.collect()
    img = read_exr(exr)[..., :3].astype(np.float64)
    assert img.shape == ref.shape[1:]

    def blocks(a):
        h, w = a.shape[-3] // block, a.shape[-2] // block
        return a[..., :h * block, :w * block, :].reshape(*a.shape[:-3], h, block, w, block, 3).mean(axis=(-4, -2, -1))
    b_img, b_ref = blocks(img), blocks(ref)
    var = b_ref.var(axis=0, ddof=1)
    z = (b_img - b_ref.mean(axis=0)) / np.sqrt(var * (1 + 1 / passes) + 1e-12)
    assert np.abs(z).max() < 6.0, (np.abs(z).max(), z.round(1))


def test07_two_tabs_keep_their_own_views(served, browser):
    """Tab A orbits while tab B refines: B's camera and version stay, and
    B's accumulation holds only its own camera (its snapshot renders to the
    same picture), though both share one scene."""
    server, root = served
    a, b = browser.new_page(), browser.new_page()
    for p in (a, b):
        p.goto(server.url)
        p.wait_for_function("window.viewerStats.lastFrame && !window.viewerStats.lastFrame.preview", timeout=HANG_MS)
    b_version = _stats(b)["lastFrame"]["version"]
    box = a.get_by_test_id("view").bounding_box()
    a.mouse.move(box["x"] + 50, box["y"] + 50)
    a.mouse.down()
    a.mouse.move(box["x"] + 250, box["y"] + 60, steps=8)
    a.mouse.up()
    a.wait_for_function("window.viewerStats.lastFrame.version > 0", timeout=HANG_MS)
    b.wait_for_function("window.viewerStats.lastFrame.spp >= 16 && !window.viewerStats.lastFrame.preview",
                        timeout=HANG_MS)
    assert _stats(b)["lastFrame"]["version"] == b_version
    b.get_by_test_id("snapshot-name").fill("tab-b")
    b.get_by_test_id("snapshot").click()
    b.wait_for_function("window.viewerStats.snapshots.length > 0", timeout=HANG_MS)
    spp = _stats(b)["snapshots"][0]["spp"]
    a.close()
    b.close()
    _same_picture(root / "snapshots" / "tab-b.exr", root / "snapshots" / "tab-b.xml", spp)


def _refined_snapshot(engine, spp: int, out, name: str):
    """``(files, frame headers)``: a view of ``engine`` (loaded) refined to
    ``spp``, then its snapshot's four files."""
    assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
    frames = []
    view = engine.open_view(lambda header, jpeg: frames.append(header))
    wait_until(lambda: frames and frames[-1]["spp"] >= spp, f"frame of {spp} spp")
    return engine.snapshot(view, out, name), frames


@pytest.mark.slow
def test08_a_yt_data_set_in_the_viewer(tmp_path):
    """An Enzo output through yt (``mi-amr view DIR --field Density``): the
    view renders, and its snapshot with ``embed_data`` writes the data once
    as .amrb beside an XML that renders to the same picture."""
    pytest.importorskip("yt")
    from amr_formats import write_enzo
    from mi_amr.view.engine import ViewEngine
    rng = np.random.default_rng(3)
    x, y, z = np.meshgrid(*[np.arange(16)] * 3, indexing="ij")
    top = 1.0 + 4.0 * np.exp(-((x - 9) ** 2 + (y - 7) ** 2 + (z - 8) ** 2) / 30.0) + 0.1 * rng.random((16, 16, 16))
    path = write_enzo(tmp_path / "DD0003", "DD0003", top, [((8, 8, 8), 3.0 + 2.0 * rng.random((8, 8, 8)))])
    engine = ViewEngine(path, "Density", res=32, max_spp=16, embed_data=True).start()
    try:
        files, frames = _refined_snapshot(engine, 16, tmp_path / "out", "enzo")
        assert frames[-1]["spp"] == 16 and frames[-1]["width"] == 32
    finally:
        engine.stop()
    assert [f.name for f in files] == ["enzo.exr", "enzo.png", "enzo.xml", "enzo.tf.json"]
    assert list((tmp_path / "out").glob("*.amrb")), "the yt data were not written for the XML"
    _same_picture(files[0], files[2], 16, block=8)


def test09_notebook_frame_and_command_line(served, tmp_path, capsys):
    """``mi_amr.view.notebook`` shows the same page (an IFrame of a served
    URL); ``mi-amr view`` names a missing file; ``mi-amr render --denoise``
    writes the denoised image beside the noisy one."""
    pytest.importorskip("IPython")
    from mi_amr.tools.cli import main
    from mi_amr.images import read_exr
    from mi_amr.view import notebook
    _, root = served
    frame = notebook(root / "cloud.cells", res=32, out_dir=tmp_path)
    try:
        assert frame.engine.ready.wait(HANG_S)
        status, body = _get(frame.src)
        assert status == 200 and 'data-testid="tf-editor"' in body and "127.0.0.1" in frame.src
    finally:
        frame.server.stop()
        frame.engine.stop()
    assert main(["view", str(tmp_path / "missing.cells"), "--no-browser"]) == 2
    assert "missing.cells" in capsys.readouterr().err
    scene = Path(__file__).parents[1] / "scenes" / "blocks.xml"
    out = tmp_path / "b.exr"
    from mi_amr.view.engine import JIT_LOCK
    with JIT_LOCK:             # the served viewer may be rendering on its thread
        assert main(["render", str(scene), "-o", str(out), "--spp", "4", "-D", "res=32", "--denoise", "-q"]) == 0
        gc.collect()
    noisy, clean = read_exr(out), read_exr(tmp_path / "b-denoised.exr")
    assert clean.shape == noisy.shape[:2] + (3,) and np.isfinite(clean).all()
    assert abs(clean.mean() - noisy[..., :3].mean()) < 0.1 * noisy[..., :3].mean()
    # the denoiser smooths: neighbouring pixels differ less than in the noisy image
    assert np.abs(np.diff(clean, axis=1)).mean() < np.abs(np.diff(noisy[..., :3], axis=1)).mean()


@pytest.mark.slow
def test10_an_xml_scene_in_the_viewer(tmp_path):
    """``mi-amr view scenes/blocks.xml``: the scene's own camera, colours
    and density to start with; after an orbit and a TF change the snapshot
    is the source XML with the new camera and TF (its relative data path
    still found), rendering to the same picture."""
    from mi_amr.view.engine import ViewEngine
    scene = Path(__file__).parents[1] / "scenes" / "blocks.xml"
    engine = ViewEngine(scene, res=32, max_spp=16).start()
    try:
        assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
        assert "scene" in engine.colormaps and engine.initial_spec.colormap == "scene"
        frames = []
        view = engine.open_view(lambda header, jpeg: frames.append(header))
        engine.change(view, {"type": "camera", "azimuth": view.camera.azimuth + 40, "elevation": 20})
        engine.change(view, {"type": "tf", "density": view.spec.density * 0.5, "colormap": "viridis"})
        wait_until(lambda: frames and frames[-1]["spp"] >= 16 and frames[-1]["version"] == 2,
                   "frame of 16 spp of the new view")
        assert frames[-1]["spp"] == 16
        files = engine.snapshot(view, tmp_path, "blocks")
    finally:
        engine.stop()
    text = files[2].read_text()
    assert "lookat" in text and "blocks.tf.json" in text and "data/blocks.cells" in text
    _same_picture(files[0], files[2], 16, block=8)


def test11_the_editor_histogram_is_the_volume_weighted_one():
    """Re-binned from the fine histogram, the editor's bins hold the
    volume-weighted shares of direct counting (within one fine bin's mass
    at each edge), in linear and log10 display over log-stored values."""
    from mi_amr.data.statistics import cells_and_weights
    from mi_amr.data.blocks import BlockVolume
    from mi_amr.data.datasets import make_dataset
    from mi_amr.data.transform import apply_value_transform
    from mi_amr.view.tf_spec import Histogram
    vol, _ = apply_value_transform(BlockVolume.from_cells(make_dataset("cloud", cells=20000, seed=4)), "log10")
    hist = Histogram(vol)
    v = np.concatenate([a for a, _ in cells_and_weights(vol)])
    w = np.concatenate([b for _, b in cells_and_weights(vol)])
    lo, hi = np.quantile(v, [0.2, 0.9])
    for spec, x in ((TFSpec(log=True, range=(lo, hi)), v), (TFSpec(log=False, range=(10 ** lo, 10 ** hi)), 10 ** v)):
        got = np.array(hist.shares(spec, stored_log=True, bins=32))
        direct = np.histogram(x, bins=32, range=spec.range, weights=w)[0] / w.sum()
        assert np.abs(got - direct).max() < 0.01, np.abs(got - direct).max()
        assert got.sum() == pytest.approx(direct.sum(), abs=0.01)


def test12_a_missing_denoiser_is_said_not_hidden(monkeypatch, tmp_path, capsys):
    """Without mitsuba-oidn the page is told why (and the denoise switch is
    refused with that reason), and ``mi-amr render --denoise`` stops before
    rendering with one line naming the extra."""
    import mi_amr.view.engine as eng
    from mi_amr.tools.cli import main
    monkeypatch.setattr(eng, "denoiser", lambda: (None, "denoising needs mitsuba-oidn: pip install 'mi-amr[view]'"))
    engine, view = dataless_view(64, 8)
    hello = engine.describe(view)
    assert hello["denoiser"] is False and "mi-amr[view]" in hello["denoiser_missing"] and hello["denoise"] is False
    with pytest.raises(ValueError, match="mitsuba-oidn"):
        engine.change(view, {"type": "denoise", "on": True})
    scene = Path(__file__).parents[1] / "scenes" / "blocks.xml"
    assert main(["render", str(scene), "-o", str(tmp_path / "x.exr"), "--denoise"]) == 2
    assert "mitsuba-oidn" in capsys.readouterr().err and not (tmp_path / "x.exr").exists()


# ---- the wire protocol ------------------------------------------------------------------
def test13_every_message_round_trips():
    """Each page message parses from its JSON back to itself; each server
    message is the JSON the page reads (the wire format of before)."""
    from mi_amr.view import protocol as p
    page = [p.CameraChange(10.0, -20.0, 2.5, (0.1, 0.2, 0.3)), p.CameraChange(azimuth=5.0), p.CameraChange(),
            p.TFChange(((0.0, 0.0), (0.5, 1.0), (1.0, 0.25)), "viridis", True, (-2.0, 1.5), 4.0),
            p.TFChange(density=0.5), p.DenoiseChange(True), p.DenoiseChange(False), p.HistogramRequest(),
            p.SnapshotRequest("shot-1.v2"), p.Ack(), p.ModeChange("single"), p.HybridChange(False),
            p.IsoChange((0.25, 3e-27), True), p.IsoChange(only=False)]
    assert {type(m) for m in page} == set(p.PageMessage.__args__)
    for msg in page:
        assert p.parse(p.dumps(msg)) == msg
    assert p.to_json(p.CameraChange(azimuth=5.0)) == {"type": "camera", "azimuth": 5.0}
    cam, spec = OrbitCamera.looking((2, 0, 0), (0, 0, 0), (0, 0, 1), 35.0), TFSpec()
    wire = [
        (p.Status("loading", "reading x", 3, None), {"type": "status", "state": "loading", "desc": "reading x",
                                                      "done": 3, "total": None}),
        (p.Hello(7, cam, spec, ("plasma",), True, False, "no oidn", False, (32, 16), 64, "d.cells",
                 {"plasma": ["#0d0887"]}),
         {"type": "hello", "view": 7, "camera": cam.to_json(), "tf": spec.to_json(), "colormaps": ["plasma"],
          "log_available": True, "denoiser": False, "denoiser_missing": "no oidn", "denoise": False,
          "size": [32, 16], "max_spp": 64, "data": "d.cells", "colormap_stops": {"plasma": ["#0d0887"]}}),
        (p.HistogramReply((0.25, 0.75), (0.0, 1.0), False),
         {"type": "histogram", "counts": [0.25, 0.75], "range": [0.0, 1.0], "log": False}),
        (p.Frame(3, 8, True, False, 32, 16, 12.5, 64),
         {"type": "frame", "version": 3, "spp": 8, "denoised": True, "preview": False, "width": 32, "height": 16,
          "render_ms": 12.5, "max_spp": 64}),
        (p.SnapshotDone(("/o/a.exr", "/o/a.xml"), 16), {"type": "snapshot", "files": ["/o/a.exr", "/o/a.xml"],
                                                        "spp": 16}),
        (p.Error("bad", "tf"), {"type": "error", "message": "bad", "about": "tf"}),
        (p.Error("not JSON"), {"type": "error", "message": "not JSON"}),
    ]
    assert {type(m) for m, _ in wire} == set(p.ServerMessage.__args__)
    for msg, expected in wire:
        assert json.loads(p.dumps(msg)) == expected
        assert all(msg[k] == v for k, v in expected.items())          # read as the page reads it


def test14_bad_messages_get_the_errors_of_before():
    """Binary, oversized, not JSON, not an object, an unknown type, a field
    a message lacks, wrong types, NaN and Inf: one `ProtocolError` each,
    worded as the server's replies were, and the server's reply to each is
    that error (naming the message type once it is known)."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from mi_amr.view import protocol as p
    from mi_amr.view.server import _handle
    cases = [
        (b"\x00\x01binary", "messages must be JSON text, not binary", None),
        ("x" * 100_000, f"message too long (100000 > {p.MAX_MESSAGE} bytes)", None),
        ("not json {", "not JSON: Expecting value: line 1 column 1 (char 0)", None),
        ("[1, 2]", "a message is a JSON object with a 'type'", None),
        (json.dumps({"type": "reboot"}), "unknown message type 'reboot'", None),
        (json.dumps({"azimuth": 3}), "unknown message type None", None),
        (json.dumps({"type": ["camera"]}), "unknown message type ['camera']", None),
        (json.dumps({"type": "camera", "azimuth": "NaN"}), "azimuth: a finite number in [-1000000.0, 1000000.0]",
         "camera"),
        ('{"type": "camera", "azimuth": NaN}', "azimuth: a finite number in [-1000000.0, 1000000.0]", "camera"),
        ('{"type": "camera", "azimuth": 1e999}', "azimuth: a finite number in [-1000000.0, 1000000.0]", "camera"),
        (json.dumps({"type": "camera", "azimuth": 10 ** 400}), "azimuth: a finite number in [-1000000.0, 1000000.0]",
         "camera"),
        (json.dumps({"type": "camera", "elevation": True}), "elevation: a finite number in [-90, 90]", "camera"),
        ('{"type": "camera", "distance": Infinity}', "distance: a finite number above 0", "camera"),
        (json.dumps({"type": "camera", "target": [0, 0]}), "target: three numbers", "camera"),
        ('{"type": "camera", "target": [0, 0, NaN]}', "target: three finite numbers", "camera"),
        (json.dumps({"type": "camera", "zoom": 2}), "camera: no field(s) 'zoom' "
         "(fields: azimuth, distance, elevation, target)", "camera"),
        (json.dumps({"type": "tf", "points": [[0, 0]] * 5000}), "points: a list of 2 to 256 [u, alpha] pairs", "tf"),
        (json.dumps({"type": "tf", "points": [[0, 0], ["1", 1]]}), "points: a list of [u, alpha] number pairs", "tf"),
        ('{"type": "tf", "points": [[0, 0], [1, NaN]]}', "points: a list of finite [u, alpha] pairs", "tf"),
        (json.dumps({"type": "tf", "points": [[0, 0], [2, 1]]}), "points: u and alpha must lie in [0, 1]", "tf"),
        (json.dumps({"type": "tf", "log": "yes"}), "log: true or false", "tf"),
        (json.dumps({"type": "tf", "range": "a"}), "range: [lo, hi], two numbers", "tf"),
        ('{"type": "tf", "range": [0, Infinity]}', "range: finite, with lo < hi", "tf"),
        (json.dumps({"type": "tf", "range": [1, 1]}), "range: finite, with lo < hi", "tf"),
        (json.dumps({"type": "tf", "density": True}), "density: a positive number", "tf"),
        (json.dumps({"type": "tf", "density": -1}), "density: a positive number", "tf"),
        (json.dumps({"type": "tf", "colormap": 3}), "colormap: the name of a colormap", "tf"),
        (json.dumps({"type": "denoise", "on": 1}), "denoise: 'on' must be true or false", "denoise"),
        (json.dumps({"type": "denoise"}), "denoise: 'on' must be true or false", "denoise"),
        (json.dumps({"type": "snapshot", "name": "../../escape"}),
         "snapshot name '../../escape': letters, digits, '-', '_' and '.' only (not leading), no folders", "snapshot"),
        (json.dumps({"type": "snapshot"}), "snapshot name: 1 to 100 characters", "snapshot"),
        (json.dumps({"type": "ack", "spp": 3}), "ack: no field(s) 'spp' (fields: none)", "ack"),
    ]
    for text, message, about in cases:
        with pytest.raises(p.ProtocolError) as e:
            p.parse(text)
        assert (str(e.value), e.value.about) == (message, about), text
        wire = {"text": text} if isinstance(text, str) else {"bytes": text}
        with ThreadPoolExecutor(1) as pool:          # a loop of its own (Playwright's may run on this thread)
            reply = pool.submit(asyncio.run, _handle(wire, None, None, None, None, None)).result()
        assert p.to_json(reply) == {"type": "error", "message": message, **({"about": about} if about else {})}


def test15_an_xml_scene_keeps_its_own_tf(tmp_path):
    """An XML scene's TF table (7 uneven entries) reaches the editor entry by
    entry and the medium as it is, also after the page sends the TF back
    with a new density; the snapshot writes the same table values. A table
    longer than the editor takes (300 entries) starts the editor from 65
    samples, the medium still from the table itself."""
    from mi_amr.data.datasets import make_dataset
    from mi_amr.data.io import save_cells
    from mi_amr.transfer.function import TransferFunction
    from mi_amr.view import protocol as p
    from mi_amr.view.engine import JIT_LOCK, ViewEngine
    from mi_amr.view.scene import EDITOR_POINTS, LoadedScene, scene_spec
    rgba = [[0.1, 0.2, 0.3, 0.0], [0.9, 0.1, 0.1, 0.137], [0.2, 0.8, 0.1, 0.0123], [0.3, 0.3, 0.9, 0.91],
            [0.5, 0.5, 0.5, 0.333], [1.0, 0.7, 0.0, 0.05], [0.0, 0.0, 0.0, 0.777]]
    (tmp_path / "tf7.json").write_text(json.dumps({"domain": [0.015, 1.7], "rgba": rgba}))
    save_cells(make_dataset("cloud", cells=5000, seed=1), tmp_path / "d.cells")
    (tmp_path / "s.xml").write_text(f"""<scene version="3.0.0">
    <integrator type="volpath"><integer name="max_depth" value="8"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="35"/>
        <transform name="to_world"><lookat origin="1.8, 1.3, 2.6" target="0.5, 0.5, 0.5" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="0.8"/></emitter>
    <medium type="amr" id="m">
        <string name="filename" value="d.cells"/>
        <string name="transfer_function" value="{tmp_path / 'tf7.json'}"/>
        <float name="density_scale" value="20"/>
    </medium>
    <shape type="cube">
        <transform name="to_world"><scale value="0.5"/><translate value="0.5, 0.5, 0.5"/></transform>
        <bsdf type="null"/><ref name="interior" id="m"/>
    </shape>
</scene>""")
    source = TransferFunction(rgba, (0.015, 1.7))
    engine = ViewEngine(tmp_path / "s.xml", res=16, max_spp=2).start()
    try:
        assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
        spec = engine.initial_spec
        assert spec.points == list(zip(np.linspace(0, 1, 7).tolist(), source.rgba[:, 3].tolist()))
        assert spec.range == (0.015, 1.7) and spec.colormap == "scene"
        frames = []
        view = engine.open_view(lambda header, jpeg: frames.append(header))
        hello = engine.describe(view)
        # the page sends its TF back as it got it, with a new density (the slider)
        text = json.dumps({"type": "tf", **json.loads(p.dumps(hello))["tf"], "density": 7.5})
        assert engine.change(view, p.parse(text)) is False
        assert view.spec.density == 7.5 and engine.loaded.table(view.spec) is engine.loaded.scene_tf
        wait_until(lambda: frames and frames[-1]["spp"] >= 2 and frames[-1]["version"] == 1,
                   "frame of 2 spp of the new density")
        with JIT_LOCK:
            np.testing.assert_array_equal(engine.loaded.medium.tf.rgba, source.rgba)
            assert engine.loaded.medium.tf.domain == source.domain
        files = engine.snapshot(view, tmp_path / "out", "kept")
    finally:
        engine.stop()
    written = json.loads(files[3].read_text())
    assert written["domain"] == [0.015, 1.7]
    np.testing.assert_allclose(written["rgba"], rgba, atol=1e-7, rtol=0)
    assert 'name="density_scale" value="7.5"' in files[2].read_text()
    long = TransferFunction(np.linspace(0, 1, 300)[:, None] * [1, 0.5, 0.25, 1], (0.0, 2.0))
    spec = scene_spec(long, False, 1.0)
    assert len(spec.points) == EDITOR_POINTS
    s = LoadedScene("x.xml", None, "x", [16, 16], OrbitCamera.looking((2, 0, 0), (0, 0, 0), (0, 0, 1), 35.0),
                    spec, ("scene",), False, scene_rgb=long.rgba[:, :3], scene_tf=long)
    assert s.table(spec) is long and s.table(TFSpec(spec.points, "scene", False, (0.0, 2.0), 3.0)) is long
    edited = TFSpec([(0.0, 0.0), (1.0, 1.0)], "scene", False, (0.0, 2.0), 1.0)
    assert s.table(edited) is not long and len(s.table(edited)) == TABLE_SIZE


def test16_the_log10_toggle_plans_range_and_density_again(tmp_path):
    """Data planned linear (within a decade, all positive: log10 stored):
    ticking log10 gives the range and density the plan chooses for a log10
    display (`planned_display`), not the linear plan's density; the next
    histogram carries the density to the page once; unticking gives the
    linear plan back (range and density within the table's discretisation).
    A density sent with the toggle is the user's and is kept."""
    import mi_amr
    from mi_amr.autoscene import planned_display
    from mi_amr.data.io import write_exabricks
    from mi_amr.view.engine import ViewEngine
    z, y, x = np.meshgrid(*[np.linspace(0, 1, 16)] * 3, indexing="ij")
    v = 5.5 + 4.5 * np.sin(2 * np.pi * x) * np.cos(2 * np.pi * y) * np.sin(np.pi * z)
    path, _ = write_exabricks(mi_amr.dense_to_amr(v.astype(np.float32), 0.0, 1), tmp_path / "waves.cells")
    engine = ViewEngine(path, res=16, max_spp=2).start()
    try:
        assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
        view = engine.open_view(lambda header, jpeg: None)
        linear = view.spec
        assert not linear.log and engine.loaded.stored_log
        lo, hi = linear.range
        assert engine.change(view, {"type": "tf", "log": True, "range": [np.log10(lo), np.log10(hi)]})
        logged = view.spec
        loaded = engine.loaded
        want_range, want_density = planned_display(
            loaded.plan.data, loaded.medium.volume, True,
            lambda r: TFSpec(logged.points, logged.colormap, True, tuple(r), 1.0).table(True))
        assert logged.log and logged.range == pytest.approx(want_range) and logged.density == pytest.approx(want_density)
        assert abs(np.log(logged.density / linear.density)) > 0.1
        reply = engine.histogram(view)
        assert reply.density == pytest.approx(logged.density) and engine.histogram(view).density is None
        engine.change(view, {"type": "tf", "log": False, "range": [lo, hi]})
        back = view.spec
        assert back.range == pytest.approx(linear.range, rel=1e-6)
        assert back.density == pytest.approx(linear.density, rel=0.03)
        engine.change(view, {"type": "tf", "log": True, "range": [0.0, 1.0], "density": 7.0})
        assert view.spec.density == 7.0 and view.spec.range == (0.0, 1.0)
    finally:
        engine.stop()


def test17_the_field_selector_shows_the_field_the_user_named(tmp_path):
    """``mi-amr view DD0003 --field density`` where yt's on-disk name is
    ``enzo,Density``: the editor's field is that entry of the selector (it
    was blank: the names differ in case), and the picture is planned."""
    pytest.importorskip("yt")
    from amr_formats import write_enzo
    from mi_amr.view.engine import ViewEngine
    x, y, z = np.meshgrid(*[np.arange(8)] * 3, indexing="ij")
    path = write_enzo(tmp_path / "DD0003", "DD0003", 1.0 + np.exp(-((x - 4) ** 2 + (y - 3) ** 2 + z ** 2) / 9.0), [])
    engine = ViewEngine(path, "density", res=16, max_spp=2).start()
    try:
        assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
        extras = engine._editor_extras()
        assert extras["field"] == "enzo,Density" and extras["field"] in extras["fields"]
    finally:
        engine.stop()


def test18_a_snapshot_of_yt_data_names_them_and_checks_them(tmp_path):
    """By default a snapshot of data yt loads copies nothing: its XML names
    the output, the field and the data's checksum, renders to the snapshot's
    picture, and once the output is written again with other values the
    XML is refused in one line naming data_checksum (not rendered from the
    wrong data)."""
    pytest.importorskip("yt")
    import mitsuba as mi
    from amr_formats import write_enzo
    from mi_amr.view.engine import ViewEngine
    x, y, z = np.meshgrid(*[np.arange(8)] * 3, indexing="ij")
    top = 1.0 + 4.0 * np.exp(-((x - 4) ** 2 + (y - 3) ** 2 + (z - 4) ** 2) / 6.0)
    path = write_enzo(tmp_path / "DD0003", "DD0003", top, [])
    engine = ViewEngine(path, "density", res=16, max_spp=4).start()
    try:
        files, _ = _refined_snapshot(engine, 4, tmp_path / "out", "enzo")
    finally:
        engine.stop()
    assert not list((tmp_path / "out").glob("*.amrb")) and not list((tmp_path / "out").glob("*.cells"))
    text = files[2].read_text()
    assert str(path.resolve()) in text and 'name="field"' in text and 'name="data_checksum"' in text
    _same_picture(files[0], files[2], 4, block=8)
    write_enzo(tmp_path / "DD0003", "DD0003", 2.0 * top, [])           # the output written again
    with pytest.raises(Exception) as e:
        mi.load_file(str(files[2]))
    line = plugin_error(str(e.value))
    assert "\n" not in line and "data_checksum" in line and "DD0003" in line, line
