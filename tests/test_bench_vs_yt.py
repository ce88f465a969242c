"""yt's volume renderer as a second witness of ``emission_absorption``
(`mi_amr.bench.vs_yt`, docs/performance/vs-yt.md): on data whose yt grids
each hold one value, yt's image and ours both equal the dense ray march of
Max's model, each within its own error, and the benchmark row has its
fields."""

import numpy as np
import pytest

pytest.importorskip("yt")

from mi_amr.bench import vs_yt  # noqa: E402


def test01_yt_and_ours_agree_with_the_reference(llvm):
    rec = vs_yt.run_case(32, 16, "blocks", [1, 4, 16], rounds=1, steps=512)
    for key in ("yt_s", "yt_rmse", "ours_rmse", "ours_s", "to_yt_error", "to_1pct", "ours_vs_yt", "corners"):
        assert key in rec, key
    # the same camera: domain corners on the same pixels, the same opacity centroid
    assert rec["corners"]["max_diff_px"] < 1e-3
    assert np.abs(rec["placement_px"]).max() < 0.05
    # yt's rays are the pixel centres: it equals the centre-ray march within its
    # first-order steps (measured 0.06% of the mean at 32^2 to 256^2)
    assert rec["yt_rmse_centre_rel"] < 3e-3, rec["yt_rmse_centre_rel"]
    # ours has no floor: its error is noise, 1/sqrt(spp) from 1 to 16 spp
    e = rec["ours_rmse"]
    assert 2.8 < e[0] / e[2] < 5.5, e
    assert e[2] / rec["ref_mean"] < 0.1


def test02_the_witness_tells_a_wrong_brightness(llvm):
    """The check above can fail: yt's image with brightness 20% off is far
    outside the error it has with the right one."""
    import mi_amr
    import mitsuba as mi
    tf = vs_yt.tf_of()
    ds = vs_yt.load_yt(vs_yt.block_grids(16, 0, "blocks"), 16)
    cells = mi_amr.from_yt(ds, vs_yt.FIELD)
    scene = mi.load_dict(vs_yt.our_scene_dict(cells, tf, 32))
    _, ref_centre, _ = vs_yt.references(scene, cells, tf, 32, 512)
    good, _ = vs_yt.yt_image(vs_yt.yt_scene(ds, tf, 32))
    bad, _ = vs_yt.yt_image(vs_yt.yt_scene(ds, tf, 32, brightness=1.2 * vs_yt.BRIGHTNESS))
    mean = ref_centre.mean()
    assert vs_yt.rmse(good, ref_centre) / mean < 3e-3
    assert vs_yt.rmse(bad, ref_centre) / mean > 10 * vs_yt.rmse(good, ref_centre) / mean
