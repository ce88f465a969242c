"""Colours as the active Mitsuba variant's spectra, and blackbody emission.

The TF holds sRGB colours (linear). Each JIT variant renders them as
Mitsuba renders an RGB texture there (docs/manual/medium.md, "Variants"):

* rgb: the colour itself;
* mono: its luminance (``mi.luminance``), as ``gridvolume`` does;
* spectral: Mitsuba's sRGB spectral upsampling as ``gridvolume`` applies
  it: per TF entry the scale ``s = 2 max(rgb)`` and the model coefficients
  of ``rgb / s`` (``mi.srgb_model_fetch``, host), evaluated per sample at
  its wavelengths (``s * mi.srgb_model_eval``); between two entries the two
  spectra are interpolated linearly, as a texture's texels are. An
  *emitted* colour is also multiplied by the CIE D65 illuminant
  (``mi.cie_d65``), as Mitsuba's emitters turn an RGB radiance into a
  spectrum (its ``d65`` texture), so that a white emission renders white.

Blackbody emission (`BLACKBODY_REFERENCE_K`): the radiance at temperature
``T`` (kelvin) and wavelength ``lambda`` is Planck's law divided by the
luminance ``Y`` of a blackbody at 6500 K, so that a 6500 K gas has
luminance 1 (times ``emission_scale``); Y is the CIE 1931 ``y`` integral
as Mitsuba's films normalise it (a flat spectrum of 1 has Y = 1). Spectral
variants evaluate Planck's law exactly at the sampled wavelengths; rgb and
mono variants look its CIE XYZ projection (converted to linear sRGB,
resp. Y) up in a table over ``log10 T`` (`blackbody_table`), interpolated
in ``log XYZ``; beyond the table it is 0 (colder) or grows linearly in T
(hotter: the Rayleigh-Jeans limit, exact to 1e-4 there).
"""

from __future__ import annotations

from functools import lru_cache

import drjit as dr
import mitsuba as mi
import numpy as np

#: The colour models of the JIT variants the plugins accept.
KINDS = ("rgb", "spectral", "mono")


def variant_kind(variant: str | None = None) -> str | None:
    """``"rgb"``, ``"spectral"`` or ``"mono"`` for a JIT variant the plugins
    render in, None for any other (`refusal` says why)."""
    v = mi.variant() if variant is None else variant
    if v is None or refusal(v) is not None:
        return None
    return v.rsplit("_", 1)[1]


def refusal(variant: str | None) -> str | None:
    """One line saying why the plugins refuse ``variant``, or None."""
    if variant is None:
        return "no Mitsuba variant is set"
    if not (variant.startswith("llvm_") or variant.startswith("cuda_")):
        return ("scalar variants are refused: the medium and integrators run as Dr.Jit kernels over "
                "many rays, which need a JIT variant (llvm_ad_* or cuda_ad_*)")
    if variant.endswith("_polarized"):
        return ("polarized variants are refused: the integrators carry unpolarized radiance (Mueller "
                "matrices at surfaces are not tracked); use the unpolarized form of the variant")
    if variant.rsplit("_", 1)[1] not in KINDS:
        return f"the variant {variant!r} is not one of the rgb, spectral or mono JIT variants"
    return None


def require_supported_variant(what: str = "mi_amr"):
    """A one-line RuntimeError unless the active variant is a JIT rgb,
    spectral or mono one."""
    v = mi.variant()
    why = refusal(v)
    if why is not None:
        raise RuntimeError(f"{what} needs a JIT Mitsuba variant (llvm_ad_rgb, llvm_ad_spectral, llvm_ad_mono or "
                           f"their cuda_ad_ forms); the active variant is {v!r}: {why}")


# ---- sRGB -> spectrum (host tables, device evaluation) ---------------------------
def upsampling_table(rgb: np.ndarray) -> np.ndarray:
    """Per row of ``rgb`` (N x 3, linear sRGB) the coefficients of Mitsuba's
    sRGB model for ``rgb / s`` and the scale ``s = 2 max(rgb)`` (N x 4,
    float32), exactly as ``gridvolume`` converts a voxel in spectral
    variants. Negative components are clamped to 0 first."""
    rgb = np.clip(np.asarray(rgb, np.float64).reshape(-1, 3), 0.0, None).astype(np.float32)
    unique, inverse = np.unique(rgb, axis=0, return_inverse=True)
    rows = np.zeros((len(unique), 4), np.float32)
    for k, c in enumerate(unique):
        s = np.float32(2.0) * c.max()
        norm = c / max(np.float32(1e-8), s)
        rows[k, :3] = np.asarray(mi.srgb_model_fetch(mi.ScalarColor3f(norm.tolist())), np.float32)
        rows[k, 3] = s
    return rows[np.asarray(inverse).reshape(-1)]


