"""The gradient cost benchmark (`mi_amr.bench.gradients`,
docs/performance/gradients.md) on tiny data: every row is there, timed and
measured, and its gradients are real."""

import math

import numpy as np
import pytest

import mi_amr
from mi_amr.bench import gradients
from mi_amr.bench.__main__ import parse
from mi_amr.data.datasets import make_dataset
from mi_amr.plugins.medium import live_media


@pytest.mark.slow      # 8 s of CPU cold; test_gradients checks the gradients themselves (slow since the session of issues 61/64: the default suite over its 5-minute budget on CI)
def test01_gradient_case_measures_every_row_with_real_gradients(llvm, tmp_path):
    """A 2,000-cell case at 16x16, 1 spp, one round of one step: the rows of
    amrvolpath, prbvolpath (primal, values, tf_rgba) and the dense medium
    (primal, voxels) are all timed (positive, finite), the integrator that
    does not load is skipped with its reason, each gradient is finite and not
    zero, and the parameter sizes are those of the scene's arrays; the tables
    are written."""
    cells = make_dataset("cloud", cells=2000, levels=3)
    tf = mi_amr.TransferFunction.preset("spiky", cells.value_range)
    case = gradients.gradient_case(cells, tf, 60.0, res=16, spp=1, steps=1, repeats=1,
                                   integrators=["prbvolpath", "no-such-integrator"], max_depth=8)
    rows = case["rows"]
    expected = {"amr amrvolpath primal", "amr prbvolpath primal", "amr prbvolpath grad values",
                "amr prbvolpath grad tf_rgba", "dense prbvolpath primal", "dense prbvolpath grad voxels"}
    assert set(rows) == expected
    assert set(case["skipped"]) == {f"amr no-such-integrator {k}" for k in ("primal", "grad values", "grad tf_rgba")}
    assert all("no-such-integrator" in why for why in case["skipped"].values())
    for label, row in rows.items():
        for key in ("wall", "cpu", "render"):
            assert len(row[key]) == 1 and all(math.isfinite(t) and t > 0 for t in row[key]), (label, key, row[key])
        assert len(row["memory"]) == 1 and row["memory"][0]["drjit_peak_bytes"] >= 0
        if row["kind"] == "primal":
            assert row["backward"] == [0.0] and "grad" not in row
            continue
        assert all(math.isfinite(t) and t > 0 for t in row["backward"] + row["update"]), label
        assert row["vs_primal"]["median"] > 0 and math.isfinite(row["vs_primal"]["median"])
        g = row["grad"]
        assert g["finite"] and g["nonzero"] > 0 and g["abs_sum"] > 0, (label, g)
        # the gradient has the parameter's size: 4 bytes an entry
        assert g["size"] == case["param_sizes"][row["kind"]] and g["bytes"] == 4 * g["size"], (label, g)
        assert row["memory"][0]["drjit_peak_bytes"] > 0, label       # the step allocates its gradient
    sizes = case["param_sizes"]
    assert sizes["voxels"] == int(np.prod(case["dense_shape"])) == 28 ** 3
    assert sizes["tf_rgba"] == 4 * len(tf.rgba)
    assert sizes["values"] == case["value_slots"] >= len(cells) == rows["amr prbvolpath grad values"]["grad"]["entries"]
    assert "vs_dense_grad" in rows["amr prbvolpath grad values"]
    # the tables: every row and the parameter counts
    case.update(dataset="cloud (3 levels)", spec="cloud:2000:3", tf="spiky")
    gradients.write_tables([case], tmp_path, "python -m mi_amr.bench --grad", [0.5, 0.6])
    md = (tmp_path / "gradients.md").read_text()
    assert all(f"| {label} |" in md for label in expected) and f"{sizes['voxels']:,}" in md
    assert live_media() == 0                  # every pass freed its scene


def test02_command_line_dispatches_grad():
    """``--grad`` and its options parse; the integrators are a list."""
    args = parse(["--grad", "--out", "x", "--grad-integrators", "prbvolpath", "amrprbvolpath",
                  "--grad-data", "cloud:2e4:4"])
    assert args.grad and args.grad_integrators == ["prbvolpath", "amrprbvolpath"]
    assert gradients.parse_data(args.grad_data[0]) == ("cloud", 20000, 4)
