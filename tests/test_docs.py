"""The manual's Python examples and the notebooks run as written, and the
words around the code keep up with it: cited paths, doc sections, dotted
names and test numbers exist, test names are unique, the manual's parameter
tables match what the plugins accept, every image the README and the docs
show is in the repository, and the manual (MkDocs, docs/) builds with no
warning."""

import ast
import json
import os
import re
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from test_readme import PAGES as FRESH_PROCESS_PAGES       # every block in a fresh process of its own

ROOT = Path(__file__).resolve().parents[1]


#: The manual's pages with Python examples, in the order their examples run
#: (one namespace: the transfer-function page changes the medium's scene).
EXAMPLE_PAGES = ("docs/manual/medium.md", "docs/manual/cluster.md", "docs/manual/transfer-functions.md")


def test01_manual_python_examples_run():
    """Every ```python block of the manual's pages, in order, in one
    namespace (README.md and the Python page run block by block in fresh
    processes: tests/test_readme.py)."""
    blocks = [(page, b) for page in EXAMPLE_PAGES
              for b in re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)]
    assert len(blocks) >= 4, [page for page, _ in blocks]
    others = [p.relative_to(ROOT).as_posix() for p in sorted((ROOT / "docs" / "manual").glob("*.md"))
              if "```python" in p.read_text()
              and p.relative_to(ROOT).as_posix() not in EXAMPLE_PAGES + FRESH_PROCESS_PAGES]
    assert not others, f"Python examples that no test runs: {others}"
    ns = {}
    exec(compile(blocks[0][1], blocks[0][0], "exec"), ns)
    img = np.array(ns["image"])
    assert img.shape == (128, 128, 3) and np.isfinite(img).all() and img[..., 0].std() > 0.01
    for page, block in blocks[1:]:
        exec(compile(block, page, "exec"), ns)
    med = ns["mi_amr"].amr_media(ns["scene"])[0]
    assert med.density_scale == 200.0 and med.tf.rgba[:, 3].max() == 1.0


#: Runs a notebook's code cells in order in a fresh interpreter, as a new
#: Jupyter kernel would (no state left by other tests: the frozen preview
#: counts its recordings, which objects alive from earlier tests can change).
_RUN_NOTEBOOK = """
import json, sys
import matplotlib
matplotlib.use("Agg")
nb = json.load(open(sys.argv[1]))
ns = {"__name__": "__main__"}
for cell in nb["cells"]:
    if cell["cell_type"] == "code":
        exec(compile("".join(cell["source"]), sys.argv[1], "exec"), ns)
"""


#: Notebooks run in the default suite; the others run with marker ``slow``
#: (quickstart.ipynb runs in a real Jupyter kernel in tests/test_widget.py
#: test04 by default, its widget included; inverse.ipynb's gradients are
#: tests/test_gradients.py's by default).
FAST_NOTEBOOKS = {"view.ipynb"}
#: Set for every notebook run here: a notebook with a size switch (inverse.ipynb) runs at its
#: small size; the committed outputs are those of the full size.
SMALL_NOTEBOOKS = {"MI_AMR_NOTEBOOK_SMALL": "1"}


@pytest.mark.parametrize("name", [n if n in FAST_NOTEBOOKS else pytest.param(n, marks=pytest.mark.slow)
                                  for n in sorted(p.name for p in (ROOT / "notebooks").glob("*.ipynb"))])
def test02_notebooks_run_top_to_bottom(name):
    import subprocess
    import sys
    path = ROOT / "notebooks" / name
    nb = json.loads(path.read_text())
    for cell in nb["cells"]:                   # a package it imports is missing (ipywidgets): skipped
        if cell["cell_type"] == "code":
            for node in ast.walk(ast.parse("".join(cell["source"]))):
                mods = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                        [node.module] if isinstance(node, ast.ImportFrom) and not node.level else [])
                for mod in mods:
                    pytest.importorskip(mod.split(".")[0])
    r = subprocess.run([sys.executable, "-c", _RUN_NOTEBOOK, str(path)], capture_output=True, text=True,
                       timeout=600, cwd=ROOT / "notebooks", env={**os.environ, **SMALL_NOTEBOOKS})
    assert r.returncode == 0, f"{name} failed:\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}"