def upsampling_jacobian(rgb: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """The derivatives of each `upsampling_table` row (coefficients and
    scale) by the row's red, green and blue (N x 3 x 4, float32): central
    differences of step ``h`` (one-sided at 0). They carry the gradient of
    a TF colour into its spectrum (the model's coefficients come from a
    host table look-up, which Dr.Jit cannot differentiate)."""
    rgb = np.clip(np.asarray(rgb, np.float64).reshape(-1, 3), 0.0, None)
    jac = np.zeros((len(rgb), 3, 4), np.float32)
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        up, down = rgb + step, np.maximum(rgb - step, 0.0)
        jac[:, k, :] = (upsampling_table(up) - upsampling_table(down)) / (up[:, k] - down[:, k])[:, None]
    return jac


def _d65(wavelengths):
    """CIE D65 at each wavelength channel (Mitsuba's emitter normalisation)."""
    return mi.UnpolarizedSpectrum([mi.cie_d65(wavelengths[i]) for i in range(dr.size_v(mi.UnpolarizedSpectrum))])


def spectrum_of_entry(table, i, wavelengths, active=True):
    """The spectrum of entry ``i`` of an `upsampling_table` (uploaded as a
    flat Float array) at ``wavelengths``."""
    c = [dr.gather(mi.Float, table, 4 * i + k, active) for k in range(4)]
    return c[3] * mi.srgb_model_eval(mi.Vector3f(c[0], c[1], c[2]), wavelengths)


def colour_as_spectrum(rgb, wavelengths, emitted: bool = False, entries=None):
    """A colour (``mi.Color3f``) as the active variant's unpolarized spectrum
    at ``wavelengths``: itself (rgb), its luminance (mono) or, in spectral
    variants, ``entries(wavelengths)``: the interpolated spectra of its
    table entries (`spectrum_of_entry`), which the caller evaluates (the
    host-side upsampling of the TF's entries). ``emitted``: times D65 in
    spectral variants (module docstring)."""
    kind = variant_kind()
    if kind == "rgb":
        return rgb
    if kind == "mono":
        return mi.UnpolarizedSpectrum(mi.luminance(rgb))
    if wavelengths is None:
        raise ValueError("a TF colour in a spectral variant is a spectrum at the sample's wavelengths: pass "
                         "them (e.g. eval_local(u, active, mei.wavelengths))")
    spectrum = entries(wavelengths)
    return spectrum * _d65(wavelengths) if emitted else spectrum


# ---- Blackbody --------------------------------------------------------------------
#: The temperature (kelvin) whose blackbody has luminance 1 at emission_scale 1.
BLACKBODY_REFERENCE_K = 6500.0
#: Second radiation constant h c / k, nm K.
C2_NM_K = 1.438776877e7
#: The table of the rgb and mono variants: log10 T from ... to ... (kelvin), entries.
TABLE_LOG10_T = (2.0, 8.0)
TABLE_SIZE = 1024


def planck_relative(wavelength_nm, temperature_k):
    """Planck's spectral radiance up to a constant factor: ``(lambda /
    1 um)^-5 / (exp(c2 / (lambda T)) - 1)``; numpy (float64) or Dr.Jit
    (float32; 0 for T <= 0; exp overflow gives 0, small arguments use the
    series of expm1)."""
    if isinstance(wavelength_nm, np.ndarray) or isinstance(temperature_k, np.ndarray) or \
            np.isscalar(wavelength_nm):
        lam = np.asarray(wavelength_nm, np.float64)
        t = np.asarray(temperature_k, np.float64)
        with np.errstate(over="ignore", divide="ignore"):
            x = C2_NM_K / (lam * t)
            return np.where(t > 0, (lam * 1e-3) ** -5 / np.expm1(x), 0.0)
    lam = wavelength_nm
    t = dr.maximum(temperature_k, 1e-6)
    x = C2_NM_K / (lam * t)
    em1 = dr.select(x < 1e-3, x * (1.0 + 0.5 * x), dr.exp(dr.minimum(x, 88.0)) - 1.0)
    b = dr.power(lam * 1e-3, -5.0) / em1
    return dr.select((temperature_k > 0.0) & (x < 88.0), b, 0.0)


@lru_cache(maxsize=None)
def _cie_table():
    """(lambda (nm), xbar, ybar, zbar) on a 1 nm grid over Mitsuba's CIE range."""
    lam = np.arange(mi.MI_CIE_MIN, mi.MI_CIE_MAX + 0.5, 1.0)
    xyz = mi.cie1931_xyz(mi.Float(lam.astype(np.float32)))
    return lam, np.stack([np.asarray(xyz[k].numpy(), np.float64) for k in range(3)], axis=1)


def blackbody_xyz(temperature_k) -> np.ndarray:
    """CIE XYZ of `planck_relative` at temperatures (kelvin, numpy), in
    Mitsuba's film normalisation (trapezoid rule, 1 nm): N x 3, float64."""
    lam, cmf = _cie_table()
    t = np.atleast_1d(np.asarray(temperature_k, np.float64))
    b = planck_relative(lam[None, :], t[:, None])             # T x lambda
    return np.trapezoid(b[:, :, None] * cmf[None], lam, axis=1) * mi.MI_CIE_Y_NORMALIZATION


@lru_cache(maxsize=None)
def blackbody_norm() -> float:
    """Y of the 6500 K blackbody (`planck_relative`): the divisor of every
    blackbody radiance."""
    return float(blackbody_xyz(BLACKBODY_REFERENCE_K)[0, 1])


@lru_cache(maxsize=None)
def blackbody_table() -> np.ndarray:
    """``log`` of the normalised XYZ over ``log10 T`` in `TABLE_LOG10_T`
    (`TABLE_SIZE` x 3, float32, row major; -1e4 where a value is 0)."""
    t = np.logspace(*TABLE_LOG10_T, TABLE_SIZE)
    xyz = blackbody_xyz(t) / blackbody_norm()
    with np.errstate(divide="ignore"):
        return np.maximum(np.log(xyz), -1e4).astype(np.float32)


#: linear sRGB from CIE XYZ (Mitsuba's ``xyz_to_srgb``)
XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535],
                        [-0.969256, 1.875991, 0.041556],
                        [0.055648, -0.204043, 1.057311]])


