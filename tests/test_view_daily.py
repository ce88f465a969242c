"""``mi-amr view`` as a daily tool (issue 42, the server's half): nothing one
tab does stops the others, errors are in sight and one line, samples are
kept, snapshots never overwrite or follow links, and other local pages get
neither the websocket nor the token. Browser tests drive Debian's chromium
through Playwright, on one served viewer of small data for the module."""

import json
import logging
import os
import shutil
import socket
import stat
import struct
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from conftest import HANG_S, wait_until

pytest.importorskip("starlette")
#: Playwright's deadlines, in milliseconds: only a hang reaches them.
HANG_MS = HANG_S * 1000

ROOT = Path(__file__).resolve().parents[1]
MAX_SPP = 48


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A viewer of a 20,000-cell cloud at 32x32 (48 spp at most), on loopback."""
    from mi_amr.data.datasets import make_dataset
    from mi_amr.data.io import save_cells
    from mi_amr.view.engine import ViewEngine
    from mi_amr.view.server import ViewServer
    root = tmp_path_factory.mktemp("daily")
    src = save_cells(make_dataset("cloud", cells=20000, seed=0), root / "cloud.cells")
    engine = ViewEngine(src, res=32, max_spp=MAX_SPP).start()
    server = ViewServer(engine, out_dir=root / "snapshots", quiet=True).start()
    assert engine.ready.wait(HANG_S) and engine.error is None, engine.error
    yield server, root
    server.stop()
    engine.stop()




def _ws(server, **kw):
    from websockets.sync.client import connect
    return connect(f"ws://127.0.0.1:{server.port}/ws?token={server.token}", max_size=2**24, **kw)


def _next(ws, kind, timeout=HANG_S, frames=None):
    """The next reply of ``kind`` ("frame": a binary frame's header), acking
    frames on the way (their headers appended to ``frames``)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = ws.recv(timeout=max(0.01, deadline - time.monotonic()))
        if isinstance(m, bytes):
            n = struct.unpack(">I", m[:4])[0]
            header = json.loads(m[4:4 + n])
            ws.send(json.dumps({"type": "ack"}))
            if frames is not None:
                frames.append(header)
            if kind == "frame":
                return header
            continue
        reply = json.loads(m)
        if reply["type"] == kind:
            return reply
    raise AssertionError(f"no {kind} within {timeout} s")


def _open(browser, url):
    page = browser.new_page()
    page.goto(url)
    page.wait_for_function("window.viewerStats.lastFrame && !window.viewerStats.lastFrame.preview", timeout=HANG_MS)
    return page


def _stats(page):
    return page.evaluate("window.viewerStats")


# ---- 1. isolation -------------------------------------------------------------------------
def test01_a_bad_range_in_one_tab_while_another_renders(served, browser):
    """Tab A types a range float32 cannot hold (0 .. 1e-300, 1 .. 1.00000001):
    refused with a message in A, A's state stays and A still renders; tab B
    keeps refining, sees no error. A density of 1e300 on a third socket is
    refused alike."""
    server, _ = served
    a, b = _open(browser, server.url), _open(browser, server.url)
    b.evaluate("window.viewerStats.errors = []")
    for lo, hi in (("0", "1e-300"), ("1", "1.00000001")):
        n = len(_stats(a)["errors"])
        a.get_by_test_id("range-lo").fill(lo)
        a.get_by_test_id("range-hi").fill(hi)
        a.get_by_test_id("range-hi").press("Enter")
        a.wait_for_function(f"window.viewerStats.errors.length > {n}", timeout=HANG_MS)
        assert "float32" in _stats(a)["errors"][-1]["message"]
        assert "cannot be rendered" in a.get_by_test_id("message").inner_text()
    with _ws(server) as ws:
        _next(ws, "hello")
        ws.send(json.dumps({"type": "tf", "density": 1e300}))
        assert "density_scale" in _next(ws, "error")["message"]
    # B refines on (a camera change restarts it; its frames go on coming)
    frames_b = _stats(b)["frames"]
    b.get_by_test_id("view").scroll_into_view_if_needed()
    box = b.get_by_test_id("view").bounding_box()
    b.mouse.move(box["x"] + 100, box["y"] + 100)
    b.mouse.down()
    b.mouse.move(box["x"] + 160, box["y"] + 110, steps=4)
    b.mouse.up()
    b.wait_for_function(f"window.viewerStats.frames > {frames_b} && window.viewerStats.lastFrame.spp >= 8 "
                        "&& !window.viewerStats.lastFrame.preview", timeout=HANG_MS)
    assert _stats(b)["errors"] == [] and _stats(b)["fatal"] is None
    # A is alive: an orbit gives a new frame
    version = _stats(a)["lastFrame"]["version"]
    # typing into the range inputs scrolled them into view: the picture may be above it now
    a.get_by_test_id("view").scroll_into_view_if_needed()
    box = a.get_by_test_id("view").bounding_box()
    a.mouse.move(box["x"] + 100, box["y"] + 100)
    a.mouse.down()
    a.mouse.move(box["x"] + 150, box["y"] + 100, steps=4)
    a.mouse.up()
    a.wait_for_function(f"window.viewerStats.lastFrame.version > {version}", timeout=HANG_MS)
    a.close()
    b.close()


def test02_a_failing_pass_goes_back_to_the_last_picture(served):
    """A state that passes the checks but fails to render (a failure made
    here) is reported to its view alone, which goes back to the last state
    that rendered and refines on; another view never notices."""
    server, _ = served
    engine = server.engine
    loaded = engine.loaded
    apply = loaded.apply

    def failing(camera, spec, size):
        if spec.density == 12345.0:
            raise RuntimeError("drjit: a made-up failure")
        return apply(camera, spec, size)
    frames, told, told_other = [], [], []
    view = engine.open_view(lambda h, j: frames.append(h), told.append)
    bystander = engine.open_view(lambda h, j: None, told_other.append)
    loaded.apply = failing
    try:
        wait_until(lambda: any(h.spp >= 2 and not h.preview for h in frames), "refined frame")
        good = view.spec
        engine.change(view, {"type": "tf", "density": 12345.0})
        wait_until(lambda: told, "error told to the view")
        error = told[0]
        assert error.TYPE == "error" and "made-up failure" in error.message, told
        assert error.tf == good and view.spec == good
        n = len(frames)
        wait_until(lambda: len(frames) > n and frames[-1].spp >= 4, "frame of 4 spp after the failure")
        assert frames[-1].spp >= 4 and engine._thread.is_alive()
        assert told_other == [] and len(told) == 1
    finally:
        del loaded.apply
        engine.close_view(view)
        engine.close_view(bystander)


# ---- 1. a failed load: in the page, one line, exit 2 ---------------------------------------
def test03_a_failed_load_is_shown_in_the_page_and_exits_2(served, browser, tmp_path):
    """``mi-amr view`` of a truncated .cells: the browser, opened through a
    private redirect file (0600 in a 0700 folder; no token on its command
    line), shows the load's error in a visible box; stderr gets one line;
    the exit status is 2."""
    _, root = served
    bad = tmp_path / "bad.cells"
    bad.write_bytes((root / "cloud.cells").read_bytes()[:1000])
    shutil.copy(root / "cloud.scalars", tmp_path / "bad.scalars")
    record = tmp_path / "browser-args"
    opener = tmp_path / "opener.sh"
    opener.write_text(f'#!/bin/sh\necho "$@" > {record}\n')
    opener.chmod(0o700)
    env = dict(os.environ, BROWSER=f"{opener} %s")
    proc = subprocess.Popen([sys.executable, "-m", "mi_amr.tools.cli", "view", str(bad), "--out", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        wait_until(lambda: record.exists() and record.read_text().strip(), "browser opened")
        uri = record.read_text().strip()
        assert uri.startswith("file://") and "token" not in uri, uri
        opened = Path(uri[len("file://"):])
        assert stat.S_IMODE(opened.stat().st_mode) == 0o600 and stat.S_IMODE(opened.parent.stat().st_mode) == 0o700
        page = browser.new_page()
        page.goto(uri)
        fatal = page.get_by_test_id("fatal")
        fatal.wait_for(state="visible", timeout=HANG_MS)
        assert "bad.cells" in fatal.inner_text() and "disconnected" not in page.get_by_test_id("status").inner_text()
        out, err = proc.communicate(timeout=HANG_S)
        page.close()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("mi-amr view: error:") and "bad.cells" in lines[0], err
    assert not opened.parent.exists()                   # the redirect file is gone with the viewer


def test04_every_load_failure_is_one_line(served, tmp_path, monkeypatch, capsys):
    """A truncated .cells and .amrb, a renamed PNG, a broken XML, an XML
    without an amr medium, a directory, a yt field that is not there: the
    engine's error is one line, no traceback; the command exits 2 with it."""
    from amr_formats import write_enzo
    from mi_amr.data.io import save_cells
    from mi_amr.data.datasets import make_dataset
    from mi_amr.tools import commands
    from mi_amr.tools.cli import main
    from mi_amr.view.engine import ViewEngine
    _, root = served
    cells = (root / "cloud.cells").read_bytes()
    (tmp_path / "short.cells").write_bytes(cells[:len(cells) // 2 + 3])
    shutil.copy(root / "cloud.scalars", tmp_path / "short.scalars")
    amrb = save_cells(make_dataset("cloud", cells=2000, seed=2), tmp_path / "whole.amrb").read_bytes()
    (tmp_path / "short.amrb").write_bytes(amrb[:len(amrb) // 2])
    from PIL import Image
    Image.new("RGB", (40, 30), (200, 10, 10)).save(tmp_path / "picture.png")
    (tmp_path / "picture.png").rename(tmp_path / "picture.cells")
    shutil.copy(root / "cloud.scalars", tmp_path / "picture.scalars")
    (tmp_path / "broken.xml").write_text('<scene version="3.0.0"><sensor type="perspective">')
    (tmp_path / "plain.xml").write_text('<scene version="3.0.0"><emitter type="constant"/>'
                                        '<shape type="sphere"/></scene>')
    (tmp_path / "folder").mkdir()
    enzo = write_enzo(tmp_path / "DD0001", "DD0001", np.ones((8, 8, 8)), [])
    cases = [("short.cells", None), ("short.amrb", None), ("picture.cells", None), ("broken.xml", None),
             ("plain.xml", None), ("folder", None), (enzo, "nosuch")]
    for name, field in cases:
        engine = ViewEngine(tmp_path / name, field, res=16).start()
        try:
            assert engine.ready.wait(HANG_S)
        finally:
            engine.stop()
        assert engine.error and "\n" not in engine.error and "Traceback" not in engine.error, (name, engine.error)
    monkeypatch.setattr(commands, "LOAD_ERROR_WAIT", 0.2)
    capsys.readouterr()
    assert main(["view", str(tmp_path / "plain.xml"), "--no-browser", "--out", str(tmp_path)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "no amr medium" in err[0], err
    # served to other machines only when asked, and then told that nothing is encrypted
    assert main(["view", str(tmp_path / "plain.xml"), "--no-browser", "--out", str(tmp_path),
                 "--host", "0.0.0.0", "--allow-remote"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 2 and "not encrypted" in err[0] and "no amr medium" in err[1], err


# ---- 2. errors -----------------------------------------------------------------------------
def test05_every_bad_argument_is_one_line(served, tmp_path, capsys):
    """Each bad argument of ``mi-amr view``: exit status 2 (returned, or the
    argument parser's exit) and one line on stderr."""
    from mi_amr.tools.cli import main
    _, root = served
    data = str(root / "cloud.cells")
    (tmp_path / "file").write_text("x")
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen(1)
    cases = [
        (["--host", "example.invalid"], "--allow-remote"),
        (["--host", "example.invalid", "--allow-remote"], "cannot serve on example.invalid"),
        (["--host", "0.0.0.0"], "--allow-remote"),
        (["--port", "70000"], "--port 70000"),
        (["--port", "-1"], "--port -1"),
        (["--port", str(taken.getsockname()[1])], "cannot serve on 127.0.0.1"),
        (["--res", "5"], "res must lie"),
        (["--max-spp", "0"], "--max-spp"),
        (["--preview-scale", "3"], "preview_scale"),
        (["--out", str(tmp_path / "file")], "not a folder"),
        (["--variant", "nosuch"], "nosuch"),
        (["--field", "density", "--", str(ROOT / "scenes" / "blocks.xml")], "--field is for data"),
        (["--", str(tmp_path / "missing.cells")], "no such file"),
    ]
    try:
        for extra, words in cases:
            argv = ["view", "--no-browser", "--out", str(tmp_path)] + extra
            if "--" not in extra:
                argv.append(data)
            try:
                code = main(argv)
            except SystemExit as e:               # refused by the argument parser itself
                code = e.code
            assert code == 2, extra
            err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
            assert len(err) == 1 and err[0].startswith("mi-amr view: error:") and words in err[0], (extra, err)
    finally:
        taken.close()


class _Records(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records = []

    def emit(self, record):
        self.records.append(record)


def test06_malformed_messages_name_the_field_and_disconnects_are_quiet(served):
    """JSON nested 10^4 deep and 400-digit numbers get an error naming the
    field; sockets dropped abruptly (mid-frame, no close) log nothing; the
    socket listens before the URL exists (a first connection at once works)."""
    from mi_amr.view.server import ViewServer
    server, _ = served
    records = _Records()
    loggers = [logging.getLogger(n) for n in ("uvicorn", "uvicorn.error", "asyncio")]
    for lg in loggers:
        lg.addHandler(records)
    try:
        with _ws(server) as ws:
            _next(ws, "hello")
            cases = [("[" * 10000 + "]" * 10000, "nested"),
                     ('{"type": "tf", "density": 1' + "0" * 400 + "}", "density"),
                     ('{"type": "tf", "range": [0, 1' + "0" * 400 + "]}", "range"),
                     ('{"type": "camera", "azimuth": -' + "9" * 400 + "}", "azimuth"),
                     ('{"type": "camera", "target": [0, 0, 1' + "0" * 400 + ".5]}", "target")]
            for text, field in cases:
                ws.send(text)
                reply = _next(ws, "error")
                assert reply["message"].startswith(field if field != "nested" else "message: nested"), reply
                assert "Traceback" not in reply["message"]
        for _ in range(3):                       # gone without a close frame, frames in flight
            with _ws(server) as ws:
                _next(ws, "frame")
                ws.send(json.dumps({"type": "camera", "azimuth": 33.0}))
                ws.socket.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                ws.socket.close()
        time.sleep(1.0)
        with _ws(server) as ws:                  # and the server goes on
            _next(ws, "frame")
    finally:
        for lg in loggers:
            lg.removeHandler(records)
    loud = [r for r in records.records if r.levelno >= logging.WARNING]
    assert not loud, [r.getMessage() for r in loud]
    fresh = ViewServer(server.engine, quiet=True)            # made, not yet serving
    try:
        socket.create_connection(("127.0.0.1", fresh.port), timeout=HANG_S).close()
    finally:
        fresh.stop()


def test12_unread_replies_stay_bounded():
    """A page that asks and never reads: a newer histogram or status
    replaces the unsent one, and at most MAX_PENDING replies wait."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from mi_amr.view import protocol as p
    from mi_amr.view.server import MAX_PENDING, Outbox

    async def flood():
        box = Outbox()
        for k in range(10000):
            box.put(p.HistogramReply((float(k),), (0.0, 1.0), False))
            box.put(p.Status("ready", f"s{k}"))
            box.put(p.Error(f"e{k}", "tf"))
        kinds = [(await box.get()) for _ in range(len(box))]
        return kinds
    with ThreadPoolExecutor(1) as pool:          # a loop of its own (Playwright's may run on this thread)
        sent = pool.submit(asyncio.run, flood()).result()
    assert len(sent) <= MAX_PENDING
    assert [m.counts for m in sent if m.TYPE == "histogram"] == [(9999.0,)]
    assert [m.desc for m in sent if m.TYPE == "status"] == ["s9999"]
    assert sent[-1].message == "e9999"


# ---- 4. samples are kept -------------------------------------------------------------------
def test07_the_denoiser_switch_keeps_the_samples(served, browser):
    """Switching the denoiser off and on keeps the accumulation (the spp
    shown never falls back); between denoised images the counter shows the
    real spp with the denoised image's own; at the end (``max_spp``, or
    sooner where the view is clean: docs/manual/adaptive.md) the page says
    done."""
    pytest.importorskip("mitsuba_oidn")
    server, _ = served
    page = _open(browser, server.url)
    page.wait_for_function("window.viewerStats.lastFrame.spp >= 6 && !window.viewerStats.lastFrame.preview",
                           timeout=HANG_MS)
    for on in (False, True):
        before = _stats(page)["lastFrame"]
        page.get_by_test_id("denoise").set_checked(on)
        page.wait_for_function(f"window.viewerStats.lastFrame.version > {before['version']} "
                               f"&& window.viewerStats.lastFrame.denoised === {json.dumps(on)}", timeout=HANG_MS)
        after = _stats(page)["lastFrame"]
        assert not after["preview"] and after["spp"] >= before["spp"], (before, after)
    page.wait_for_function("window.viewerStats.lastFrame.spp >= window.viewerStats.lastFrame.max_spp",
                           timeout=HANG_MS)
    page.wait_for_function("document.querySelector('[data-testid=spp]').textContent.includes('done')",
                           timeout=HANG_MS)
    last = _stats(page)["lastFrame"]
    assert 16 <= last["spp"] <= MAX_SPP and f"{last['spp']} spp" in page.get_by_test_id("spp").inner_text()
    page.close()
    with _ws(server) as ws:                       # denoised on: every spp counted, images now and then
        frames = []
        wait_until(lambda: (lambda f: f["spp"] >= f["max_spp"] and not f["preview"])(
            _next(ws, "frame", frames=frames)), "the last full frame (max_spp, or clean)")
    full = [f for f in frames if not f["preview"]]
    spps = [f["spp"] for f in full]
    assert spps == sorted(spps) and any(s & (s - 1) for s in spps), spps     # not only 1, 2, 4, 8, ...
    between = [f for f in full if f.get("shown_spp")]
    assert between and all(f["denoised"] and f["shown_spp"] < f["spp"] for f in between), full
    assert full[-1]["denoised"] and "shown_spp" not in full[-1]


def test08_a_snapshot_png_and_exr_come_from_the_same_samples(served, tmp_path):
    """Taken mid-refinement with the denoiser on, the PNG is the denoised
    EXR (8-bit sRGB), whatever denoised image the page had."""
    pytest.importorskip("mitsuba_oidn")
    from PIL import Image

    from mi_amr.images import read_exr, srgb8
    from mi_amr.view.engine import denoiser
    server, _ = served
    engine = server.engine
    frames = []
    view = engine.open_view(lambda h, j: frames.append(h))
    try:
        wait_until(lambda: frames and frames[-1]["spp"] >= 19, "frame of 19 spp")
        shot = engine.take_snapshot(view, tmp_path, "same")
    finally:
        engine.close_view(view)
    exr = read_exr(shot.files[0])[..., :3]
    png = np.asarray(Image.open(shot.files[1]).convert("RGB"), np.float64)
    expect = srgb8(denoiser()[0](exr)).astype(np.float64)
    assert np.abs(png - expect).max() <= 2, np.abs(png - expect).max()


# ---- 5. snapshots --------------------------------------------------------------------------
def test09_snapshots_never_overwrite_nor_follow_links(served, browser, tmp_path):
    """A taken name gets a number (said in the reply), the page shows the
    folder, a name planted as a symbolic link is refused in the page and
    the file it points to is untouched; a budget refuses beyond its count."""
    from mi_amr.view.snapshot import SnapshotBudget
    server, root = served
    out = root / "snapshots"
    out.mkdir(exist_ok=True)
    outside = tmp_path / "precious.txt"
    outside.write_text("keep me")
    (out / "trap.png").symlink_to(outside)
    (out / "taken.xml").write_text("mine")
    page = _open(browser, server.url)
    assert str(out) in page.get_by_test_id("snapshot-folder").inner_text()
    page.get_by_test_id("snapshot-name").fill("trap")
    page.get_by_test_id("snapshot").click()
    page.wait_for_function("document.querySelector('[data-testid=snapshot-result]').textContent.includes('link')",
                           timeout=HANG_MS)
    assert outside.read_text() == "keep me" and not (out / "trap.exr").exists()
    page.get_by_test_id("snapshot-name").fill("taken")
    page.get_by_test_id("snapshot").click()
    page.wait_for_function("window.viewerStats.snapshots.length > 0", timeout=HANG_MS)
    snap = _stats(page)["snapshots"][-1]
    assert [Path(f).name for f in snap["files"]][:4] == ["taken-1.exr", "taken-1.png", "taken-1.xml",
                                                          "taken-1.tf.json"]
    assert "taken-1" in snap["notes"][0] and (out / "taken.xml").read_text() == "mine"
    assert "taken-1" in page.get_by_test_id("snapshot-result").inner_text()
    page.close()
    engine = server.engine
    view = engine.open_view(lambda h, j: None)
    try:
        wait_until(lambda: view.accum_epoch == view.epoch, "full frame of the view")
        budget = SnapshotBudget(count=1)
        engine.take_snapshot(view, tmp_path, "one", budget)
        with pytest.raises(ValueError, match="1 snapshots"):
            engine.take_snapshot(view, tmp_path, "two", budget)
        with pytest.raises(ValueError, match="MB"):
            engine.take_snapshot(view, tmp_path, "three", SnapshotBudget(nbytes=0))
    finally:
        engine.close_view(view)
    assert not list(tmp_path.glob("two*")) and not list(tmp_path.glob("three*"))
    # data the XML cannot name as they are (here a field's own .scalars; yt data alike) are written
    # once beside the snapshots, and the reply says so
    from dataclasses import replace

    from mi_amr.view.snapshot import write_snapshot
    shutil.copy(root / "cloud.scalars", root / "cloud-f.scalars")
    loaded = replace(engine.loaded, field="f")
    image = np.full((32, 32, 3), 0.5, np.float32)
    first = write_snapshot(loaded, tmp_path / "side", "a", image, image, view.camera, view.spec, 4)
    again = write_snapshot(loaded, tmp_path / "side", "b", image, image, view.camera, view.spec, 4)
    assert [f.name for f in first.files] == ["a.exr", "a.png", "a.xml", "a.tf.json", "cloud-f.amrb"]
    assert "cloud-f.amrb" in first.notes[0] and "MB" in first.notes[0]
    assert len(again.files) == 4 and again.notes == [] and "cloud-f.amrb" in again.files[2].read_text()


def test10_render_takes_the_scenes_own_spp(served, tmp_path, capsys):
    """``mi-amr render SNAPSHOT.xml`` without --spp renders the snapshot's
    spp (the XML's default), with -D spp=N that, with --spp that."""
    import gc

    from mi_amr.rendering import scene_spp
    from mi_amr.tools.cli import main
    from mi_amr.view.engine import JIT_LOCK
    server, _ = served
    engine = server.engine
    view = engine.open_view(lambda h, j: None)
    try:
        wait_until(lambda: view.spp >= 5, "frame of 5 spp")
        shot = engine.take_snapshot(view, tmp_path, "s")
    finally:
        engine.close_view(view)
    xml = shot.files[2]
    assert scene_spp(xml, {}) == shot.spp and scene_spp(xml, {"spp": "3"}) == 3
    assert scene_spp(ROOT / "scenes" / "blocks.xml", {}) == 64 and scene_spp(tmp_path / "none.xml", {}) is None
    with JIT_LOCK:
        assert main(["render", str(xml), "-o", str(tmp_path / "r.exr"), "-D", "res=8"]) == 0
        gc.collect()
    assert f"{shot.spp} spp" in capsys.readouterr().out


# ---- 7. security ---------------------------------------------------------------------------
def test11_another_local_page_gets_neither_socket_nor_token(served, browser):
    """A page served by another server on 127.0.0.1 (another port), in a
    browser that has the viewer open, cannot open the websocket (with or
    without the token: the Origin is not the viewer's), cannot read the
    page, and its server never receives the token; a client claiming
    another Origin is refused too."""
    from websockets.exceptions import InvalidStatus
    server, _ = served
    heard = []
    target = f"127.0.0.1:{server.port}"
    evil = """<!doctype html><script>
    window.results = {};
    function tryWs(name, url) { return new Promise((done) => {
      const ws = new WebSocket(url);
      ws.onopen = () => { window.results[name] = "open"; };
      ws.onmessage = () => { window.results[name] = "message"; ws.close(); done(); };
      ws.onclose = () => { if (!window.results[name]) window.results[name] = "refused"; done(); };
    }); }
    window.attack = async (token) => {
      await tryWs("bare", "ws://TARGET/ws");
      await tryWs("token", "ws://TARGET/ws?token=" + token);
      try { const r = await fetch("http://TARGET/?token=" + token, {credentials: "include"});
            window.results.fetch = "read " + (await r.text()).length; }
      catch (e) { window.results.fetch = "refused"; }
      await fetch("/echo", {credentials: "include"});
    };
    </script>""".replace("TARGET", target)

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):
            heard.append(str(self.headers) + self.path)
            body = evil.encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *a):
            pass
    other = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=other.serve_forever, daemon=True).start()
    try:
        context = browser.new_context()
        viewer = context.new_page()
        viewer.goto(server.url)                   # the viewer open in the same browser
        viewer.wait_for_function("window.viewerStats.frames > 0", timeout=HANG_MS)
        page = context.new_page()
        page.goto(f"http://127.0.0.1:{other.server_address[1]}/")
        page.evaluate(f"window.attack({json.dumps(server.token)})")
        results = page.evaluate("window.results")
        context.close()
    finally:
        other.shutdown()
    assert results == {"bare": "refused", "token": "refused", "fetch": "refused"}, results
    assert heard and not any(server.token in h for h in heard)
    assert not any("cookie" in h.lower() for h in heard)
    with pytest.raises(InvalidStatus):
        with _ws(server, origin="http://evil.example"):
            pass
    with _ws(server, origin=f"http://{target}") as ws:        # the viewer's own origin is welcome
        _next(ws, "hello")
