"""The floor plan of the package, checked from the source (docs/design.md
section 6c): every module sits on a floor, imports only from its own floor
or below (imports inside functions count too), and no modules import each
other in a circle. A module added on no floor fails here until it is placed."""

import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mi_amr"

#: Floors from the bottom: a module's floor is that of the longest prefix
#: that names it (``mi_amr`` alone is the package's ``__init__``, which
#: registers the plugins and offers the short-cuts of the top floors).
FLOORS = [
    # foundations: no mi-amr import at all; core/ holds the block keys and
    # the Dr.Jit structs every folder above reaches downward
    ["mi_amr._llvm", "mi_amr.parallel", "mi_amr.progress", "mi_amr.params", "mi_amr.memory", "mi_amr.core"],
    # reconstruction methods (host and device halves of tent and nearest)
    ["mi_amr.reconstruction"],
    # data: cells, blocks, files, yt, synthetic data sets, their device copy
    ["mi_amr.data"],
    # transfer functions: the host table, its device tables, the classification
    ["mi_amr.transfer"],
    # host structures: macrocell grids, bricks, trees, hashes, cost model
    ["mi_amr.structures"],
    # their device halves: traversal, sampling, tracking
    ["mi_amr.device"],
    # building the structures a medium asks for
    ["mi_amr.building"],
    # the Mitsuba plugins
    ["mi_amr.plugins"],
    # images, what a picture shows, scene files, Mitsuba's own medium on the same data, test helpers,
    # the annotations and slices that tell what a picture shows (outline, levels, legend)
    ["mi_amr.images", "mi_amr.visibility", "mi_amr.scene_xml", "mi_amr.reference", "mi_amr.testing",
     "mi_amr.annotations", "mi_amr.slicing"],
    # scenes planned from data and written for Mitsuba, the native file written with what they and a medium
    # read first, a run's outputs
    ["mi_amr.autoscene", "mi_amr.scene_writer", "mi_amr.native_file", "mi_amr.series"],
    # services: rendering on a cluster, rendering as a library (and the variant it renders in),
    # the Python API from data to picture, the viewer
    ["mi_amr.distributed", "mi_amr.rendering", "mi_amr.data_scene", "mi_amr.view"],
    # the package's front (plugin registration, short-cuts to the floors below)
    ["mi_amr"],
    # the benchmarks (bench: protocol, scale, resample, peers, view, distributed and their
    # shared harness)
    ["mi_amr.bench"],
    # what a user runs: the command line and its adapters of the library (tools: cli, render,
    # commands, info, gallery; `mi-amr bench` hands over to the benchmarks)
    ["mi_amr.tools"],
]


def modules() -> dict:
    """Dotted module name -> path, for every module of the package."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def imports(name: str, path: Path, known: dict) -> set:
    """The package's modules that ``name`` imports, anywhere in its source."""
    is_package = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in known}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            submodules = {f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in known}
            found |= submodules
            if target in known and len(submodules) < len(node.names):   # names defined in target itself
                found.add(target)
    found.discard(name)
    return found


def floor_of(name: str):
    best, length = None, -1
    for i, prefixes in enumerate(FLOORS):
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and len(p) > length:
                best, length = i, len(p)
    return best


def graph() -> dict:
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def test01_every_module_is_on_a_floor():
    missing = sorted(name for name in modules() if floor_of(name) is None)
    assert not missing, f"modules on no floor (place them in FLOORS): {missing}"


def test02_no_import_runs_up():
    up = sorted(f"{a} (floor {floor_of(a)}) imports {b} (floor {floor_of(b)})"
                for a, targets in graph().items() for b in targets if floor_of(b) > floor_of(a))
    assert not up, "imports that run up:\n" + "\n".join(up)


