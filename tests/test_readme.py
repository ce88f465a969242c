"""The README and the Python page of the manual run as written, each
```python block in a fresh Python started in the repository's root, as a
new user would paste it: no variant set, nothing imported before, no state
of another block (docs/manual/python.md). And the front door's choice of
a Mitsuba variant (`mi_amr.rendering.use_variant`): the variant
``mi-amr render`` would choose when none is set, said in one line; the
user's variant respected; a variant the plugins cannot render in refused in
one line.

A block that cannot run on its own (it needs a cluster, a file the
repository does not hold...) says so in the text, on the line before its
fence: ``<!-- not standalone: REASON -->``; it is compiled here, not run,
and the reason is required, so no block is skipped silently."""

import json
import os
import re
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The pages whose Python blocks run here, each block in a fresh process.
PAGES = ("README.md", "docs/manual/python.md")

#: The mark of a block that cannot run standalone, on the line before its fence.
NOT_STANDALONE = re.compile(r"<!--\s*not standalone:\s*(.*?)\s*-->\s*$")

#: The line `use_variant` says when it chooses the variant itself.
CHOSEN = "mi-amr: rendering in Mitsuba's "


def python_blocks(text: str) -> list:
    """``(line, source, reason)`` of every ```python block of a Markdown
    text: its first line (1-based), its code, and the reason given by a
    ``<!-- not standalone: ... -->`` line just before the fence (None: it
    runs standalone)."""
    lines, blocks, i = text.splitlines(), [], 0
    while i < len(lines):
        if re.match(r"^```python\s*$", lines[i]):
            end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
            mark = NOT_STANDALONE.match(lines[i - 1].strip()) if i else None
            blocks.append((i + 2, "\n".join(lines[i + 1:end]) + "\n", mark.group(1) if mark else None))
            i = end
        i += 1
    return blocks


def all_blocks() -> list:
    return [(page, line, src, reason) for page in PAGES
            for line, src, reason in python_blocks((ROOT / page).read_text())]


#: Runs one block (argv[1]: its source, argv[2]: its name) as ``__main__``,
#: then prints what it left: every picture (a 3-D array) with its shape,
#: whether all is finite and its spread, and the class of every widget.
_RUN_BLOCK = r"""
import json, sys
import numpy as np
ns = {"__name__": "__main__"}
exec(compile(sys.argv[1], sys.argv[2], "exec"), ns)
left = {}
for name, value in ns.items():
    if isinstance(value, np.ndarray) and value.ndim == 3:
        a = np.asarray(value, np.float64)
        left[name] = {"shape": list(a.shape), "finite": bool(np.isfinite(a).all()), "std": float(a.std())}
    elif type(value).__name__.endswith("Widget"):
        left[name] = {"widget": type(value).__name__}
print("BLOCK-LEFT " + json.dumps(left))
"""


@lru_cache(maxsize=None)
def run_block(src: str, name: str) -> tuple:
    """``(completed process, what the block left)`` of ``src`` in a fresh
    Python in the repository's root (once per block: test02 reads test01's run)."""
    r = subprocess.run([sys.executable, "-c", _RUN_BLOCK, src, name], capture_output=True, text=True,
                       timeout=600, cwd=ROOT, env={**os.environ, "MPLBACKEND": "Agg"})
    left = [ln for ln in r.stdout.splitlines() if ln.startswith("BLOCK-LEFT ")]
    return r, json.loads(left[-1].split(" ", 1)[1]) if left else None


@pytest.mark.parametrize("page,line,src,reason", all_blocks(), ids=[f"{b[0]}:{b[1]}" for b in all_blocks()])
def test01_every_python_block_runs_standalone(page, line, src, reason):
    """Each block in a fresh process: it exits 0 with no traceback, every
    picture it leaves is finite and not blank, and it says which variant it
    chose at most once. A block marked not standalone compiles, with a
    reason."""
    name = f"{page}:{line}"
    if reason is not None:
        assert reason, f"{name}: a block marked not standalone says why"
        compile(src, name, "exec")
        return
    r, left = run_block(src, name)
    assert r.returncode == 0 and left is not None, f"{name} failed:\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}"
    assert "Traceback" not in r.stderr, f"{name}:\n{r.stderr[-4000:]}"
    for var, what in left.items():
        if "shape" in what:
            assert what["finite"] and what["std"] > 1e-4, f"{name}: {var} is not a picture: {what}"
    said = [ln for ln in r.stderr.splitlines() if ln.startswith(CHOSEN)]
    assert len(said) <= 1, f"{name}: the variant was said {len(said)} times:\n{r.stderr}"


def test02_the_readme_front_door_needs_no_variant():
    """The README's first Python block never names Mitsuba, and in a fresh
    process it leaves a picture (finite, not blank) and a widget, having said
    in one line which variant it chose; every page's blocks are found (a
    changed fence or a block lost would pass test01 with nothing run)."""
    blocks = all_blocks()
    assert {page for page, *_ in blocks} == set(PAGES), [b[:2] for b in blocks]
    page, line, src, reason = blocks[0]
    assert page == "README.md" and reason is None
    assert "mitsuba" not in src and "set_variant" not in src, src
    r, left = run_block(src, f"{page}:{line}")
    assert r.returncode == 0, r.stderr[-4000:]
    pictures = [w for w in left.values() if "shape" in w]
    assert pictures and all(p["shape"][2] == 3 and p["finite"] and p["std"] > 1e-4 for p in pictures), left
    assert [w["widget"] for w in left.values() if "widget" in w] == ["ViewWidget"], left
    said = [ln for ln in r.stderr.splitlines() if ln.startswith(CHOSEN)]
    assert len(said) == 1 and re.fullmatch(CHOSEN + r"(cuda|llvm)_ad_rgb \(.*\)", said[0]), r.stderr


