"""The cosmo data set and the resample study (mi_amr.bench.resample), small and fast."""

import json
import math

import numpy as np
import pytest

from mi_amr.data.datasets import make_dataset, write_block_dataset


def test_cosmo_levels_span_and_determinism():
    c = make_dataset("cosmo", 60_000, levels=7)
    levels = np.unique(c.level)
    assert len(levels) >= 7 and 2 ** (levels.max() - levels.min()) >= 64
    lo, hi = c.bounds
    n = int((hi - lo).max())
    assert n & (n - 1) == 0                          # a power-of-two domain: resamples align
    assert np.log10(c.value.max() / c.value.min()) > 4      # densities spanning decades
    # refined where it is dense: the finest cells are denser than the coarsest
    assert np.median(c.value[c.level == 0]) > 10 * np.median(c.value[c.level == levels.max()])
    d = make_dataset("cosmo", 60_000, levels=7)
    assert np.array_equal(c.pos, d.pos) and np.array_equal(c.value, d.value)


def test_cosmo_streamed_file_loads_back(tmp_path):
    from mi_amr.data.io import load_cells
    mem = make_dataset("cosmo", 60_000, levels=7)
    path = write_block_dataset(tmp_path / "c.cells", 60_000, levels=7, name="cosmo")
    back = load_cells(path)
    assert len(back) == len(mem)
    order_a, order_b = np.lexsort(mem.pos.T), np.lexsort(back.pos.T)
    assert np.array_equal(mem.value[order_a], back.value[order_b])
    with pytest.raises(ValueError, match="block-structured"):
        write_block_dataset(tmp_path / "x.cells", 1000, name="cloud")


