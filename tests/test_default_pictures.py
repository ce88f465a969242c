"""Every default picture shows its data: the plan of `mi_amr.autoscene` on
the gallery of outputs (tests/gallery_outputs.py: five codes' formats, fields
spanning one to seven decades, zeros, negatives, a thin sheet in an empty
domain, an embedded boundary, a uniform background with a small dense
core), its predicted picture (the plan's check, `mi_amr.autoscene._checked`) and the rendered one (`rendered_visibility`), in all three modes."""

import mitsuba as mi
import pytest

from mi_amr.autoscene import MAX_OPAQUE, MIN_SHOWN, _checked, plan_scene
from mi_amr.scene_writer import scene_for
from mi_amr.data.statistics import value_stats
from mi_amr.visibility import rendered_visibility

from conftest import FORCED_VARIANT
from gallery_outputs import CASES

yt = pytest.importorskip("yt")

#: The scale each case should be planned in.
EXPECTED_LOG = {"cosmology": True, "collapse": True, "deep": True, "core": True,
                "waves": False, "velocity": False, "sheet": False, "embedded": False}
MODES = ("emission_absorption", "single", "multi")
#: A rendered picture shows the data when at least this share of the
#: footprint's blocks differ from the empty scene (4 sigma and 3%).
RENDERED_MIN = 0.03


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """``{case: (path, field)}``: the gallery written once."""
    return {name: case(tmp_path_factory.mktemp(name)) for name, case in CASES.items()}


@pytest.fixture(scope="module")
def plans(outputs):
    """``{case: ScenePlan}``: the default plans (the variant set as ``llvm``
    sets it: the plans hold Mitsuba objects)."""
    mi.set_variant(FORCED_VARIANT or "llvm_ad_rgb")
    return {name: plan_scene(str(path), field) for name, (path, field) in outputs.items()}


def test01_plans_choose_the_scale_and_range_where_the_data_are(llvm, plans):
    """log10 where the volume and the mass span decades, linear otherwise;
    the TF range holds the volume's median (the bulk of the data), lies
    within the values' span (never widened into values that no cell holds)
    and the predicted picture shows the data without a flat opaque block."""
    assert EXPECTED_LOG.keys() == plans.keys()
    for name, plan in plans.items():
        notes = "\n".join(plan.notes)
        assert (plan.transform == "log10") == EXPECTED_LOG[name], (name, notes)
        vs = value_stats(plan.data)
        lo, hi = vs.span(plan.transform == "log10")
        assert lo - 1e-9 <= plan.tf_range[0] < plan.tf_range[1] <= hi + 1e-6 * max(1.0, abs(hi)), (name, notes)
        assert plan.visibility.shown >= MIN_SHOWN or name == "core", (name, notes)
        assert plan.visibility.opaque < MAX_OPAQUE * plan.visibility.shown, (name, notes)
        assert "predicted picture" in notes


def test02_the_five_decade_density_is_log10_over_its_web(llvm, plans):
    """The Enzo cosmology density (five decades, its volume within 15x):
    log10, and the range reaches from the voids into the haloes (the
    mass's tail), with the density scale within the bound: the picture the
    issue's user had from yt, not an empty ground (the old rule took linear
    values and a range at the TF's transparent bottom)."""
    plan = plans["cosmology"]
    assert plan.transform == "log10"
    assert plan.value_range[0] < -29.0 and plan.value_range[1] > -26.5
    # the default layers span the values the picture's pixels reach, from the voids into the filaments
    assert plan.value_range[0] <= plan.tf_range[0] < -28.5 and -28.5 < plan.tf_range[1] <= plan.value_range[1]
    assert "mass up to" in plan.notes[1]
    assert plan.optical_depth > 0.5 and plan.visibility.shown > 0.2


def test03_a_tf_transparent_at_every_value_is_replanned(llvm, outputs, monkeypatch):
    """The sheet (values 0 and 1 only): the default layers would show one
    layer at most (the values do not spread over layers), so the plan takes
    'ramp' and says why; so does a default transparent at both values
    ('spiky'); a TF the user names is kept, and its (empty) prediction is
    reported."""
    import mi_amr.autoscene as autoscene
    path, field = outputs["sheet"]
    layered = plan_scene(str(path), field)
    assert layered.tf == "ramp" and layered.visibility.shown >= MIN_SHOWN, layered.notes
    assert any("layers would be seen" in n and "TF 'ramp' instead" in n for n in layered.notes), layered.notes
    monkeypatch.setattr(autoscene, "DEFAULT_TF", "spiky")
    plan = plan_scene(str(path), field)
    assert plan.tf == "ramp" and any("transparent at every value" in n for n in plan.notes), plan.notes
    named = plan_scene(str(path), field, tf="spiky")
    assert named.tf == "spiky" and named.visibility.shown < MIN_SHOWN


