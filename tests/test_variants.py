"""The plugins in Mitsuba's spectral and monochromatic variants (issue 54).

Each test runs in a process of its own (`own_process.in_own_process`: the
suite's process stays in its rgb variant), sets its variant and puts the
rgb one back (`in_variant`). The
colour conversions are checked against Mitsuba's own ``gridvolume`` and
``d65`` textures; the images against ``heterogeneous`` + ``gridvolume`` on
the same single-level data by per-block z-tests over independent passes
(|z| < 4, `mi_amr.testing.block_z_scores`), as tests/test_medium.py does
in rgb. Blackbody emission: tests/test_blackbody.py.
"""


import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.reference import reference_medium
from mi_amr.testing import block_z_scores, render_passes
from mi_amr.transfer.spectra import refusal, variant_kind

from conftest import volume_scene
from own_process import PREFIX, in_own_process, in_variant

PASSES = 16
Z_MAX = 4.0
#: the JIT backend of the variants the tests switch to (cuda where the
#: suite is forced onto it)
#: Seven TF entries of different colours (one grey): the data's values fall
#: on the entries, so that the amr medium's colour is the entry's own, as
#: the baked grid's voxel is.
ENTRY_RGBA = np.array([[0.9, 0.2, 0.1, 0.0], [0.2, 0.8, 0.3, 0.3], [0.1, 0.3, 0.9, 0.6], [0.5, 0.5, 0.5, 1.0],
                       [0.95, 0.9, 0.2, 0.8], [0.3, 0.1, 0.6, 0.4], [0.7, 0.7, 0.9, 0.2]])


def entry_data():
    """Single-level data (10 x 12 x 14 cells) whose values are the TF's entries (0, 1/6, .., 1)."""
    rng = np.random.default_rng(7)
    v = (rng.integers(0, 7, (10, 12, 14)) / 6.0).astype(np.float32)
    return mi_amr.dense_to_amr(v, 0.0, 0), mi_amr.TransferFunction(ENTRY_RGBA, (0.0, 1.0))


def wavelengths_of(n):
    """Spectral sample wavelengths (nm) spread over the visible range, n lanes."""
    c = dr.size_v(mi.Spectrum)
    lam = np.linspace(380.0, 780.0, n * c).reshape(c, n).astype(np.float32)
    return mi.Spectrum([mi.Float(lam[i]) for i in range(c)])


@pytest.mark.parametrize("kind", ["spectral", "mono"])
@in_own_process
def test01_tf_colours_become_spectra_as_mitsuba_textures_do(kind):
    """At every TF entry the medium's albedo equals Mitsuba's ``gridvolume``
    holding that colour (spectral upsampling / luminance) and the emitted
    colour equals Mitsuba's ``d65`` texture of it (an RGB radiance of an
    emitter), at the same wavelengths, to float32 rounding."""
    with in_variant(kind):
        cells, tf = entry_data()
        med = mi.load_dict({"type": "amr", "data": cells, "transfer_function": tf, "reconstruction": "nearest",
                            "emission": tf, "emission_min": 0.0, "emission_max": 1.0})
        n = len(ENTRY_RGBA)
        values = mi.Float(np.arange(n) / (n - 1.0))
        it = dr.zeros(mi.SurfaceInteraction3f, n)
        it.p = mi.Point3f(0.5, 0.5, mi.Float((np.arange(n) + 0.5) / n))    # lane i: voxel i of n x 1 x 1
        if kind == "spectral":
            it.wavelengths = wavelengths_of(n)
        albedo, _ = med.classification.albedo_and_sigma_t(values, mi.Bool(True), it.wavelengths)
        emitted = med.classification.emitted_radiance(values, mi.Bool(True), it.wavelengths)
        grid = mi.load_dict({"type": "gridvolume", "filter_type": "nearest", "grid": mi.VolumeGrid(
            np.ascontiguousarray(ENTRY_RGBA[:, None, None, :3], np.float32))})
        channels = dr.size_v(mi.Spectrum)

        def lanes(x):
            a = np.asarray(x, np.float64).reshape(channels, -1)        # (channels, lanes), a constant: 1 lane
            return np.broadcast_to(a, (channels, n)).T

        assert lanes(albedo) == pytest.approx(lanes(grid.eval(it)), rel=1e-5, abs=1e-6), kind
        for i in range(n):
            d65 = mi.load_dict({"type": "d65", "color": ENTRY_RGBA[i, :3].tolist()})
            ref = lanes(d65.eval(it))[i] * ENTRY_RGBA[i, 3]
            assert lanes(emitted)[i] == pytest.approx(ref, rel=1e-5, abs=1e-6), (kind, i)


