"""Blackbody emission (``emission_model="blackbody"``, docs/manual/glowing-gas.md):
Planck's law at the sampled wavelengths in spectral variants, its CIE 1931
projection to linear sRGB from a table over temperature in rgb variants.
The rgb render equals the spectral render (which Mitsuba's film turns into
sRGB) within Monte Carlo noise (per-block z-test over passes, |z| < 4):
the table's error, checked against exact integration here, is far below it.
The tests that switch variants run in a process of their own
(`own_process.in_own_process`).
"""


import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.params import ParameterError
from mi_amr.testing import block_z_scores, render_passes
from mi_amr.transfer import spectra

from conftest import volume_scene
from own_process import RGB, in_own_process, in_variant

PASSES = 16
#: The documented bound on the rgb table's error, relative to the
#: luminance of the same temperature (docs/manual/glowing-gas.md).
TABLE_ERROR = 3e-3


def hot_gas():
    """Single-level data whose values are temperatures, 2500 to 12000 K."""
    rng = np.random.default_rng(3)
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, 12)] * 3, indexing="ij")
    t = 2500.0 + 9500.0 * np.exp(-2.0 * (x ** 2 + y ** 2 + z ** 2)) * rng.uniform(0.7, 1.0, x.shape)
    return mi_amr.dense_to_amr(t.astype(np.float32), 0.0, 0)


def glowing(cells, **kw):
    """Black (purely absorbing) gas of rising opacity that glows as a blackbody."""
    lo, hi = cells.value_range
    tf = mi_amr.TransferFunction([[0, 0, 0, 0.2], [0, 0, 0, 1.0]], (lo, hi))
    return {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 4.0,
            "emission_model": "blackbody", **kw}


@in_own_process
def test01_the_rgb_table_matches_exact_integration():
    """The table's linear sRGB against the exact CIE integration (numpy,
    float64) from 1000 K to 1e9 K: within `TABLE_ERROR` of the
    temperature's luminance per channel; 0 at and below 0 K. And the
    spectral kernel's Planck's law against numpy's at a few wavelengths."""
    mi.set_variant(RGB)
    t = np.logspace(3, 9, 400)
    exact = spectra.blackbody_rgb_host(t)
    table = mi.Float(spectra.blackbody_table().ravel())
    got = np.asarray(spectra.blackbody_radiance(table, mi.Float(t.astype(np.float32)), None), np.float64).T
    luminance = spectra.blackbody_xyz(t)[:, 1] / spectra.blackbody_norm()
    err = np.abs(got - exact).max(axis=1) / luminance
    assert err.max() < TABLE_ERROR, (t[err.argmax()], err.max())
    zero = spectra.blackbody_radiance(table, mi.Float([0.0, -5.0]), None)
    assert np.all(np.asarray(zero) == 0.0)
    with in_variant("spectral"):
        lam = np.array([[400.0, 500.0], [550.0, 600.0], [650.0, 700.0], [450.0, 750.0]], np.float32)
        wl = mi.Spectrum([mi.Float(r) for r in lam])
        temps = np.array([3000.0, 20000.0])
        got = np.asarray(spectra.blackbody_radiance(None, mi.Float(temps.astype(np.float32)), wl), np.float64)
        ref = spectra.planck_relative(lam.astype(np.float64), temps[None, :]) / spectra.blackbody_norm()
        assert got == pytest.approx(ref, rel=2e-4)
    # the convention: a 6500 K blackbody has luminance 1, white to a few percent
    rgb = spectra.blackbody_rgb_host(spectra.BLACKBODY_REFERENCE_K)[0]
    assert float(spectra.blackbody_xyz(6500.0)[0, 1] / spectra.blackbody_norm()) == pytest.approx(1.0)
    assert rgb == pytest.approx([1.0, 1.0, 1.0], abs=0.05)


@in_own_process
def test02_spectral_render_in_srgb_matches_the_rgb_render():
    """The same glowing gas rendered by ``amrvolpath`` in llvm_ad_spectral
    (Planck's law per wavelength; Mitsuba's film integrates against the
    CIE curves and converts to sRGB) and in llvm_ad_rgb (the table): the
    same image in expectation, per-block z-test over passes."""
    cells = hot_gas()
    scene = volume_scene(glowing(cells), res=16, integrator="amrvolpath", max_depth=8, emitters="")
    with in_variant("spectral"):
        a = render_passes(mi.load_dict(scene), PASSES, 16)
    mi.set_variant(RGB)
    b = render_passes(mi.load_dict(scene), PASSES, 16, seed0=10_000)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    z = block_z_scores(a, b, 4)
    assert np.abs(z).max() < 4.0, f"max |z| = {np.abs(z).max():.2f}"
    mean = b.mean(axis=(0, 1, 2))
    assert mean.min() > 0.01                            # the gas is seen glowing


def test03_blackbody_options_are_checked(llvm):
    """An emission TF, an emission domain or a log10 transform with the
    blackbody are refused in one line; only ``emission_scale`` is a scene
    parameter, and `set_emission` refuses a TF."""
    cells = hot_gas()
    for extra in ({"emission": "blackbody"}, {"emission_min": 1.0}, {"emission_transform": "log10"},
                  {"emission_model": "planck"}):
        with pytest.raises(Exception) as e:
            mi.load_dict(glowing(cells, **extra))
        assert "emission" in str(e.value).strip().splitlines()[-1]
    with pytest.raises(Exception, match="kelvin"):
        mi.load_dict(glowing(cells, value_transform="log10"))
    med = mi.load_dict(glowing(cells, emission_scale=2.0))
    keys = [k for k in mi.traverse(med).keys() if k.startswith("emission")]
    assert keys == ["emission_scale"]
    with pytest.raises(ParameterError, match="blackbody"):
        med.set_emission(mi_amr.TransferFunction([[1, 1, 1, 1], [1, 1, 1, 1]], (0, 1)))
    med.set_emission(emission_scale=3.0)
    assert med.classification.emission_scale_value == 3.0
