"""Rendering as a library (`mi_amr.rendering`): what ``mi-amr render``
does, from Python with no command line: the same images, nothing written,
bad jobs refused before any data are read."""

import numpy as np
import pytest

from mi_amr.data.io import write_exabricks
from mi_amr.images import read_exr
from mi_amr.rendering import RenderJob, render_jobs
from mi_amr.tools.cli import main

from conftest import random_amr


def test01_jobs_render_what_the_command_line_renders(llvm, tmp_path):
    """A data job and an XML job give, number for number, the images the
    command line writes for the same data, seed, spp and mode; the data
    job's result carries its plan; rendering wrote no file."""
    data = tmp_path / "d.cells"
    write_exabricks(random_amr(1, 8, 2), data)
    cli = tmp_path / "cli"
    assert main(["render", str(data), "--res", "12", "--spp", "4", "--no-adaptive", "--seed", "3",
                 "--mode", "single", "-o", str(cli / "d.exr"), "-q"]) == 0
    before = sorted(p.name for p in tmp_path.rglob("*"))
    data_job = RenderJob(str(data), res=12, spp=4, seed=3, mode="single")
    xml_job = RenderJob(str(cli / "d.xml"), spp=4, seed=3, mode="single", defines={"res": "12"})
    first, second = render_jobs([data_job, xml_job])
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
    np.testing.assert_array_equal(first.image, read_exr(cli / "d.exr"))
    np.testing.assert_array_equal(second.image, read_exr(cli / "d.exr"))
    assert first.plan is not None and first.plan.visibility is not None and second.plan is None
    assert first.image.shape == (12, 12, 3) and first.spp == 4


@pytest.mark.parametrize("job,words", [
    (RenderJob("missing.cells", spp=0), "spp"),
    (RenderJob("missing.cells", res=-5), "res"),
    (RenderJob("missing.cells", mode="ambient"), "mode"),
    (RenderJob("missing.cells", plan_options={"colour": "red"}), "colour"),
    (RenderJob("scene.xml", field="density"), "not XML scenes"),
])
def test02_bad_jobs_are_refused_before_the_data(llvm, job, words):
    with pytest.raises(ValueError, match=words) as e:
        render_jobs([job])
    assert "\n" not in str(e.value)
