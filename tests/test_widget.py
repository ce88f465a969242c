"""The viewer in a notebook (`mi_amr.view.widget.ViewWidget`, ``sc.show()``):
the page code bundled from the viewer's own files; the widget's message
handling without a browser (frames out as binary buffers, page messages
into the view and the traits, traits set from Python into the view, the
DataScene rendering the widget's view); and, as a user meets it, JupyterLab
in chromium: a picture in the cell output, a drag that the kernel sees, a
TF set from Python that changes the picture, no port opened by the kernel."""

import json
import shutil
import subprocess
import time

import numpy as np
import pytest

import mi_amr
from conftest import HANG_S, wait_until

pytest.importorskip("anywidget")
from mi_amr.view.widget import ViewWidget, page_module  # noqa: E402


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    """The viewer tests' 20,000-cell cloud (the same kernels: 32x32, 16 spp at most)."""
    from mi_amr.data.datasets import make_dataset
    from mi_amr.data.io import save_cells
    return save_cells(make_dataset("cloud", cells=20000, seed=0), tmp_path_factory.mktemp("widget") / "cloud.cells")


class Recorded(ViewWidget):
    """The widget with what it sends over the comm channel kept, in order."""

    def send(self, content, buffers=None):
        self.__dict__.setdefault("sent", []).append((content, buffers))


def _wait_for(w, test, timeout=HANG_S):
    """What ``w`` sent that passes ``test`` (its content), once something has."""
    return wait_until(lambda: [(c, b) for c, b in list(w.__dict__.get("sent", [])) if test(c)],
                      "message of the kind sent", timeout)


def test01_the_page_code_is_the_viewers_own():
    """One copy: the widget's module carries viewer.js, tf_editor.js and
    camera.js verbatim (their imports bound to the bundled modules), the
    markup of index.html and viewer.css; no import and no URL remain, and
    node parses it as an ES module."""
    from mi_amr.view.widget import STATIC
    esm = page_module()
    for name in ("viewer.js", "tf_editor.js", "camera.js"):
        lines = [ln for ln in (STATIC / name).read_text().splitlines() if ln.strip() and not ln.startswith(("import", "export"))]
        assert all(ln in esm for ln in lines), name
    assert esm.count("function createTfEditor(") == 1 and esm.count("function startViewer(") == 1
    assert 'data-testid=\\"view\\"' in esm and "mi-amr-root" in esm
    assert not [ln for ln in esm.splitlines() if ln.startswith("import ")]
    assert "export default { render }" in esm
    node = shutil.which("node")
    assert node, "node is missing: make setup installs it (Debian's nodejs)"
    r = subprocess.run([node, "--input-type=module", "--check"], input=esm, capture_output=True, text=True,
                       timeout=HANG_S)
    assert r.returncode == 0, r.stderr
    broken = esm.replace("export default { render }", "export default { render ")      # the check can fail
    r = subprocess.run([node, "--input-type=module", "--check"], input=broken, capture_output=True, text=True,
                       timeout=HANG_S)
    assert r.returncode != 0 and "SyntaxError" in r.stderr