def test03_no_circles():
    """Tarjan's strongly connected components of the import graph: each a
    single module."""
    g = graph()
    index, low, stack, on, circles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in g[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                circles.append(sorted(part))
    for v in g:
        if v not in index:
            visit(v)
    assert not circles, f"modules that import each other in a circle: {circles}"


def test04_the_check_sees_an_import_that_runs_up(tmp_path):
    """The parser resolves relative imports, at module level and inside
    functions, so an import up cannot hide (a check that cannot fail
    proves nothing)."""
    src = tmp_path / "m.py"
    src.write_text("from ..plugins.medium import AMRMedium\n"
                   "def f():\n    from .. import tools\n    from .blocks import BlockVolume\n")
    known = {"mi_amr.plugins.medium": None, "mi_amr.tools": None, "mi_amr.data.blocks": None}
    found = imports("mi_amr.data.m", src, known)
    assert found == {"mi_amr.plugins.medium", "mi_amr.tools", "mi_amr.data.blocks"}
    assert floor_of("mi_amr.plugins.medium") > floor_of("mi_amr.data.m")
    assert floor_of("mi_amr.tools") > floor_of("mi_amr.data.m")


#: The only imports that may wait inside a function, each with its reason.
#: Everything else is imported at the top of its module: importing any
#: module of the package runs the package's ``__init__`` (Mitsuba, Dr.Jit, numpy
#: and the plugins) anyway, so deferring those saves nothing.
LAZY_IMPORTS = {
    # optional dependencies: a user without the extra still imports the package
    "yt": "the mi-amr[yt] extra, and 1-2 s to import",
    "h5py": "the mi-amr[yt] extra (mi_amr.data.enzo_example writes an Enzo output)",
    "dask": "the mi-amr[distributed] extra",
    "distributed": "the mi-amr[distributed] extra",
    "starlette": "the mi-amr[view] extra",
    "uvicorn": "the mi-amr[view] extra",
    "websockets": "the mi-amr[view] extra",
    "mitsuba_oidn": "the mi-amr[view] extra (the denoiser)",
    "PIL": "the mi-amr[view] extra (JPEG frames)",
    "imageio_ffmpeg": "the mi-amr[movie] extra",
    "playwright": "a test and benchmark dependency (dev extra)",
    "IPython": "notebooks only",
    "eradiate": "a peer of the benchmark, installed apart",
    # start-up time
    "matplotlib": "0.3-0.5 s to import; only plots and colormap presets need it",
    "webbrowser": "only `mi-amr view` opens a browser",
    "mi_amr.view": "the viewer needs the mi-amr[view] extra; other commands do not load it",
    "mi_amr.bench": "`python -m mi_amr.bench` imports only the benchmark it runs",
    # needs a variant
    "mitsuba.ad": "Mitsuba's Python integrators are defined for the variant set at import",
    "mitsuba.python.ad": "the same modules under the name Mitsuba reloads on a variant change",
}


def inner_imports():
    """``(module, line, imported name)`` of every import inside a function."""
    known = modules()
    for name, path in sorted(known.items()):
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for node in ast.walk(fn):
                    if isinstance(node, ast.Import):
                        for a in node.names:
                            yield name, node.lineno, a.name
                    elif isinstance(node, ast.ImportFrom):
                        if node.level:
                            is_package = path.name == "__init__.py"
                            base = name.split(".") if is_package else name.split(".")[:-1]
                            base = base[:len(base) - (node.level - 1)]
                            target = ".".join(base + ([node.module] if node.module else []))
                        else:
                            target = node.module
                        for a in node.names:        # ``from . import x``: the submodule counts
                            sub = f"{target}.{a.name}"
                            yield name, node.lineno, sub if sub in known else target


def lazy_reason(target: str):
    for prefix, reason in LAZY_IMPORTS.items():
        if target == prefix or target.startswith(prefix + "."):
            return reason
    return None


def test05_imports_wait_inside_functions_only_with_a_reason():
    """docs/design.md section 6c: an import inside a function is one of
    `LAZY_IMPORTS` (an optional dependency, start-up time, a variant);
    the rest sit at the top of their modules."""
    bad = [f"{m}:{line} imports {t} inside a function" for m, line, t in inner_imports() if lazy_reason(t) is None]
    assert not bad, "imports inside functions without a reason (move them to the top):\n" + "\n".join(bad)


def test06_the_lazy_check_sees_an_inner_import(tmp_path, monkeypatch):
    """The same check on a planted module: an inner import of numpy is
    flagged, one of yt is allowed."""
    pkg = tmp_path / "mi_amr"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "m.py").write_text("def f():\n    import numpy\n    import yt\n    from . import view\n")
    (pkg / "view.py").write_text("")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    found = [(m, t, lazy_reason(t)) for m, _, t in inner_imports()]
    assert ("mi_amr.m", "numpy", None) in found
    assert ("mi_amr.m", "yt", LAZY_IMPORTS["yt"]) in found
    assert ("mi_amr.m", "mi_amr.view", LAZY_IMPORTS["mi_amr.view"]) in found


def folder_of(name: str) -> str:
    """The folder (sub-package) a module sits in, or the module itself for
    one at the package's top (``mi_amr.rendering``) and the package's front."""
    parts = name.split(".")
    return ".".join(parts[:2]) if len(parts) > 2 or (PACKAGE / parts[-1]).is_dir() else name


def test07_a_folder_is_one_floor():
    """Folders are floors: every module of a folder sits on the folder's
    floor (no FLOORS entry splits a folder), so the floor plan can be read
    from the folders themselves."""
    split = sorted(f"{name} (floor {floor_of(name)}) in {folder_of(name)} (floor {floor_of(folder_of(name))})"
                   for name in modules() if floor_of(name) != floor_of(folder_of(name)))
    assert not split, "modules off their folder's floor:\n" + "\n".join(split)


def test08_no_folder_imports_up_or_in_a_circle():
    """Between folders: no import runs up a floor and no two folders import
    each other (directly or round a circle), counted over every import,
    inside functions too."""
    edges = {}
    for a, targets in graph().items():
        for b in targets:
            fa, fb = folder_of(a), folder_of(b)
            if fa != fb and fb != "mi_amr":
                edges.setdefault(fa, set()).add(fb)
    up = sorted(f"{a} -> {b}" for a, bs in edges.items() for b in bs if floor_of(b) > floor_of(a))
    assert not up, "folders importing up:\n" + "\n".join(up)
    mutual = sorted(f"{a} <-> {b}" for a, bs in edges.items() for b in bs if a in edges.get(b, ()) and a < b)
    assert not mutual, "folders importing each other:\n" + "\n".join(mutual)