def test04_a_flat_opaque_block_is_replanned(llvm, plans):
    """A planned density 1000x too high makes all that the waves' picture
    shows opaque: the check lowers it until about half of it is, and says
    so; a density the user gives is kept."""
    plan = plans["waves"]
    import copy
    dense = copy.copy(plan)
    dense.notes = []
    dense.density_scale, dense.optical_depth, dense.peak_depth = (1000 * x for x in (
        plan.density_scale, plan.optical_depth, plan.peak_depth))
    vs = value_stats(plan.data)
    checked = _checked(copy.copy(dense), plan.data, vs, tf_given=True, scale_given=False)
    assert checked.density_scale < dense.density_scale
    seen = checked.visibility
    assert seen.opaque <= 0.55 * seen.shown and any("flat block" in n for n in checked.notes), checked.notes
    kept = _checked(copy.copy(dense), plan.data, vs, tf_given=True, scale_given=True)
    assert kept.density_scale == dense.density_scale
    assert kept.visibility.opaque >= MAX_OPAQUE * kept.visibility.shown


# single: slow (multi and emission_absorption show the same plans; test_modes checks its estimator)
@pytest.mark.parametrize("mode", [pytest.param(m, marks=pytest.mark.slow) if m == "single" else m for m in MODES])
def test05_every_default_picture_shows_its_data(llvm, plans, mode):
    """Every gallery plan rendered in ``mode`` (32 x 32, 16 spp, two seeds)
    differs from the same scene with an empty medium in at least
    `RENDERED_MIN` of the footprint's blocks by 4 sigma and 3%; and the
    score can fail: the cosmology rendered with its TF range above every
    value (nothing but the transparent bottom) scores 0."""
    for name, plan in plans.items():
        scene = mi.load_dict(scene_for(plan, res=32, spp=16, mode=mode))
        seen = rendered_visibility(scene, plan.extent, spp=16)
        assert seen.footprint > 0 and seen.shown >= RENDERED_MIN, (name, mode, str(seen), plan.notes)
        del scene
    empty = plan_scene(plans["cosmology"].data, tf="spiky", value_range=(-20.0, -19.0), log=True,
                       density_scale=100.0)
    scene = mi.load_dict(scene_for(empty, res=32, spp=16, mode=mode))
    assert rendered_visibility(scene, empty.extent, spp=16).shown == 0.0
    assert empty.visibility.shown == 0.0


def test06_render_and_info_print_the_plan_and_its_check(llvm, outputs, plans, tmp_path, capsys):
    """``mi-amr info DATA --field F --plan`` gives the plan and its
    predicted picture (the numbers `plan_scene` gives); ``mi-amr render``
    prints the same check, and lets it replace the default TF (the sheet:
    'ramp', its two values spread over no layers), which the scene it
    writes keeps; the cosmology's printout says which layers it shows, and
    its scene names the planned layers."""
    import json
    from mi_amr.tools.cli import main
    path, field = outputs["sheet"]
    main(["info", str(path), "--field", field, "--plan", "--json"])
    got = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["plan"]
    plan = plans["sheet"]
    assert got["tf"] == plan.tf == "ramp" and got["tf_range"] == pytest.approx(plan.tf_range)
    assert got["predicted"]["shown"] == pytest.approx(plan.visibility.shown)
    main(["render", str(path), "--field", field, "--res", "8", "--spp", "1", "-o", str(tmp_path / "sheet.exr")])
    out = capsys.readouterr().out
    assert "predicted picture:" in out and "TF 'ramp' instead" in out
    assert 'name="transfer_function" value="ramp"' in (tmp_path / "sheet.xml").read_text()
    path, field = outputs["cosmology"]
    plan = plans["cosmology"]
    main(["render", str(path), "--field", field, "--res", "8", "--spp", "1", "-o", str(tmp_path / "cosmo.exr")])
    out = capsys.readouterr().out
    assert plan.tf.startswith("layers") and f"predicted {plan.layers}" in out
    assert f'name="transfer_function" value="{plan.tf}"' in (tmp_path / "cosmo.xml").read_text()


def test07_the_opacity_grid_is_the_cells_volume_mean(llvm):
    """`opacity_grid` (what the check marches through): over 32^3 cells, a
    64-voxel grid gives each voxel the value of the cell that holds it
    (cells larger than a voxel are spread over the voxels they cover), a
    16-voxel grid the mean of the 8 cells in each voxel, exactly; a
    sample of a few cells a block spreads over the block."""
    import numpy as np
    from mi_amr.data.blocks import BlockVolume
    from mi_amr.visibility import opacity_grid
    v = np.random.default_rng(0).random((32, 32, 32)).astype(np.float32)
    vol = BlockVolume.from_dense(v, block=8)
    xyz = v.transpose(2, 1, 0).astype(np.float64)                      # [x, y, z], as the grid
    fine = np.repeat(np.repeat(np.repeat(xyz, 2, 0), 2, 1), 2, 2)
    np.testing.assert_allclose(opacity_grid(vol, lambda x: x, grid=64), fine, rtol=1e-12)
    coarse = xyz.reshape(16, 2, 16, 2, 16, 2).mean(axis=(1, 3, 5))
    np.testing.assert_allclose(opacity_grid(vol, lambda x: x, grid=16), coarse, rtol=1e-6)
    # a sample of 8 cells a block (of 16^3) spreads over x, y and z, not down one column of the block
    from mi_amr.visibility import sampled_cells
    big = BlockVolume.from_dense(v, block=16)
    pos = np.concatenate([p for p, _, _, _ in sampled_cells(big, max_cells=64)])
    first = pos[(pos < 16).all(axis=1)]
    assert len(first) == 8 and all(len(np.unique(first[:, k])) == 8 for k in range(3)), first