def test02_messages_frames_and_traits(llvm, cloud):
    """Frames leave as one JPEG buffer each behind a Frame header, the next
    waiting for the page's acks; a page's camera change reaches the traits
    and the DataScene; traits set from Python change the view (the page is
    sent a new hello), bad values and bad messages are refused in one line
    with nothing changed; ``sc.render()`` then renders the widget's view:
    per 8x8 block within |z| < 6 of the engine's own accumulation, which a
    render of the view before the drag is not."""
    sc = mi_amr.scene(str(cloud), res=32, spp=16)
    w = Recorded(sc, res=32, max_spp=16)
    try:
        w.wait(HANG_S)
        content, buffers = _wait_for(w, lambda c: c.get("type") == "frame")[0]
        header = content["header"]
        assert header["type"] == "frame" and header["width"] > 0 and len(buffers) == 1
        assert bytes(buffers[0][:3]) == b"\xff\xd8\xff"                 # JPEG
        # no ack yet: at most MAX_IN_FLIGHT frames went out
        from mi_amr.view.widget import MAX_IN_FLIGHT
        time.sleep(0.5)
        assert sum(c.get("type") == "frame" for c, _ in w.sent) <= MAX_IN_FLIGHT
        assert w.mode == "multi" and w.camera["fov"] == pytest.approx(sc.fov)
        before = sc.render(seed=7)

        # the page orbits: the traits and the scene follow
        w._on_page(w, {"type": "camera", "azimuth": w.view.camera.azimuth + 60.0}, [])
        w.sync()
        np.testing.assert_allclose(w.camera["origin"], w.view.camera.origin, rtol=1e-12)
        np.testing.assert_allclose(sc.origin, w.view.camera.origin, rtol=1e-12)
        for _ in range(40):                      # acks: the frames flow again
            w._on_page(w, {"type": "ack"}, [])
        wait_until(lambda: w.view.accum_epoch == w.view.epoch and w.view.spp == 16, "new view refined to max_spp")
        accum = (w.view.accum / w.view.spp).astype(np.float64)
        assert w.view.spp == 16 and w.view.accum_epoch == w.view.epoch

        # bad page messages and bad trait values: one line each, nothing changed
        n = len(w.sent)
        w._on_page(w, {"type": "camera", "distance": -1}, [])
        w._on_page(w, "not an object", [])
        errors = [c for c, _ in w.sent[n:] if c.get("type") == "error"]
        assert len(errors) == 2 and all("\n" not in e["message"] for e in errors)
        assert mi_amr.show is not None and isinstance(mi_amr.show(str(cloud), res=32, spp=4), ViewWidget)
        camera = dict(w.camera)
        with pytest.raises(ValueError, match="fov"):
            w.camera = {"fov": 0}
        with pytest.raises(ValueError, match="no field"):
            w.camera = {"eye": [1, 2, 3]}
        with pytest.raises(ValueError, match="tf"):
            w.tf = "no such preset"
        with pytest.raises(ValueError, match="mode"):
            w.mode = "ambient"
        assert w.camera == camera

        # the same view rendered by the DataScene at full quality: the engine's picture
        views = np.stack([sc.render(seed=s) for s in range(4)]).astype(np.float64)

        def blocks(a):
            return a.reshape(*a.shape[:-3], 4, 8, 4, 8, 3).mean(axis=(-4, -2, -1))
        mean, var = blocks(views).mean(axis=0), blocks(views).var(axis=0, ddof=1)
        z = (blocks(accum) - mean) / np.sqrt(var * (1 + 1 / 4) + 1e-12)
        assert np.abs(z).max() < 6.0, np.abs(z).max()
        z_before = (blocks(before.astype(np.float64)) - mean) / np.sqrt(var * (1 + 1 / 4) + 1e-12)
        assert np.abs(z_before).max() > 6.0                 # the check sees a different view

        # traits set from Python: the view changes and the page hears of it
        n = len(w.sent)
        w.tf = "foggy"
        assert w.tf["colormap"] == "viridis" and w.view.spec.colormap == "viridis"
        assert sc.tf.endswith(".json") and tuple(sc.tf_range) == pytest.approx(w.view.spec.range)
        w.density_scale = 2.0
        assert w.view.spec.density == 2.0 and sc.density_scale == 2.0
        w.camera = {"origin": [0.0, -3.0, 0.5], "fov": 30.0}
        assert w.view.camera.fov == 30.0 and sc.fov == 30.0
        np.testing.assert_allclose(w.view.camera.origin, [0.0, -3.0, 0.5], atol=1e-9)
        w.mode = "single"
        assert w.view.mode == "single" and sc.mode == "single"
        hellos = [c for c, _ in w.sent[n:] if c.get("type") == "hello"]
        assert len(hellos) == 4 and hellos[-1]["mode"] == "single" and hellos[-1]["camera"]["fov"] == 30.0
    finally:
        w.close()
    assert not w.engine._thread.is_alive()


