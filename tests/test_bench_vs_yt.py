"""yt's volume renderer beside ``ray_march`` and ``emission_absorption``
(`mi_amr.bench.vs_yt`, docs/performance/vs-yt.md): the same camera, yt's
image and ours against the exact emission-absorption integral each within
its own error, the ray marcher exact per ray where the estimator is noisy,
``vs_yt.json``'s records, and an Enzo-format output in log10 on both sides."""

import json
import os

import numpy as np
import pytest

pytest.importorskip("yt")
# yt's OpenMP renderer with threads that sleep at its barriers, as the bench
# runs it (`vs_yt.omp_wait_policy`): spinning ones make a 32^2 render take
# seconds while other processes share the cores. libgomp reads it when yt's
# renderer loads it, after this.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from mi_amr.bench import vs_yt  # noqa: E402
from mi_amr.bench.__main__ import main  # noqa: E402

#: Keys of every record of ``vs_yt.json`` (issue 59), and of ours besides.
KEYS = {"renderer": str, "data": str, "size": int, "seconds": float, "rmse_over_mean": float}


def by_renderer(records, data, size):
    return {r["renderer"]: r for r in records if r["data"] == data and r["size"] == size}


def test01_json_records_and_the_marcher_against_the_estimator(llvm, tmp_path):
    """``--vs-yt blocks`` at 32^2 (yt, ray_march at 1 and 4 spp, the
    estimator at 1, 4, 16): one record per renderer with the issue's keys,
    the plot, and the properties each row rests on."""
    assert main(["--vs-yt", "blocks", "--vs-yt-res", "32", "--vs-yt-n0", "16", "--vs-yt-cap", "16",
                 "--vs-yt-march-cap", "4", "--vs-yt-rounds", "1", "--out", str(tmp_path)]) == 0
    records = json.loads((tmp_path / "vs_yt.json").read_text())
    assert (tmp_path / "vs_yt.png").stat().st_size > 10000 and (tmp_path / "vs_yt.md").exists()
    assert sorted(r["renderer"] for r in records) == sorted(vs_yt.RENDERERS)
    for r in records:
        for key, kind in KEYS.items():
            assert isinstance(r[key], kind), (key, r[key])
        assert r["seconds"] > 0 and r["rmse_over_mean"] > 0
        if r["renderer"] != "yt":
            assert isinstance(r["seconds_to_yt_rmse"], float) or r["seconds_to_yt_rmse"] is None
    g = by_renderer(records, "blocks", 32)
    y, m, e = g["yt"], g["ray_march"], g["emission_absorption"]
    # the same camera: domain corners on the same pixels, the same opacity centroid
    assert y["corners"]["max_diff_px"] < 1e-3
    assert np.abs(y["placement_px"]).max() < 0.05
    # yt's rays are the pixel centres: it equals the exact march of them within its
    # first-order steps (measured 0.05-0.06% of the mean at 32^2 to 256^2)
    assert y["rmse_centre_over_mean"] < 3e-3, y["rmse_centre_over_mean"]
    # the marcher at 1 spp of centred strata shoots the same rays, and with nearest
    # it is exact per ray: equal to the exact walk within float32 rounding
    assert m["sampler"] == "centres" and m["centre_rays_over_mean"] < 1e-3, m["centre_rays_over_mean"]
    # so its error is the pixel footprint alone, far below the estimator's noise at
    # the same spp, and it falls as the strata refine
    ce, cm = {p["spp"]: p["rmse_over_mean"] for p in e["curve"]}, {p["spp"]: p["rmse_over_mean"] for p in m["curve"]}
    for spp in (1, 4):
        assert cm[spp] < 0.1 * ce[spp], (spp, cm[spp], ce[spp])
    assert cm[4] < 0.7 * cm[1], cm
    # the estimator has no floor: its error is noise, 1/sqrt(spp) from 1 to 16 spp
    assert 2.8 < ce[1] / ce[16] < 5.5, ce
    assert m["seconds_to_yt_rmse"] is None or m["seconds_to_yt_rmse"] > 0


def test02_the_witness_tells_a_wrong_brightness(llvm):
    """The checks above can fail: yt's image with brightness 20% off is far
    outside the error it has with the right one."""
    import mitsuba as mi
    case = vs_yt.own_case("blocks", 16)
    scene = mi.load_dict(vs_yt.our_scene_dict(case, 32))
    _, ref_centre, _ = vs_yt.references(case, scene, 32)
    good, _ = vs_yt.yt_image(vs_yt.yt_scene(case, 32))
    bad, _ = vs_yt.yt_image(vs_yt.yt_scene(case, 32, brightness=1.2 * vs_yt.BRIGHTNESS))
    mean = ref_centre.mean()
    assert vs_yt.rmse(good, ref_centre) / mean < 3e-3
    assert vs_yt.rmse(bad, ref_centre) / mean > 10 * vs_yt.rmse(good, ref_centre) / mean


def test03_an_enzo_output_in_log10_on_both_sides(llvm, tmp_path):
    """An Enzo-format output (16^3 root cells, 32^3 finest) read by yt:
    the plan takes log10, yt (``log_field``) and ours render it with one TF
    over log10 values; our marcher equals the exact walk of its rays, and
    yt, which interpolates vertex values, differs from the nearest field by
    its interpolation only (5% at this coarse resolution, where yt's field
    over linear values with the same log10 bounds is 66% off)."""
    import dataclasses

    import mitsuba as mi
    from mi_amr.data.enzo_example import write_example
    case = vs_yt.output_case(write_example(tmp_path, root=16, grids=6), "density", "enzo")
    assert case.log and case.tf.domain[1] < -20, case.tf.domain
    recs = vs_yt.run_case(case, 32, [1], [1], rounds=1)
    g = {r["renderer"]: r for r in recs}
    assert g["yt"]["corners"]["max_diff_px"] < 1e-3
    assert g["ray_march"]["centre_rays_over_mean"] < 1e-3, g["ray_march"]["centre_rays_over_mean"]
    assert 1e-3 < g["yt"]["rmse_centre_over_mean"] < 0.15, g["yt"]["rmse_centre_over_mean"]
    # measured 5.3%; the check can fail: yt's TF over linear values is 66% off
    wrong, _ = vs_yt.yt_image(vs_yt.yt_scene(dataclasses.replace(case, log=False), 32))
    box, centre, _ = vs_yt.references(case, mi.load_dict(vs_yt.our_scene_dict(case, 32)), 32)
    assert vs_yt.rmse(wrong, centre) / centre.mean() > 0.3
    assert g["ray_march"]["rmse_over_mean"] < g["emission_absorption"]["rmse_over_mean"] / 10