@pytest.mark.parametrize("kind", ["spectral", "mono"])
@in_own_process
def test02_amrvolpath_matches_heterogeneous_gridvolume(kind):
    """The ``amr`` medium in ``amrvolpath`` and Mitsuba's ``heterogeneous``
    + ``gridvolume`` (nearest) in ``volpath`` on the same single-level data
    and TF colours: the same image in expectation (per-block z-test over
    independent passes), in the spectral and the mono variant."""
    with in_variant(kind):
        cells, tf = entry_data()
        a = render_passes(mi.load_dict(volume_scene(
            {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 12.0,
             "reconstruction": "nearest"}, res=16, integrator="amrvolpath", max_depth=8)), PASSES, 16)
        b = render_passes(mi.load_dict(volume_scene(
            reference_medium(cells, tf, 12.0, "nearest"), res=16, max_depth=8)), PASSES, 16, seed0=10_000)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    z = block_z_scores(a, b, 4)
    assert np.abs(z).max() < Z_MAX, f"{kind}: max |z| = {np.abs(z).max():.2f}"
    assert a.mean(axis=0)[..., 0].std() > 0.02          # the medium is seen


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["spectral", "mono"])
@pytest.mark.parametrize("integrator", ["volpath", "amrprbvolpath"])
@in_own_process
def test03_stock_volpath_and_amrprbvolpath_match_heterogeneous_gridvolume(kind, integrator):
    """As test02, the ``amr`` medium rendered by Mitsuba's ``volpath``
    (its ``sample_interaction`` path) and by ``amrprbvolpath``'s primal."""
    with in_variant(kind):
        cells, tf = entry_data()
        a = render_passes(mi.load_dict(volume_scene(
            {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 12.0,
             "reconstruction": "nearest"}, res=16, integrator=integrator, max_depth=8)), PASSES, 16)
        b = render_passes(mi.load_dict(volume_scene(
            reference_medium(cells, tf, 12.0, "nearest"), res=16, max_depth=8)), PASSES, 16, seed0=10_000)
    z = block_z_scores(a, b, 4)
    assert np.abs(z).max() < Z_MAX, f"{kind} {integrator}: max |z| = {np.abs(z).max():.2f}"


@pytest.mark.parametrize("variant", ["scalar_rgb", "scalar_spectral", PREFIX + "spectral_polarized",
                                     PREFIX + "mono_polarized"])
@in_own_process
def test04_scalar_and_polarized_variants_are_refused_in_one_line(variant):
    """Scalar and polarized variants: a one-line error naming the variant and why."""
    with in_variant(variant):
        assert variant_kind() is None and refusal(variant)
        for desc in ({"type": "amr", "data": entry_data()[0]}, {"type": "amrvolpath"}, {"type": "amrprbvolpath"}):
            with pytest.raises(Exception) as e:
                mi.load_dict(desc)
            msg = str(e.value).strip().splitlines()[-1]
            assert variant in msg and ("scalar variants are refused" in msg or "polarized variants are refused"
                                       in msg), msg


@in_own_process
def test05_spectral_gradients_match_finite_differences():
    """``amrprbvolpath`` in llvm_ad_spectral, backward mode: the gradient of
    the image's mean along a TF entry's alpha and red (its spectrum through
    the upsampling's derivatives), against central differences of the same
    image with the same seed: tests/test_gradients.py's test02 (shapes,
    steps and z-test), in the spectral variant. The density scale's and the
    cells' directions, which reach the medium as the same numbers in every
    variant, are test02's in rgb (with them here: three backward kernels
    instead of one, 8.8 s CPU cold instead of about 4)."""
    from test_gradients import check_image_gradients
    with in_variant("spectral"):
        check_image_gradients("amrprbvolpath", "tent", keys=("tf_rgba",))
