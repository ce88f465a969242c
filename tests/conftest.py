"""Shared fixtures: the Mitsuba variant and small data factories."""

import gc
import os
import shutil

import numpy as np
import pytest

import mi_amr  # noqa: F401  (sets DRJIT_LIBLLVM_PATH before mitsuba starts LLVM)
import mitsuba as mi


def pytest_addoption(parser):
    parser.addoption("--stress-size", default="small", choices=("small", "large"),
                     help="size of the stress tests (marker 'stress')")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Marker ``slow`` for the cases a module names in ``SLOW_CASES`` (test
    names with their parameters, e.g. ``test02_x[amrex]``): for cases of a
    module-scoped fixture's parameter, which ``pytest.param`` would mark in
    every test that uses it."""
    for item in items:
        if item.name in getattr(item.module, "SLOW_CASES", ()):
            item.add_marker(pytest.mark.slow)


@pytest.fixture
def stress_size(request):
    return request.config.getoption("--stress-size")


#: ``MI_AMR_VARIANT=cuda_ad_rgb`` (``make test-gpu``, tools/gpu-check) runs the
#: variant-dependent tests on that variant alone, those asking for ``llvm``
#: included.
FORCED_VARIANT = os.environ.get("MI_AMR_VARIANT") or None


def _jit_rgb_variants():
    if FORCED_VARIANT:
        if FORCED_VARIANT not in mi.variants():
            raise pytest.UsageError(f"MI_AMR_VARIANT={FORCED_VARIANT}: not a variant of this Mitsuba")
        return [FORCED_VARIANT]
    out = []
    for v in ("llvm_ad_rgb", "cuda_ad_rgb"):
        if v not in mi.variants():
            continue
        if v.startswith("cuda"):
            try:
                import drjit as dr
                if not dr.has_backend(dr.JitBackend.CUDA):
                    continue
            except Exception:
                continue
        out.append(v)
    return out


@pytest.fixture(params=_jit_rgb_variants(), scope="module")
def variant(request):
    """Every JIT rgb variant available here (llvm_ad_rgb; cuda_ad_rgb on a GPU)."""
    mi.set_variant(request.param)
    return request.param


@pytest.fixture
def llvm():
    """``llvm_ad_rgb``, or the variant ``MI_AMR_VARIANT`` names."""
    v = FORCED_VARIANT or "llvm_ad_rgb"
    mi.set_variant(v)
    return v


#: What Dr.Jit says when it finds no libLLVM (a GPU machine without it,
#: tools/test-gpu): there a test that needs the LLVM backend is skipped, not
#: failed. On CI (``CI`` set, as CI services do) libLLVM is part of the
#: set-up (tools/setup.sh), so its absence fails those tests loudly: a
#: suite that skipped every LLVM test would pass having checked nothing.
NO_LLVM = "the LLVM backend is inactive"
#: Whether this is a CI run (the ``CI`` variable set and not 0/false).
ON_CI = os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


#: What the tests skip without (``pytest.importorskip``) and the set-up
#: installs (the ``dev`` extra, tools/setup.sh): on CI each must be there,
#: else the suite would pass with whole files skipped.
CI_NEEDS = ("yt", "h5py", "starlette", "websockets", "anywidget", "nbclient", "IPython", "mitsuba_oidn",
            "imageio_ffmpeg", "dask.distributed", "playwright")
CI_COMMANDS = ("node", "chromium")


def pytest_sessionstart(session):
    """On CI, the suite stops at once, naming what the set-up failed to
    install, rather than skipping the tests that need it."""
    if not ON_CI:
        return
    import importlib.util

    def importable(name):
        try:
            return importlib.util.find_spec(name) is not None
        except ImportError:                     # a parent package missing
            return False
    missing = [m for m in CI_NEEDS if not importable(m)] + [c for c in CI_COMMANDS if not shutil.which(c)]
    if missing:
        raise pytest.UsageError(f"CI: {', '.join(missing)} missing: make setup installs them (tests would "
                                f"skip without them)")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.failed and call.excinfo is not None and NO_LLVM in report.longreprtext and not ON_CI:
        report.outcome = "skipped"
        report.longrepr = (str(item.path), item.location[1] or 0,
                           "Skipped: needs Dr.Jit's LLVM backend, and no libLLVM was found here")


# ---- Waiting for events -------------------------------------------------------
#: Seconds a test waits for something that must happen (a frame, a reply, a
#: thread's state): far beyond a loaded 2-core machine's worst case, so that
#: only a hang reaches it. Speed is measured by ``python -m mi_amr.bench``,
#: never by a test's deadline.
HANG_S = 120.0


def wait_until(predicate, what: str = "the condition", timeout: float = HANG_S, poll: float = 0.01):
    """Poll ``predicate()`` until it is true (returns its value); an
    AssertionError naming ``what`` once ``timeout`` seconds pass (a hang)."""
    import time
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"no {what} within {timeout:g} s (a hang?)")
        time.sleep(poll)


# ---- Data factories --------------------------------------------------------
def random_amr(seed=0, n=16, levels=3, quantize=4):
    """Small random AMR data: a smooth random volume, quantised so that block
    coarsening produces every level up to ``levels - 1``."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n)] * 3, indexing="ij")
    c = rng.uniform(-0.3, 0.3, 3)
    v = np.exp(-3 * ((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2))
    v = v + 0.15 * rng.random(v.shape) * (v > 0.5)
    v = np.round(v * quantize) / quantize
    return mi_amr.dense_to_amr(v.astype(np.float32), 0.0, levels - 1)


def dataless_view(size: int, max_spp: int):
    """``(engine, view)``: a `ViewEngine` whose loaded scene has no data (a
    ``size`` x ``size`` view, ``max_spp`` the most passes), ready, with one
    view open whose frames go nowhere: for the scheduler's and the page's
    logic without rendering."""
    from mi_amr.view import engine as eng
    from mi_amr.view.camera import OrbitCamera
    from mi_amr.view.scene import LoadedScene
    from mi_amr.view.tf_spec import TFSpec
    engine = eng.ViewEngine("unused.cells")
    engine.loaded = LoadedScene("unused.cells", None, "test", [size, size],
                                OrbitCamera.looking((2, 0, 0), (0, 0, 0), (0, 0, 1), 35.0), TFSpec(), ("plasma",),
                                stored_log=False)
    engine.max_spp = max_spp
    engine.ready.set()
    return engine, engine.open_view(lambda header, jpeg: None)


def volume_scene(medium, res=32, integrator="volpath", max_depth=32, emitters="env+sun",
                 to_world=None, target=(0.5, 0.5, 0.5), fov=40):
    """A small scene: the medium inside a cube covering its unit cube
    (placed by ``to_world``), seen by a perspective camera."""
    T = mi.ScalarTransform4f
    to_world = to_world if to_world is not None else T()
    cube = to_world @ T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5)
    scene = {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": max_depth},
        "sensor": {"type": "perspective", "fov": fov,
                   "to_world": T().look_at(to_world @ mi.ScalarPoint3f(1.8, 1.3, 2.6),
                                           to_world @ mi.ScalarPoint3f(*target),
                                           to_world @ mi.ScalarVector3f(0, 1, 0)),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}}},
        "cube": {"type": "cube", "to_world": cube, "bsdf": {"type": "null"}, "interior": medium},
    }
    if "env" in emitters:
        scene["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.6, 0.7, 0.8]}}
    if "sun" in emitters:
        scene["sun"] = {"type": "directional", "direction": [-0.5, -1, -0.3],
                        "irradiance": {"type": "rgb", "value": 2.0}}
    return scene


def cloud_scene_xml(tmp_path, cells: str = "d.cells", data=None):
    """The bundled ``scenes/cloud.xml`` written to ``tmp_path/s.xml`` with its
    data file replaced by ``cells`` (relative to ``tmp_path``); ``data``
    (AMRCells) is written there first, or nothing is (a missing file)."""
    from pathlib import Path
    from mi_amr.data.io import write_exabricks
    if data is not None:
        write_exabricks(data, tmp_path / cells)
    root = Path(__file__).resolve().parents[1]
    text = (root / "scenes" / "cloud.xml").read_text().replace("data/cloud.cells", cells)
    (tmp_path / "s.xml").write_text(text)
    return tmp_path / "s.xml"


def render_cli(argv):
    """``mi-amr render ARGV -q`` in a subprocess (``CompletedProcess``)."""
    import subprocess
    import sys
    return subprocess.run([sys.executable, "-m", "mi_amr.tools.cli", "render", *[str(a) for a in argv], "-q"],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def browser():
    """Debian's chromium driven by Playwright (no browser download), one per
    test module: the viewer's browser tests share it."""
    from playwright.sync_api import sync_playwright   # a dev dependency, for the browser tests only
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail("Debian's chromium is missing: make setup installs it (apt-get install chromium)")
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=exe, args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", "--no-first-run"])
        new_page, new_context = b.new_page, b.new_context

        def page_waiting_for_events(*args, **kw):
            """A page whose waits and actions give up only at `HANG_S` (Playwright's 30 s default
            is a wall-clock threshold a loaded machine can reach)."""
            page = new_page(*args, **kw)
            page.set_default_timeout(HANG_S * 1000)
            return page

        def context_waiting_for_events(*args, **kw):
            context = new_context(*args, **kw)
            context.set_default_timeout(HANG_S * 1000)
            return context
        b.new_page, b.new_context = page_waiting_for_events, context_waiting_for_events
        yield b
        b.close()


@pytest.fixture(autouse=True, scope="module")
def _collect_media_after_module():
    """Free what a test module left behind (scenes, media in exception
    tracebacks) before the next module renders: Dr.Jit dispatches a call
    over every live instance of a plugin type, so stale media would join
    the next module's kernels (slower, and one Dr.Jit 1.5 LLVM assembly
    fault, a callable defined twice, was seen only with them)."""
    yield
    gc.collect()