@pytest.mark.slow   # JupyterLab, a kernel and chromium: about 25 s
def test03_in_jupyterlab_through_the_comm_channel_alone(tmp_path, cloud, browser):
    """JupyterLab in chromium, a notebook that runs ``sc.show()``: a
    picture appears in the cell output; an orbit in the page changes it and
    the next cell prints the new camera, which ``sc`` renders; a TF set
    from Python changes the picture; the annotations and the slice panel
    work in the cell; the kernel listens on the ports Jupyter gave it and
    on no other, before and after."""
    from mi_amr.bench.widget import CANVAS_PIXELS, FIND, JupyterLab
    cells = ["import json\nimport mitsuba as mi\nmi.set_variant('llvm_ad_rgb')\nimport mi_amr",
             f"sc = mi_amr.scene({str(cloud)!r}, res=32, spp=16)\nw = sc.show(res=32, max_spp=16)\nw",
             "print(json.dumps(w.sync().camera)); print(json.dumps(sc.origin.tolist()))",
             "w.tf = 'gray ramp'",
             "print(w.mode, sc.mode)"]
    refined = ("() => { const f = window.viewerStats && window.viewerStats.lastFrame; "
               "return f && f.spp >= 16 && !f.preview && window.viewerStats.frames > %d; }")

    def changed_from(page, before, timeout=HANG_S):
        """The canvas once its 16x16 thumbnail differs from ``before``'s by
        a mean of 3 (of 255) and the view refined; the last one seen if never."""
        deadline = time.monotonic() + timeout
        while True:
            now = page.evaluate(CANVAS_PIXELS)
            moved = np.abs(np.subtract(now[2], before[2])).mean()
            if (moved > 3.0 and page.evaluate(refined % 0)) or time.monotonic() > deadline:
                return now, moved
            page.wait_for_timeout(100)
    with JupyterLab(tmp_path) as lab:
        page = lab.open(browser, "widget.ipynb", cells)
        lab.run_cell(page, 0)
        (kernel,) = lab.kernels()
        ports = lab.listening(kernel)
        assert ports, "the kernel listens on Jupyter's ports"
        lab.run_cell(page, 1)
        page.wait_for_function(refined % 0, timeout=HANG_S * 1000)
        first = page.evaluate(CANVAS_PIXELS)
        assert first[1] > 0.5, f"a picture in the cell output: {first[:2]}"      # share of lit pixels
        camera0 = json.loads(lab.run_cell(page, 2).splitlines()[0])

        # an orbit with the mouse
        box = page.evaluate(f"() => {{ const el = ({FIND})('view'); el.scrollIntoView({{block: 'center'}}); "
                            "const r = el.getBoundingClientRect(); return {x: r.x, y: r.y, w: r.width, h: r.height}; }")
        page.wait_for_timeout(300)
        frames = page.evaluate("window.viewerStats.frames")
        x, y = box["x"] + 0.3 * box["w"], box["y"] + 0.5 * box["h"]
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + 120, y + 30, steps=8)
        page.mouse.up()
        page.wait_for_function(refined % frames, timeout=HANG_S * 1000)
        dragged, moved = changed_from(page, first)
        assert moved > 3.0, f"the drag changed the picture: mean |thumbnail difference| {moved:.2f} of 255"
        out = lab.run_cell(page, 2).splitlines()
        camera1, origin = json.loads(out[0]), json.loads(out[1])
        assert np.linalg.norm(np.subtract(camera1["origin"], camera0["origin"])) > 0.1, (camera0, camera1)
        np.testing.assert_allclose(origin, camera1["origin"], rtol=1e-9)          # sc renders that view

        # a TF from Python
        lab.run_cell(page, 3)
        grey, changed = changed_from(page, dragged)
        assert changed > 3.0, f"the TF changed the picture: {changed:.2f} of 255"

        # the page's mode selector and snapshot button
        page.get_by_test_id("mode").select_option("single")
        page.wait_for_function("window.viewerStats.lastFrame.mode === 'single'", timeout=HANG_S * 1000)
        assert lab.run_cell(page, 4).split() == ["single", "single"]
        page.get_by_test_id("snapshot").click()
        page.wait_for_function("window.viewerStats.snapshots.length > 0", timeout=HANG_S * 1000)
        assert (tmp_path / "snapshot.exr").is_file() and (tmp_path / "snapshot.xml").is_file()

        # the viewer's annotations in the cell (its page code, as tests/test_view_annotations.py test04 checks
        # in mi-amr view): AMR levels add lines to the overlay, and the slice panel follows an x clip
        drawn = ("() => { const c = (%s)('overlay'), d = c.getContext('2d').getImageData(0, 0, c.width, c.height)"
                 ".data; let n = 0; for (let k = 3; k < d.length; k += 4) n += d[k] > 0; return n; }") % FIND
        outline = page.evaluate(drawn)
        page.get_by_test_id("show-levels").check()
        page.wait_for_function(f"() => ({drawn})() > {outline}", timeout=HANG_S * 1000)
        page.get_by_test_id("show-slice").check()
        page.get_by_test_id("clip-axis").select_option("x")
        page.wait_for_function("window.viewerStats.lastSlice && window.viewerStats.lastSlice.axis === 'x'",
                               timeout=HANG_S * 1000)
        assert lab.listening(kernel) == ports, "the widget opened no port"
        page.close()


def test04_the_quickstart_notebook_runs_in_a_kernel(tmp_path, monkeypatch):
    """notebooks/quickstart.ipynb in a real kernel (nbclient), small: the
    ``show()`` cell returns at once with the widget as its output (no page
    shows it here), the next cells render the view and compare it with the
    gridvolume reference (the notebook asserts the means agree within 5%)."""
    nbclient = pytest.importorskip("nbclient")
    import nbformat
    from pathlib import Path
    nb = nbformat.read(Path(__file__).resolve().parents[1] / "notebooks" / "quickstart.ipynb", as_version=4)
    monkeypatch.setenv("MI_AMR_NOTEBOOK_SMALL", "1")
    nbclient.NotebookClient(nb, timeout=int(HANG_S) * 3, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = {i: [o for o in c.get("outputs", [])] for i, c in enumerate(nb.cells) if c.cell_type == "code"}
    show = next(i for i, c in enumerate(nb.cells) if c.cell_type == "code" and ".show()" in c.source)
    assert any("application/vnd.jupyter.widget-view+json" in o.get("data", {}) for o in outputs[show])
    render = next(i for i, c in enumerate(nb.cells) if c.cell_type == "code" and "sc.render()" in c.source)
    assert any("image/png" in o.get("data", {}) for o in outputs[render])
    assert any("relative RMSE" in o.get("text", "") for out in outputs.values() for o in out)
    assert (tmp_path / "out" / "quickstart" / "view.exr").is_file()
