"""The README's Python example and the notebooks run as written."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test01_readme_python_examples_run():
    """Every ```python block of the README, in order, in one namespace."""
    src = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", src, re.S)
    assert len(blocks) >= 2
    ns = {}
    exec(compile(blocks[0], "README.md", "exec"), ns)
    img = np.array(ns["image"])
    assert img.shape == (128, 128, 3) and np.isfinite(img).all() and img[..., 0].std() > 0.01
    for block in blocks[1:]:
        exec(compile(block, "README.md", "exec"), ns)
    med = ns["mi_amr"].amr_media(ns["scene"])[0]
    assert med.density_scale == 200.0 and med.tf.rgba[:, 3].max() == 1.0


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "notebooks").glob("*.ipynb")))
def test02_notebooks_run_top_to_bottom(name, monkeypatch):
    import matplotlib
    matplotlib.use("Agg")
    nb = json.loads((ROOT / "notebooks" / name).read_text())
    ns = {}
    for cell in nb["cells"]:
        if cell["cell_type"] == "code":
            exec(compile("".join(cell["source"]), f"{name}", "exec"), ns)


def test03_every_image_the_readme_links_is_in_the_repository():
    """Markdown images and <img> tags with relative paths; the gallery's
    PNGs also stay under 200 kB (front-page weight)."""
    src = (ROOT / "README.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", src) + re.findall(r'<img[^>]*src="([^"]+)"', src)
    local = [l for l in links if not l.startswith(("http://", "https://"))]
    assert len([l for l in local if l.startswith("docs/images/")]) >= 4, local
    for link in local:
        path = ROOT / link
        assert path.is_file(), f"README links {link}, which is not in the repository"
        if link.startswith("docs/images/"):
            assert path.stat().st_size < 200_000, f"{link}: {path.stat().st_size} bytes"
