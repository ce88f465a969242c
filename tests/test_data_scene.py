"""The Python API from data to picture (`mi_amr.scene`, `DataScene`): the
plan of ``mi-amr render`` as attributes, pictures number for number those of
the command line, edits applied to the loaded scene without reloading it,
inline PNGs, and a saved scene that renders again to the same picture."""

import io
import copy

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.data.io import write_exabricks
from mi_amr.images import read_exr, srgb8
from mi_amr.tools.cli import main

from conftest import random_amr


@pytest.fixture
def data(tmp_path):
    path = tmp_path / "d.cells"
    write_exabricks(random_amr(1, 8, 2), path)
    return path


def test01_the_picture_is_the_command_lines(llvm, data, tmp_path):
    sc = mi_amr.scene(str(data), res=12, spp=4, mode="single")
    assert isinstance(sc, mi_amr.DataScene) and sc.notes == mi_amr.autoscene.plan_scene(str(data)).notes
    image = sc.render(seed=3)
    assert main(["render", str(data), "--res", "12", "--spp", "4", "--no-adaptive", "--seed", "3",
                 "--mode", "single", "-o", str(tmp_path / "cli.exr"), "-q"]) == 0
    np.testing.assert_array_equal(image, read_exr(tmp_path / "cli.exr"))
    with pytest.raises(ValueError, match="mode"):
        mi_amr.scene(str(data), mode="ambient")
    with pytest.raises(ValueError, match="spp"):
        sc.render(spp=0)


def test02_edits_go_into_the_loaded_scene(llvm, data):
    """A new density scale, TF range and camera: the same Mitsuba scene
    object renders them (nothing reloaded), and the picture equals a scene
    planned with those choices from the start (same seed)."""
    sc = mi_amr.scene(str(data), res=12, spp=4)
    first = sc.render(seed=1)
    loaded = sc.mitsuba_scene
    sc.density_scale = 0.5 * sc.density_scale
    sc.tf_range = (sc.tf_range[0], 0.8 * sc.tf_range[1])
    sc.origin = 1.25 * sc.origin
    edited = sc.render(seed=1)
    assert sc.mitsuba_scene is loaded
    plan = copy.copy(sc.plan)
    fresh = mi_amr.DataScene(plan, res=12, spp=4).render(seed=1)
    np.testing.assert_allclose(edited, fresh, rtol=1e-5, atol=1e-6)
    assert np.abs(edited - first).mean() > 1e-3                     # the edits changed the picture


def test03_inline_png_and_a_saved_scene(llvm, data, tmp_path):
    """``_repr_png_`` is the sRGB preview `write_png` writes; ``save``
    writes the EXR, the PNG and the XML, which ``mi-amr render`` renders
    again to the same picture (at the fixed count: ``--no-adaptive``)."""
    from PIL import Image as PILImage
    sc = mi_amr.scene(str(data), res=12, spp=4, mode="emission_absorption")
    image = sc.render(seed=2)
    decoded = np.asarray(PILImage.open(io.BytesIO(image._repr_png_())).convert("RGB"))
    np.testing.assert_array_equal(decoded, srgb8(image))
    paths = sc.save(tmp_path / "out" / "x.exr", seed=2)
    assert {"exr", "png", "xml"} <= set(paths) and all(p.is_file() for p in paths.values())
    assert main(["render", str(paths["xml"]), "--seed", "2", "--no-adaptive", "-o", str(tmp_path / "again.exr"),
                 "-q"]) == 0
    np.testing.assert_array_equal(read_exr(paths["exr"]), read_exr(tmp_path / "again.exr"))
    assert isinstance(image.to_bitmap(), mi.Bitmap)


def test04_a_clip_plane_from_python(llvm, data):
    """``sc.clip = (normal, offset)`` (world space) clips the loaded
    medium: the picture equals one with the plane given to the medium
    directly (same seed), and ``sc.clip = None`` gives the first picture
    back, all in the same loaded scene."""
    sc = mi_amr.scene(str(data), res=12, spp=4)
    first = sc.render(seed=1)
    loaded = sc.mitsuba_scene
    sc.clip = ([1.0, 0.0, 0.0], 0.0)
    clipped = sc.render(seed=1)
    assert sc.mitsuba_scene is loaded and np.abs(clipped - first).mean() > 1e-3
    fresh = mi_amr.DataScene(copy.copy(sc.plan), res=12, spp=4)
    fresh.mitsuba_scene.shapes()                                   # loaded, then clipped by hand
    fresh.medium.set_clip_plane([1.0, 0.0, 0.0], 0.0)
    np.testing.assert_allclose(clipped, fresh.render(seed=1), rtol=1e-5, atol=1e-6)
    sc.clip = None
    np.testing.assert_array_equal(sc.render(seed=1), first)
