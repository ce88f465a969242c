"""The floor plan of the package, checked from the source (docs/design.md
section 6c): every module sits on a floor, imports only from its own floor
or below (imports inside functions count too), and no modules import each
other in a circle. A module added on no floor fails here until it is placed."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mi_amr"

#: Floors from the bottom: a module's floor is that of the longest prefix
#: that names it (``mi_amr`` alone is the package's ``__init__``, which
#: registers the plugins and offers the short-cuts of the top floors).
FLOORS = [
    # foundations: no mi-amr import at all
    ["mi_amr._llvm", "mi_amr.parallel", "mi_amr.progress", "mi_amr.params", "mi_amr.memory"],
    # cells and their integer bookkeeping
    ["mi_amr.data.block_keys", "mi_amr.data.cells", "mi_amr.data.metadata"],
    # reconstruction methods (host and device halves of tent and nearest)
    ["mi_amr.reconstruction"],
    # data: blocks, files, yt, synthetic data sets
    ["mi_amr.data"],
    # device arrays of the data, Dr.Jit structs, transfer function tables
    ["mi_amr.device.values", "mi_amr.device.structs", "mi_amr.transfer.function"],
    # host structures: macrocell grids, bricks, trees, hashes, cost model
    ["mi_amr.structures"],
    # their device halves: traversal, sampling, tracking
    ["mi_amr.device"],
    # classification: TF and density scale on the device
    ["mi_amr.transfer"],
    # building the structures a medium asks for
    ["mi_amr.builds", "mi_amr.strategies", "mi_amr.pipeline"],
    # the Mitsuba plugins
    ["mi_amr.plugins"],
    # images, scene files, the native file, test helpers
    ["mi_amr.images", "mi_amr.scene_xml", "mi_amr.native_file", "mi_amr.testing"],
    # scenes planned from data, a run's outputs
    ["mi_amr.autoscene", "mi_amr.series"],
    # the package's front (plugin registration, short-cuts)
    ["mi_amr"],
    # services: rendering on a cluster, the viewer, render jobs and their frames
    ["mi_amr.distributed", "mi_amr.view", "mi_amr.render"],
    # what a user runs: the command line (tools), the benchmarks (bench: protocol, scale,
    # resample, peers, view, distributed and their shared harness)
    ["mi_amr.tools", "mi_amr.bench"],
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
