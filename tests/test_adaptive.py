"""Adaptive sampling and denoising by default (`mi_amr.adaptive`,
`mi_amr.denoising`, ``mi-amr render``; docs/manual/adaptive.md).

One scene serves the estimate and the stopping rule (one Dr.Jit kernel):
the unit cube seen along z (tests/test_emission.py's camera) under a
constant environment, empty but for a scattering column in its middle (the
*feature*: multiple scattering noise in 4 of the 16 tiles). Every other
pixel sees the environment through empty space, the same value for every
sample: its error is zero. The feature's converged picture is rendered once
here at many samples (its own remaining error estimated and taken off).
"""

import numpy as np
import pytest

import mitsuba as mi

from mi_amr import AMRCells, TransferFunction, adaptive, distributed
from mi_amr.images import read_exr
from mi_amr.tools.cli import main

from conftest import FORCED_VARIANT, dataless_view
from test_emission import ortho_scene

RES, TILE = 32, 8
#: The feature's tiles (tile rows and columns 1 and 2 of the 4 x 4).
FEATURE_TILES = (slice(1, 3), slice(1, 3))


def feature_scene():
    """The scene of the module docstring, loaded: 16^3 cells of value 0 but
    for a 4 x 4 column of value 1 along z (optical depth 3, albedo 0.8),
    pixels 9 to 22 of 32 across and down: in tiles 1 and 2 of each axis."""
    n = 16
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    inside = (g[:, :2] >= 6) & (g[:, :2] <= 9)
    cells = AMRCells(g, np.zeros(len(g), np.int32), np.where(inside.all(axis=1), 1.0, 0.0))
    tf = TransferFunction(np.array([[0.8, 0.8, 0.8, 0.0], [0.8, 0.8, 0.8, 1.0]]), (0.0, 1.0))
    medium = {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 3.0,
              "reconstruction": "nearest"}
    scene = ortho_scene(medium, res=RES, max_depth=32)
    scene["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.6, 0.7, 0.9]}}
    return mi.load_dict(scene)


@pytest.fixture(scope="module")
def scene():
    mi.set_variant(FORCED_VARIANT or "llvm_ad_rgb")       # the `llvm` fixture's, once for the module
    return feature_scene()


def pixel_means(sums):
    """Pixel means of raw film sums (0 where none landed)."""
    w = sums[..., -1:]
    return np.where(w > 0, sums[..., :3] / np.maximum(w, 1e-30), 0.0)


def test01_the_half_buffer_estimate_is_the_true_error(llvm, scene):
    """Over the feature's tiles, the estimated mean squared error of two
    half buffers' mean (`adaptive.tile_errors` squared) equals its true
    mean squared error against the converged picture, within four
    standard errors of the difference (both per-pixel quantities' spread
    over the pixels and four seeds); outside the feature both are zero."""
    feature = np.zeros((RES // TILE, RES // TILE), dtype=bool)
    feature[FEATURE_TILES] = True
    pixels = adaptive.tile_pixels(feature, TILE, RES, RES)
    r1 = adaptive.render_pixels(scene, pixels, 1024, 900)
    r2 = adaptive.render_pixels(scene, pixels, 1024, 901)
    ref = 0.5 * (pixel_means(r1) + pixel_means(r2))
    ref_mse = (0.5 * (pixel_means(r1) - pixel_means(r2))) ** 2      # the reference's own, per pixel
    estimated, true = [], []
    for seed in (1, 2, 3, 4):
        a = adaptive.render_pixels(scene, pixels, 8, 10 * seed)
        b = adaptive.render_pixels(scene, pixels, 8, 10 * seed + 1)
        errors = adaptive.tile_errors(a, b, TILE, scale=1.0)
        assert np.all(errors[~feature] == 0.0)
        assert np.all(errors[feature] > 0.0)
        est = (0.5 * (pixel_means(a) - pixel_means(b))) ** 2
        err = (0.5 * (pixel_means(a) + pixel_means(b)) - ref) ** 2 - ref_mse
        rows, cols = np.divmod(pixels.astype(np.int64), RES)
        estimated.append(est[rows, cols].mean(axis=-1))
        true.append(err[rows, cols].mean(axis=-1))
        # the tiles' estimate is the pixels' one, averaged per tile
        np.testing.assert_allclose(np.mean(errors[feature] ** 2), est[rows, cols].mean(), rtol=1e-4)
    estimated, true = np.concatenate(estimated), np.concatenate(true)
    se = np.sqrt(estimated.var(ddof=1) / len(estimated) + true.var(ddof=1) / len(true))
    assert abs(estimated.mean() - true.mean()) < 4 * se, (estimated.mean(), true.mean(), se)
    assert true.mean() > 10 * se           # a real error to estimate, not noise about zero


def test02_the_feature_keeps_sampling_and_empty_tiles_stop(llvm, scene):
    """Adaptive sampling at 3% noise: every empty tile stops after the first
    pair of passes (8 samples), every tile of the feature takes more, the
    picture ends below the threshold, its per-pixel sample counts are what
    each tile took, and its estimate is the mean of every sample (the
    empty pixels are the environment, exactly)."""
    result = adaptive.render_adaptive(scene, noise=0.03, max_spp=512, tile=TILE, seed=4)
    per_tile = result.spp[::TILE, ::TILE]
    feature = np.zeros_like(per_tile, dtype=bool)
    feature[FEATURE_TILES] = True
    assert np.all(per_tile[~feature] == 2 * adaptive.DEFAULT_PASS_SPP), per_tile
    assert np.all(per_tile[feature] > 2 * adaptive.DEFAULT_PASS_SPP), per_tile
    assert np.array_equal(result.spp, np.kron(per_tile, np.ones((TILE, TILE))))
    assert result.converged and result.stopped == "noise"
    assert np.all(result.tile_error < 0.03)
    np.testing.assert_allclose(result.image[0, 0, :3], [0.6, 0.7, 0.9], rtol=1e-5)
    assert f"{result.spp.mean():.1f} spp mean (8 to {per_tile.max():.0f}" in result.summary()
    capped = adaptive.render_adaptive(scene, noise=1e-4, max_spp=16, tile=TILE, seed=4)
    assert capped.stopped == "spp" and not capped.converged and capped.spp.max() == 16
    timed = adaptive.render_adaptive(scene, noise=1e-4, seconds=1e-3, tile=TILE, seed=4)
    assert timed.stopped == "time" and timed.passes == 2 and "time limit" in timed.summary()


def test03_render_defaults_write_the_estimate_denoised_and_the_sample_counts(llvm, tmp_path, capsys):
    """``mi-amr render DATA`` with no sampling flags: adaptive and denoised;
    it writes OUT.exr (the estimate), OUT-denoised.exr, OUT.png (showing the
    denoised picture), OUT-raw.png and OUT-spp.exr (samples per pixel, as
    the printout says)."""
    from mi_amr.denoising import denoiser_missing
    from mi_amr.images import srgb8
    from PIL import Image
    if denoiser_missing():
        pytest.skip(denoiser_missing())
    out = tmp_path / "c.exr"
    assert main(["render", "scenes/data/cloud.cells", "--res", "16", "--spp", "32", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    names = {p.name for p in tmp_path.iterdir()}
    assert {"c.exr", "c-denoised.exr", "c.png", "c-raw.png", "c-spp.exr"} <= names, names
    spp = read_exr(tmp_path / "c-spp.exr")
    assert spp.min() >= 8 and spp.max() <= 32 and f"{spp.mean():.1f} spp mean" in printed, printed
    estimate, clean = read_exr(out), read_exr(tmp_path / "c-denoised.exr")
    assert np.isfinite(clean).all() and not np.allclose(estimate[..., :3], clean[..., :3])
    shown = np.asarray(Image.open(tmp_path / "c.png"))[..., :3]
    assert np.array_equal(shown, srgb8(clean)) and "denoised" in printed


@pytest.mark.slow
def test03b_no_adaptive_no_denoise_is_the_fixed_count_as_before(llvm, tmp_path, capsys):
    """``--spp 4 --no-adaptive --no-denoise`` writes only the estimate at the
    fixed count, the image `mi_amr.distributed.render_local` makes. Slow:
    Mitsuba's own render loop is another kernel."""
    fixed = tmp_path / "c.exr"
    assert main(["render", "scenes/data/cloud.cells", "--res", "16", "--spp", "4", "--no-adaptive",
                 "--no-denoise", "-o", str(fixed)]) == 0
    assert "4 spp" in capsys.readouterr().out
    assert {p.name for p in tmp_path.iterdir()} == {"c.exr", "c.png", "c.xml"}
    want = distributed.render_local(str(tmp_path / "c.xml"), 4, chunk_spp=1)
    np.testing.assert_array_equal(read_exr(fixed), np.array(want)[..., :read_exr(fixed).shape[-1]])


@pytest.mark.parametrize("argv,words", [
    (["--no-adaptive", "--noise", "0.1"], "--noise and --time are for adaptive sampling"),
    (["--noise", "0"], "--noise"),
    (["--time", "-1"], "--time"),
])
def test04_sampling_flags_are_checked(llvm, tmp_path, capsys, argv, words):
    """Contradictory or bad sampling flags are one-line errors before any
    rendering."""
    try:
        code = main(["render", "scenes/data/cloud.cells", "--res", "8", "-o", str(tmp_path / "x.exr"), "-q", *argv])
    except SystemExit as e:                  # argparse's refusals
        code = e.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and words in err and "\n" not in err, err
    assert not (tmp_path / "x.exr").exists()


def test05_the_benchmark_takes_the_references_own_error_off():
    """`mi_amr.bench.adaptive.rel_err`: against a reference with noise of its
    own, the error of a picture with known error comes out as that error
    (the reference's mean squared error taken off), within the spread of
    200 000 pixels' squared errors (here 1% of it)."""
    from mi_amr.bench.adaptive import rel_err
    rng = np.random.default_rng(5)
    truth = rng.uniform(0.5, 1.5, (200, 333, 3))
    ref = truth + rng.normal(0, 0.02, truth.shape)
    picture = truth + rng.normal(0, 0.03, truth.shape)
    got = rel_err(picture, ref, ref_mse=0.02 ** 2)
    assert abs(got["err"] - 0.03 / truth.mean()) < 0.01 * 0.03 / truth.mean(), got
    assert got["measured"] > got["err"]


def test06_a_clean_view_stops_refining():
    """The viewer's scheduler (`mi_amr.view.scheduler`) with passes of a
    known noise (the truth plus Gaussian noise of 6 `DENOISED_NOISE` per
    pass, 1 spp each):
    the view asks for full passes until every tile's half-buffer estimate
    is below `DENOISED_NOISE` (the denoiser on), then for none, its
    estimate within 20% of the truth's error (256 pixels a tile); with the
    denoiser off it asks for passes again (the lower noise); a change
    starts over."""
    import math
    import time
    from mi_amr.view.scheduler import CLEAN_CHECK
    engine, view = dataless_view(32, 4096)
    view.denoise = True
    rng = np.random.default_rng(3)
    truth = np.full((32, 32, 3), 1.0)
    sigma = 6 * adaptive.DENOISED_NOISE
    with engine._wake:
        view.accum_epoch, view.spp, view.accum = view.epoch, 0, np.zeros((32, 32, 3))
        passes = []
        while engine._next_pass(view, time.monotonic())[0] == "full" and view.spp < 4096:
            image = truth + rng.normal(0.0, sigma, truth.shape)
            view.accum += image
            view.spp += 1
            engine._check_clean(view, image)
            passes.append(view.spp)
        true_error = np.sqrt(np.mean((view.accum / view.spp - truth) ** 2))
        estimate = engine._clean[view.id][1]
        assert view.spp % CLEAN_CHECK == 0 and estimate < adaptive.DENOISED_NOISE
        # sigma / sqrt(spp) < DENOISED_NOISE first at 36 spp, checked at 40
        assert 32 <= view.spp <= 48 and abs(estimate - true_error) < 0.2 * true_error, (view.spp, estimate)
        assert engine._next_pass(view, time.monotonic()) == (None, math.inf)
        view.denoise = False                          # 0.02 now: refining goes on
        assert engine._next_pass(view, time.monotonic())[0] == "full"
        view.denoise = True
        view.epoch += 1                               # a change: a new accumulation, not clean
        view.accum_epoch = view.epoch
        view.spp = 1
        assert engine._next_pass(view, time.monotonic())[0] == "full"