def test_resample_grid_box_conserves_mass_and_nearest_is_exact():
    from mi_amr.bench.resample import resample_grid
    c = make_dataset("cosmo", 20_000, levels=4)
    n = int((c.bounds[1] - c.bounds[0]).max())
    mass = float((c.value.astype(np.float64) * 8.0 ** c.level).sum()) / n ** 3
    for res in (n // 8, n // 2):
        g = resample_grid(c, res, "box")
        assert g.mean(dtype=np.float64) == pytest.approx(mass, rel=1e-4)
    exact_box, exact_nearest = resample_grid(c, n, "box"), resample_grid(c, n, "nearest")
    np.testing.assert_allclose(exact_box, exact_nearest, rtol=1e-5)
    with pytest.raises(ValueError, match="align"):
        resample_grid(c, n // 2 * 3, "box")


@pytest.mark.slow      # 10 s of CPU cold: the study end to end (slow since the session of issues 61/64: the default suite over its 5-minute budget on CI)
def test_resample_study_end_to_end(tmp_path):
    from mi_amr.bench.__main__ import main
    out = tmp_path / "out"
    main(["--resample", "cosmo:3e4:4", "--out", str(out), "--data-dir", str(tmp_path / "data"), "--res", "24",
          "--truth-spp", "128", "--max-spp", "8", "--resolutions", "8", "32", "--resample-methods", "nearest",
          "--renderers", "heterogeneous", "--repeats", "1", "--check-max", "0", "--unfrozen"])
    for name in ("resample.json", "resample.md", "resample.png"):
        assert (out / name).stat().st_size > 0
    rec = json.loads((out / "resample.json").read_text())[0]
    assert rec["levels"] == 4 and rec["transform"] == "log10"
    rows = {r["resolution"]: r for r in rec["rivals"]}
    assert set(rows) == {8, 32}
    assert rows[32]["floor"] < rows[8]["floor"]           # a finer resample is less biased
    assert rows[32]["bytes"] == 16 * 32 ** 3
    # the amr medium is unbiased: its error falls as 1/sqrt(spp) (1 -> 8 spp: 2.83x, within 35%)
    c = {p[0]: p[2] for p in rec["amr_curve"]}
    assert c[1] / c[8] == pytest.approx(math.sqrt(8), rel=0.35)
    assert "Lowest resolved floor of a resample" in (out / "resample.md").read_text()


def test_zoom_looks_at_the_densest_cell_from_outside():
    """``--zoom W``: a telephoto view of the cell holding the largest value,
    from the benchmark camera's direction and distance (outside the unit
    cube the volume fills), its field of view spanning W at that cell."""
    from mi_amr.bench.harness import BENCH_FOV, BENCH_ORIGIN, BENCH_TARGET, zoom_camera
    from mi_amr.bench.resample import densest_point
    cells = make_dataset("cosmo", cells=3000, levels=3, seed=2)
    p = densest_point(cells)
    lo, hi = cells.bounds
    i = int(np.argmax(cells.value))
    centre = (cells.pos[i] + 0.5 * (1 << int(cells.level[i])) - lo) / (hi - lo)
    np.testing.assert_allclose(p, centre)
    origin, target, fov = zoom_camera(p, 0.05)
    assert np.any((np.asarray(origin) < 0) | (np.asarray(origin) > 1))          # outside the volume
    dist = np.linalg.norm(np.subtract(origin, target))
    assert dist == pytest.approx(np.linalg.norm(np.subtract(BENCH_ORIGIN, BENCH_TARGET)))
    assert 2 * dist * math.tan(math.radians(fov) / 2) == pytest.approx(0.05)
    assert zoom_camera(BENCH_TARGET, 2 * dist * math.tan(math.radians(BENCH_FOV) / 2))[2] == pytest.approx(BENCH_FOV)


def test_seconds_near_a_floor_on_and_past_the_curve():
    """A rival's error falls as ``sqrt(floor^2 + c / t)``: the seconds to
    come within 10% of its floor are read off its curve when it gets there,
    and continued by that model past its end (flagged) when it does not."""
    from mi_amr.bench.resample import seconds_near_floor
    floor, c = 0.01, 4e-4

    def pts(ts):
        return [[i, t, math.sqrt(floor ** 2 + c / t), 0.0] for i, t in enumerate(ts)]
    exact = c / (0.21 * floor ** 2)                               # 1.1^2 - 1 = 0.21
    t, extrapolated = seconds_near_floor(pts([2.0 ** k for k in range(12)]), floor)     # doubling spp
    assert not extrapolated and t == pytest.approx(exact, rel=0.15)
    t, extrapolated = seconds_near_floor(pts([1, 2, 4, 8]), floor)
    assert extrapolated and t == pytest.approx(exact, rel=1e-9)
    assert seconds_near_floor(pts([1, 2]), 0.0) == (None, False)


def test_bias_floor_measures_its_own_uncertainty_under_heavy_tailed_noise():
    """`bias_floor` on synthetic halves: the truth and a rival with heavy-tailed
    (Pareto-like, firefly) noise. Without a bias the floor^2 stays within 4
    of its own standard errors of 0 in most seeds (a 4-sigma event is rare)
    and the squared floor agrees with the known bias within 4 standard errors
    where there is one."""
    from mi_amr.bench.resample import RESOLVED_SE, bias_floor

    def halves(rng, mean):
        h = [mean + 0.05 * rng.standard_normal(mean.shape) * (1 + rng.pareto(2.5, mean.shape)) for _ in range(2)]
        return 0.5 * (h[0] + h[1]), (h[0] - h[1]) ** 2 / 4.0

    base = np.random.default_rng(0).random((96, 96, 3))
    bias = 0.05 * np.sign(np.random.default_rng(1).standard_normal((96, 96, 1))) * np.ones(3)
    false_resolved = 0
    for seed in range(10):
        rng = np.random.default_rng(100 + seed)
        truth, tmap = halves(rng, base)
        img, imap = halves(rng, base)
        floor, se = bias_floor(img, imap, truth, tmap)
        assert se > 0
        false_resolved += floor ** 2 > RESOLVED_SE * se
        img, imap = halves(rng, base + bias)
        floor, se = bias_floor(img, imap, truth, tmap)
        assert abs(floor ** 2 - 0.05 ** 2) < 4 * se, (floor, se)
        assert floor ** 2 > RESOLVED_SE * se              # 0.05 is well above this noise
    assert false_resolved <= 1