def blackbody_rgb_host(temperature_k) -> np.ndarray:
    """Linear sRGB of the normalised blackbody at temperatures (numpy, exact
    integration; the reference of the table)."""
    return blackbody_xyz(temperature_k) / blackbody_norm() @ XYZ_TO_SRGB.T


def blackbody_luminance(temperature_k) -> np.ndarray:
    """Luminance Y of the normalised blackbody at temperatures (numpy,
    kelvin; any number of them, from `blackbody_table` as the rgb kernels
    look it up: 0 at or below the table, linear in T above it)."""
    t = np.asarray(temperature_k, np.float64)
    lo, hi = TABLE_LOG10_T
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.log10(np.where(t > 0, t, 1.0))
    y = np.exp(np.interp(u, np.linspace(lo, hi, TABLE_SIZE), blackbody_table()[:, 1].astype(np.float64)))
    y = np.where(u > hi, y * t / 10.0 ** hi, y)
    return np.where((t > 0) & (u >= lo), y, 0.0)


def blackbody_radiance(table, temperature_k, wavelengths, active=True):
    """The normalised blackbody radiance at ``temperature_k`` (Float,
    kelvin) as the active variant's unpolarized spectrum: Planck's law at
    ``wavelengths`` (spectral), or the table's (``table``: the uploaded
    `blackbody_table`) linear sRGB (rgb) or Y (mono)."""
    t = mi.Float(temperature_k)
    if variant_kind() == "spectral":
        if wavelengths is None:
            raise ValueError("blackbody radiance in a spectral variant needs the sample's wavelengths")
        n = dr.size_v(mi.UnpolarizedSpectrum)
        return mi.UnpolarizedSpectrum([planck_relative(wavelengths[i], t) for i in range(n)]) \
            * (1.0 / blackbody_norm())
    lo, hi = TABLE_LOG10_T
    n1 = TABLE_SIZE - 1
    u = (dr.log2(dr.maximum(t, 1e-30)) * float(np.log10(2.0)) - lo) * (n1 / (hi - lo))
    x = dr.clip(u, 0.0, float(n1))
    i = dr.minimum(mi.UInt32(dr.floor(x)), n1 - 1)
    f = x - mi.Float(i)
    xyz = []
    for k in range(3):
        a = dr.gather(mi.Float, table, 3 * i + k, active)
        b = dr.gather(mi.Float, table, 3 * i + 3 + k, active)
        xyz.append(dr.exp(dr.fma(f, b - a, a)))
    # hotter than the table: Rayleigh-Jeans, linear in T
    grow = dr.select(u > n1, t * (10.0 ** -hi), 1.0)
    xyz = [dr.select((u >= 0.0) & (t > 0.0), c * grow, 0.0) for c in xyz]
    if variant_kind() == "mono":
        return mi.UnpolarizedSpectrum(xyz[1])
    m = XYZ_TO_SRGB
    return mi.Color3f(*[float(m[r, 0]) * xyz[0] + float(m[r, 1]) * xyz[1] + float(m[r, 2]) * xyz[2]
                        for r in range(3)])
