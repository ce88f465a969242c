"""The floor plan of the package, checked from the source (docs/design.md
section 6c): every module sits on a floor, imports only from its own floor
or below (imports inside functions count too), and no modules import each
other in a circle. A module added on no floor fails here until it is placed
(test09 proves it on a planted module), and the folders are read from the
tree: a folder the table does not name fails test07 (test10)."""

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mi_amr"

#: Floors from the bottom. An entry names a folder (every module in it) or
#: one module; a module's floor is that of the longest entry that names it
#: (`covers`). ``mi_amr`` names the package's ``__init__`` alone, which
#: registers the plugins and offers the short-cuts of the top floors: a
#: module at the top of the package is on no floor until it is listed.
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
    # services: rendering on a cluster, adaptive sampling and denoising, rendering as a library (and the
    # variant it renders in),
    # the Python API from data to picture, the viewer
    ["mi_amr.distributed", "mi_amr.adaptive", "mi_amr.denoising", "mi_amr.rendering", "mi_amr.data_scene",
     "mi_amr.view"],
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


def covers(entry: str, name: str) -> bool:
    """Whether the `FLOORS` entry ``entry`` names the module ``name``: the
    module itself, or a module in the folder ``entry`` (the package's own
    name covers its ``__init__`` only, never the modules beside it)."""
    return name == entry or (entry != PACKAGE.name and name.startswith(entry + "."))


def floor_of(name: str, floors=None):
    """The floor (index into ``floors``, default `FLOORS`) of the longest
    entry that names ``name``; None when no entry does."""
    best, length = None, -1
    for i, entries in enumerate(FLOORS if floors is None else floors):
        for p in entries:
            if covers(p, name) and len(p) > length:
                best, length = i, len(p)
    return best


def unplaced(names, floors=None) -> list:
    """The modules among ``names`` that no entry of ``floors`` names."""
    return sorted(name for name in names if floor_of(name, floors) is None)


def graph() -> dict:
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def test01_every_module_is_on_a_floor():
    missing = unplaced(modules())
    assert not missing, f"modules on no floor (place them in FLOORS): {', '.join(missing)}"


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


def folders() -> list:
    """The package's folders that hold Python modules, dotted, read from the
    tree (``mi_amr.data``, ...; a folder of page files such as
    ``view/static`` holds none)."""
    return sorted({".".join(path.relative_to(PACKAGE.parent).parent.parts) for path in PACKAGE.rglob("*.py")}
                  - {PACKAGE.name})


def floor_plan_problems(floors=None) -> list:
    """What keeps the folders of the tree from being floors of ``floors``
    (default `FLOORS`): a folder no entry names as a whole, an entry that
    names a module inside a folder (it would split the folder), an entry
    that names nothing in the tree, a module off its folder's floor."""
    floors = FLOORS if floors is None else floors
    entries = [p for row in floors for p in row]
    known, dirs = modules(), folders()
    problems = [f"folder {d} is on no floor (name it in FLOORS)" for d in dirs if d not in entries]
    problems += [f"{p} names a module inside the folder {folder_of(p)} (name the folder)"
                 for p in entries if p not in dirs and folder_of(p) != p]
    problems += [f"{p} names no module or folder of the tree" for p in entries if p not in known]
    problems += [f"{name} (floor {floor_of(name, floors)}) in {folder_of(name)} "
                 f"(floor {floor_of(folder_of(name), floors)})"
                 for name in known if floor_of(name, floors) != floor_of(folder_of(name), floors)]
    return sorted(problems)


def test07_a_folder_is_one_floor():
    """Folders are floors, read from the tree: every folder holding modules
    is named whole on one floor, no entry splits a folder or names what is
    not there, so every module of a folder sits on the folder's floor and
    the floor plan can be read from the folders themselves."""
    problems = floor_plan_problems()
    assert not problems, "the folders are not the floors:\n" + "\n".join(problems)


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


def _planted_package(tmp_path, monkeypatch, files) -> Path:
    """A package ``mi_amr`` of empty ``files`` (paths inside it) under
    ``tmp_path``, made the package this module checks."""
    pkg = tmp_path / "mi_amr"
    for f in ("__init__.py", *files):
        (pkg / f).parent.mkdir(parents=True, exist_ok=True)
        (pkg / f).write_text("")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    return pkg


def test09_a_module_on_no_floor_fails_with_its_name(tmp_path, monkeypatch):
    """test01 on a planted package: a new module at the package's top
    (``mi_amr.brand_new``, which the prefix ``mi_amr`` must not place)
    fails it, named; a new module in a folder lands on the folder's floor;
    the same module added to a copy of the table passes."""
    _planted_package(tmp_path, monkeypatch, ["rendering.py", "data/__init__.py", "data/cells.py",
                                             "data/brand_new_reader.py", "brand_new.py"])
    floors = [["mi_amr.data"], ["mi_amr.rendering"], ["mi_amr"]]
    monkeypatch.setattr(sys.modules[__name__], "FLOORS", floors)
    with pytest.raises(AssertionError, match=r"(?m)^modules on no floor \(place them in FLOORS\): mi_amr\.brand_new$"):
        test01_every_module_is_on_a_floor()
    assert floor_of("mi_amr.data.brand_new_reader") == floor_of("mi_amr.data") == 0
    placed = [list(row) for row in floors]
    placed[1].append("mi_amr.brand_new")
    monkeypatch.setattr(sys.modules[__name__], "FLOORS", placed)
    test01_every_module_is_on_a_floor()
    assert floor_of("mi_amr.brand_new") == 1 and floors[1] == ["mi_amr.rendering"]     # the table itself unchanged


def test10_a_folder_the_table_does_not_name_fails(tmp_path, monkeypatch):
    """test07 on a planted tree: a new folder is read from the tree and fails
    until it is named; an entry that splits a folder, or names nothing,
    fails too."""
    _planted_package(tmp_path, monkeypatch, ["data/__init__.py", "data/cells.py", "fresh/__init__.py",
                                             "fresh/walk.py", "view/static/page.js"])
    assert folders() == ["mi_amr.data", "mi_amr.fresh"]
    monkeypatch.setattr(sys.modules[__name__], "FLOORS", [["mi_amr.data"], ["mi_amr"]])
    with pytest.raises(AssertionError, match="folder mi_amr.fresh is on no floor"):
        test07_a_folder_is_one_floor()
    assert floor_plan_problems([["mi_amr.data", "mi_amr.fresh"], ["mi_amr"]]) == []
    assert floor_plan_problems([["mi_amr.data", "mi_amr.fresh"], ["mi_amr.fresh.walk", "mi_amr"]]) == [
        "mi_amr.fresh.walk (floor 1) in mi_amr.fresh (floor 0)",
        "mi_amr.fresh.walk names a module inside the folder mi_amr.fresh (name the folder)"]
    assert floor_plan_problems([["mi_amr.data", "mi_amr.fresh", "mi_amr.gone"], ["mi_amr"]]) == [
        "mi_amr.gone names no module or folder of the tree"]