def _local_images(md: Path) -> list:
    """The repository files a Markdown file shows (images and <img> tags with
    relative paths, resolved against the file's folder)."""
    src = md.read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", src) + re.findall(r'<img[^>]*src="([^"]+)"', src)
    return [(link, (md.parent / link).resolve()) for link in links if not link.startswith(("http://", "https://"))]


def test03_every_image_the_readme_and_the_docs_link_is_in_the_repository():
    """Markdown images and <img> tags with relative paths in the README and
    every doc; the front page shows a picture under 150 kB, the gallery's
    PNGs (at least four, in the manual) stay under 200 kB."""
    images = ROOT / "docs" / "images"
    front = _local_images(ROOT / "README.md")
    assert [p for _, p in front if p.parent == images], f"README.md shows no picture of docs/images: {front}"
    for link, path in front:
        assert path.is_file(), f"README links {link}, which is not in the repository"
        assert path.stat().st_size < 150_000, f"README.md: {link}: {path.stat().st_size} bytes"
    manual = {p for md in sorted((ROOT / "docs" / "manual").glob("*.md")) for _, p in _local_images(md)}
    assert len([p for p in manual if p.parent == images]) >= 4, sorted(manual)
    for md in sorted((ROOT / "docs").glob("**/*.md")):
        for link, path in _local_images(md):
            assert path.is_file(), f"{md.relative_to(ROOT)} links {link}, which is not in the repository"
            if path.parent == images:
                assert path.stat().st_size < 200_000, f"{link}: {path.stat().st_size} bytes"


# ---- Words that keep: names, references and tables that follow the code ----
# Cheap checks (text and `ast` only, no Dr.Jit kernel): a renamed module, a
# moved function, a renumbered doc section or a parameter added to the parser
# fails here instead of leaving a stale word behind.

def _text_files():
    """The package, the plugin shim, the tests, the tools and every doc."""
    files = [ROOT / "README.md", ROOT / "Makefile"]
    for pattern in ("mi_amr/**/*.py", "plugins/*.py", "tests/*.py", "tools/*", "docs/**/*.md"):
        files += sorted(p for p in ROOT.glob(pattern) if p.is_file() and p.suffix not in (".png", ".json"))
    return [f for f in files if f != Path(__file__).resolve()]      # this file's examples are placeholders


def _module_path(parts):
    """The source file of the module ``.``.join(parts), or None."""
    base = ROOT.joinpath(*parts)
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _defined_names(body):
    """Names a module or class body defines: defs, classes, assignments,
    imports (name -> the node that defines it)."""
    names = {}
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names[node.name] = node
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                for n in ast.walk(target):
                    if isinstance(n, ast.Name):
                        names[n.id] = node
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                names[(alias.asname or alias.name).split(".")[0]] = node
        elif isinstance(node, (ast.If, ast.Try)):
            names.update(_defined_names(node.body))
    return names


@lru_cache(maxsize=None)
def _tree(path: Path) -> ast.Module:
    """A source file parsed once (references to it are many)."""
    return ast.parse(path.read_text())


@lru_cache(maxsize=None)
def _resolves(dotted: str) -> bool:
    """Whether ``mi_amr.a.b.c`` names a module, or a name defined in one
    (followed through ``from .x import name``), or a class attribute."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        path = _module_path(parts[:i])
        if path is not None:
            break
    else:
        return False
    attrs = parts[i:]
    if not attrs:
        return True
    node = _defined_names(_tree(path).body).get(attrs[0])
    if isinstance(node, ast.ImportFrom):                 # follow it to where it is defined
        pkg = parts[:i] if path.name == "__init__.py" else parts[:i - 1]
        mod = (pkg[:len(pkg) - node.level + 1] if node.level else []) + (node.module or "").split(".")
        alias = next(a for a in node.names if (a.asname or a.name) == attrs[0])
        return _resolves(".".join([m for m in mod if m] + [alias.name] + attrs[1:]))
    if node is None:
        return False
    if len(attrs) == 1:
        return True
    if not isinstance(node, ast.ClassDef):
        return False
    members = _defined_names(node.body)
    for fn in node.body:                        # attributes set on self in the methods
        if isinstance(fn, ast.FunctionDef):
            for n in ast.walk(fn):
                if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "self":
                    members.setdefault(n.attr, n)
    return attrs[1] in members and len(attrs) == 2


def _headings(md: Path) -> set:
    """Section numbers of a Markdown file's headings (``## 5b. Minorants`` -> 5b)."""
    return set(re.findall(r"^#+\s+(\d+[a-z]?)[.\s]", md.read_text(), re.M))


_SECTIONS = re.compile(r"sections?\s+(\d+[a-z]?(?:(?:,\s*|\s+and\s+)\d+[a-z]?(?![\d.]))*)")
_DOC_SECTION = re.compile(r"(docs/[\w./-]+\.md)[,\s#:]*" + _SECTIONS.pattern)
_PATH = re.compile(r"\b((?:docs|mi_amr|tests|tools|scenes|notebooks|plugins)/[\w./*-]*[\w*])")
_DOTTED = re.compile(r"\bmi_amr(?:\.[A-Za-z_]\w*)+")
_TEST_AFTER = re.compile(r"tests/(test_\w+)\.py`?[\s,;:]+((?:test\d+[a-z]*\b(?:,\s*|\s+and\s+)?)+)")
_TEST_BEFORE = re.compile(r"\b(test\d+[a-z]*)\s+(?:of|in)\s+(?:tests/)?(test_\w+?)(?:\.py)?\b")


def test04_every_reference_resolves():
    """Every repository path (``docs/...md``, ``mi_amr/...py``, ...), every
    ``docs/X.md section N`` (and, inside a doc, every bare ``section N`` of
    that doc), every ``mi_amr.x.y`` dotted name and every numbered test
    (``tests/test_x.py test03``, ``test03 of test_x``) cited in the package,
    the tests, the tools and the docs exists."""
    bad = []
    for f in _text_files():
        text = f.read_text(errors="replace")
        rel = f.relative_to(ROOT)
        for p in set(_PATH.findall(text)):
            p = p.rstrip(".")
            if re.search(r"[A-Z]{3,}", p):              # placeholders: docs/images/NAME.png
                continue
            if not (any(ROOT.glob(p)) if "*" in p else (ROOT / p).exists()):
                bad.append(f"{rel}: path {p}")
        for doc, nums in _DOC_SECTION.findall(text):
            if (ROOT / doc).is_file():
                missing = set(re.findall(r"\d+[a-z]?", nums)) - _headings(ROOT / doc)
                bad += [f"{rel}: {doc} section {n}" for n in sorted(missing)]
        if f.suffix == ".md":
            own = _headings(f)
            cited = [m.span() for m in _DOC_SECTION.finditer(text)]
            for m in _SECTIONS.finditer(text):
                if own and not any(a <= m.start() < b for a, b in cited):
                    bad += [f"{rel}: section {n}" for n in re.findall(r"\d+[a-z]?", m.group(1)) if n not in own]
        made_here = set()                  # module names a file makes itself (sys.modules[name] = ...)
        if f.suffix == ".py":
            made_here = {n.value for n in ast.walk(ast.parse(text))
                         if isinstance(n, ast.Constant) and isinstance(n.value, str) and _DOTTED.fullmatch(n.value)}
        for name in set(_DOTTED.findall(text)) - made_here:
            if not _resolves(name):
                bad.append(f"{rel}: {name}")
        cited = [(f, re.findall(r"test\d+[a-z]*", tests)) for f, tests in _TEST_AFTER.findall(text)]
        cited += [(f, [t]) for t, f in _TEST_BEFORE.findall(text)]
        for name, tests in cited:
            path = ROOT / "tests" / f"{name}.py"
            have = set(re.findall(r"^def (test\d+[a-z]*)_", path.read_text(), re.M)) if path.is_file() else set()
            bad += [f"{rel}: {t} of tests/{name}.py" for t in tests if t not in have]
    assert not bad, "stale references:\n" + "\n".join(sorted(bad))


def test05_test_names_are_unique_within_each_file():
    """No two test functions of a file share a name (the second would hide
    the first) or a number (``test05_...`` twice reads as one test)."""
    bad = []
    for f in sorted((ROOT / "tests").glob("test_*.py")):
        names = [n.name for n in ast.walk(ast.parse(f.read_text()))
                 if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name.startswith("test")]
        numbers = [m.group(0) for m in map(re.compile(r"test\d+[a-z]*(?=_|$)").match, names) if m]
        for label, items in (("name", names), ("number", numbers)):
            bad += [f"{f.name}: {label} {x} x{items.count(x)}" for x in sorted(set(items)) if items.count(x) > 1]
    assert not bad, "\n".join(bad)


def _doc_table(page: str, heading: str) -> set:
    """The names in the first column of the first table after ``heading`` in ``page``."""
    src = (ROOT / page).read_text()
    start = src.index(heading)
    rows = re.search(r"\n(\|.*\|\n)+", src[start:]).group(0).strip().splitlines()[2:]
    names = set()
    for row in rows:
        cell = row.split("|")[1]
        if not cell.strip().startswith("("):              # "(nested)" phase function
            names |= set(re.findall(r"`([^`]+)`", cell))
    return names


def _docstring_table(path: str, cls: str) -> set:
    """The parameter names of a plugin class's ``.. pluginparameters::`` table."""
    tree = ast.parse((ROOT / path).read_text())
    doc = next(ast.get_docstring(n) for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls)
    table = doc.split(".. pluginparameters::", 1)[1]
    names = set()
    for entry in re.findall(r"^\s*\* - (.+)$", table, re.M):
        if not entry.strip().startswith("("):              # "(nested phase function)"
            names |= {n.strip() for n in entry.split(",")}
    return names


def _known_set(path: str, name: str) -> set:
    """A module-level set literal ``name = {...}`` (or frozenset({...})), read without importing."""
    tree = ast.parse((ROOT / path).read_text())
    node = next(n for n in tree.body if isinstance(n, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == name for t in n.targets))
    return set(ast.literal_eval(node.value.args[0] if isinstance(node.value, ast.Call) else node.value))


@pytest.mark.parametrize("page,heading,module,cls", [
    ("docs/manual/medium.md", "## Parameters of `amr`", "mi_amr/plugins/options.py", "AMRMedium"),
    ("docs/manual/integrator.md", "# The `amrvolpath` integrator", "mi_amr/plugins/integrator.py",
     "AMRVolpathIntegrator"),
    ("docs/manual/integrator.md", "## The differentiable `amrprbvolpath`", "mi_amr/plugins/prb_integrator.py",
     "AMRPRBVolpathIntegrator"),
])
def test06_manual_parameter_tables_match_the_parsers(page, heading, module, cls):
    """The manual's parameter table of each plugin names exactly the
    parameters its parser accepts (`KNOWN`, given to `check_known`), and so
    does the plugin docstring's ``.. pluginparameters::`` table."""
    known = _known_set(module, "KNOWN")
    doc_path = "mi_amr/plugins/medium.py" if cls == "AMRMedium" else module
    assert _doc_table(page, heading) == known, f"{page} ({heading}) against {module} KNOWN"
    assert _docstring_table(doc_path, cls) == known, f"{doc_path} {cls} docstring against {module} KNOWN"


def test07_manual_builds_strictly_with_no_warning(tmp_path):
    """``mkdocs build --strict`` (what ``make docs`` runs) into a temporary
    folder: a broken link, a missing anchor, a page left out of the nav or an
    API reference that does not resolve fails it, and any other warning in
    its log fails this test. mkdocstrings reads the source (griffe): nothing
    is imported, so it takes about two seconds."""
    import subprocess
    import sys
    for mod in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        pytest.importorskip(mod)
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                        "-d", str(tmp_path / "site")], capture_output=True, text=True, timeout=300, cwd=ROOT,
                       env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    log = r.stdout + r.stderr
    assert r.returncode == 0, log[-4000:]
    warnings = [line for line in log.splitlines() if re.search(r"\bWARNING\b|\bERROR\b", line)]
    assert not warnings, "\n".join(warnings)
    pages = {p.relative_to(tmp_path / "site").as_posix() for p in (tmp_path / "site").glob("**/index.html")}
    assert {"manual/medium/index.html", "api/index.html"} <= pages, sorted(pages)
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "TransferFunction" in api and "AMRCells" in api, "the API reference is empty"