def test03_the_block_reader_sees_fences_and_marks():
    """`python_blocks` on a planted page: plain and marked blocks, other
    languages left out, the mark's reason read (a reader that found nothing
    would let test01 pass having run nothing)."""
    text = ("# t\n```python\na = 1\n```\n\n```sh\nls\n```\n"
            "<!-- not standalone: needs a Dask scheduler -->\n```python\nclient.close()\n```\n")
    assert python_blocks(text) == [(3, "a = 1\n", None), (11, "client.close()\n", "needs a Dask scheduler")]


#: The variant checks, in one fresh process (they set the process's variant).
_VARIANTS = r"""
import sys, tempfile
import drjit as dr
import mitsuba as mi
import mi_amr
from mi_amr.rendering import RenderJob, default_variant, render_jobs
from mi_amr.tools.cli import main

CLOUD = "scenes/data/cloud.cells"


def refused(call, *words):
    try:
        call()
    except ValueError as e:
        msg = str(e)
        assert "\n" not in msg and all(w in msg for w in words), msg
        return msg
    raise AssertionError(f"not refused: {words}")


# open_data and plan_scene need no variant, and set none
volume, extent, what = mi_amr.open_data(CLOUD)
mi_amr.plan_scene(volume)
assert mi.variant() is None, mi.variant()

# a variant given that is missing or that the plugins refuse: one line, nothing changes
refused(lambda: mi_amr.scene(CLOUD, variant="scalar_rgb"), "scalar_rgb", "scalar variants are refused")
refused(lambda: mi_amr.scene(CLOUD, variant="nosuch_rgb"), "nosuch_rgb", "not available")
refused(lambda: render_jobs([], variant="llvm_ad_mono_polarized"), "polarized variants are refused")
assert mi.variant() is None, mi.variant()

# the command line with no --variant renders in the variant the library chooses
with tempfile.TemporaryDirectory() as tmp:
    assert main(["render", CLOUD, "-o", f"{tmp}/c.exr", "--res", "8", "--spp", "1", "-q"]) == 0
assert mi.variant() == default_variant(), (mi.variant(), default_variant())

# a variant set before is respected by scene, scene_for and render_jobs; variant= sets another
mi.set_variant("llvm_ad_mono")
sc = mi_amr.scene(CLOUD, res=8, spp=1)
mi_amr.scene_for(CLOUD)
render_jobs([])
assert mi.variant() == "llvm_ad_mono", mi.variant()
mi_amr.scene(CLOUD, res=8, spp=1, variant="llvm_ad_rgb")
assert mi.variant() == "llvm_ad_rgb", mi.variant()

# a variant set before that the plugins cannot render in: refused in one line, not replaced
mi.set_variant("scalar_rgb")
refused(lambda: mi_amr.scene(CLOUD), "scalar_rgb")
refused(lambda: sc.render(), "scalar_rgb")
refused(lambda: render_jobs([RenderJob(CLOUD, res=8, spp=1)]), "scalar_rgb")
assert mi.variant() == "scalar_rgb"

# the choice follows Dr.Jit's backends: CUDA first, else LLVM, else one line
real = dr.has_backend
assert default_variant() == ("cuda_ad_rgb" if real(dr.JitBackend.CUDA) else "llvm_ad_rgb")
try:
    dr.has_backend = lambda b: True
    assert default_variant() == "cuda_ad_rgb"
    dr.has_backend = lambda b: b == dr.JitBackend.LLVM
    assert default_variant() == "llvm_ad_rgb"
    dr.has_backend = lambda b: False
    try:
        default_variant()
        raise AssertionError("no backend: not refused")
    except OSError as e:
        assert "\n" not in str(e) and "libLLVM" in str(e), e
finally:
    dr.has_backend = real
print("VARIANTS-OK")
"""


def test04_the_variant_when_none_is_set():
    """In a fresh process: `open_data` and `plan_scene` set no variant; a
    missing or refused ``variant=`` is one line and changes nothing;
    ``mi-amr render`` with no ``--variant`` renders in `default_variant`; a
    variant set before (``llvm_ad_mono``) is kept by `scene`, `scene_for`
    and `render_jobs`, ``variant=`` replaces it; a scalar variant set
    before is refused by them in one line; `default_variant` is
    ``cuda_ad_rgb`` where Dr.Jit has the CUDA backend, else ``llvm_ad_rgb``,
    else a one-line `OSError`. The library itself said nothing (the
    variant was always set or given)."""
    r = subprocess.run([sys.executable, "-c", _VARIANTS], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0 and "VARIANTS-OK" in r.stdout, f"{r.stdout[-2000:]}\n{r.stderr[-4000:]}"
    assert CHOSEN not in r.stderr, r.stderr
