"""Dr.Jit side of a transfer function: evaluation, range majorants and minorants.

All table data, the domain and the table size are opaque Dr.Jit variables,
so loading a different TF (other values, domain or size) changes no kernel.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..core.jit_struct import jit_struct, owned
from .function import TransferFunction
from .spectra import colour_as_spectrum, spectrum_of_entry, upsampling_jacobian, upsampling_table, variant_kind


@jit_struct(rgba="Float", sparse="Float", sparse_min="Float", n="UInt32", lo="Float", inv_width="Float",
            rgb_constant="Bool", spectral="Float", spectral_jacobian="Float")
class DeviceTransferFunction:
    """A `TransferFunction` uploaded for use in Dr.Jit kernels."""

    def __init__(self, tf: TransferFunction):
        self.set(tf)

    def set(self, tf: TransferFunction, rgba=None):
        """Upload a (new) TF: table, range-max sparse table, domain, size.
        ``rgba``: the table as a Dr.Jit array with gradients enabled (the
        traversed ``tf_rgba``), read by the kernels as it is so that its
        gradient flows; the sparse tables of the majorants come from
        ``tf``'s host table, detached."""
        self.tf = tf
        n = len(tf)
        self.rgba = owned(mi.Float, tf.rgba) if rgba is None else rgba
        self.sparse = owned(mi.Float, tf.sparse_table())
        self.sparse_min = owned(mi.Float, tf.sparse_table(np.minimum))
        self.n = mi.UInt32(n)
        self.lo = mi.Float(tf.domain[0])
        self.inv_width = mi.Float(1.0 / (tf.domain[1] - tf.domain[0]))
        # one colour for every value: the albedo is known without a look-up
        rgb = tf.rgba[:, :3]
        self.rgb_constant = mi.Bool(bool(np.all(rgb == rgb[0])))
        dr.make_opaque(self.rgba, self.sparse, self.sparse_min, self.n, self.lo, self.inv_width,
                       self.rgb_constant)
        # spectral variants: each entry's colour upsampled as gridvolume does
        # (`mi_amr.transfer.spectra`); None elsewhere (no kernel reads it)
        # and, where the table carries gradients, their derivatives by the
        # colours (`upsampling_jacobian`)
        self.spectral = self.spectral_jacobian = None
        if variant_kind() == "spectral":
            self.spectral = owned(mi.Float, upsampling_table(rgb).ravel())
            dr.make_opaque(self.spectral)
            if rgba is not None and dr.grad_enabled(rgba):
                self.spectral_jacobian = owned(mi.Float, upsampling_jacobian(rgb).ravel())
                dr.make_opaque(self.spectral_jacobian)

    def _u(self, v):
        return dr.clip((v - self.lo) * self.inv_width, 0.0, 1.0)

    def eval(self, v, active=True):
        """(rgb, alpha) at values ``v``: linear interpolation of the table."""
        c = self._channels(v, range(4), active)
        return mi.Color3f(c[0], c[1], c[2]), c[3]

    def eval_alpha(self, v, active=True):
        """Alpha at values ``v`` (as `eval`, one channel)."""
        return self._channels(v, (3,), active)[0]

    def eval_rgb(self, v, active=True):
        """Colour at values ``v`` (as `eval`, three channels)."""
        return mi.Color3f(*self._channels(v, range(3), active))

    def eval_colour(self, v, active=True, wavelengths=None, emitted: bool = False):
        """The colour at values ``v`` as the active variant's unpolarized
        spectrum at ``wavelengths`` (`colour_as_spectrum`): rgb as
        `eval_rgb`, its luminance in mono, in spectral the linear
        interpolation of the two entries' upsampled spectra (times D65 for
        an ``emitted`` colour). The spectral form's gradient reaches the
        table's colours through `upsampling_jacobian` (first order)."""
        def entries(wl):
            i, f = self._entry(v)
            a = self._entry_spectrum(i, wl, active)
            b = self._entry_spectrum(i + 1, wl, active)
            return dr.fma(f, b - a, a)
        rgb = None if variant_kind() == "spectral" else self.eval_rgb(v, active)
        return colour_as_spectrum(rgb, wavelengths, emitted, entries)

    def _entry_spectrum(self, i, wavelengths, active):
        """Entry ``i``'s upsampled spectrum (`spectrum_of_entry`); with
        gradients on the table, its coefficients move with the entry's
        colour to first order (zero in value, the derivative in AD)."""
        if self.spectral_jacobian is None or not dr.grad_enabled(self.rgba):
            return spectrum_of_entry(self.spectral, i, wavelengths, active)
        c = [dr.gather(mi.Float, self.spectral, 4 * i + m, active) for m in range(4)]
        for k in range(3):
            colour = dr.gather(mi.Float, self.rgba, 4 * i + k, active)
            delta = colour - dr.detach(colour)
            c = [c[m] + delta * dr.gather(mi.Float, self.spectral_jacobian, 12 * i + 4 * k + m, active)
                 for m in range(4)]
        return c[3] * mi.srgb_model_eval(mi.Vector3f(c[0], c[1], c[2]), wavelengths)

    def _entry(self, v):
        """Table entry ``i`` below ``v`` and the weight ``f`` of entry ``i + 1``."""
        n1 = self.n - 1
        x = self._u(v) * mi.Float(n1)
        i = dr.minimum(mi.UInt32(dr.floor(x)), n1 - 1)
        return i, x - mi.Float(i)

    def _channels(self, v, channels, active):
        n1 = self.n - 1
        x = self._u(v) * mi.Float(n1)
        i = dr.minimum(mi.UInt32(dr.floor(x)), n1 - 1)
        f = x - mi.Float(i)
        # one gather per channel, not a 4-wide packet gather: Dr.Jit's packet
        # gathers compile to one of two codes at random (measured with
        # dr.JitFlag.KernelHistory), which would cost a compile now and then
        c = []
        for k in channels:
            a = dr.gather(mi.Float, self.rgba, 4 * i + k, active)
            b = dr.gather(mi.Float, self.rgba, 4 * i + 4 + k, active)
            c.append(dr.fma(f, b - a, a))
        return c

    def range_max_alpha(self, vmin, vmax, active=True):
        """Maximum table alpha over entries ``floor(u_min (N-1)) ..
        ceil(u_max (N-1))`` (clamped): the entries whose segments the values
        of ``[vmin, vmax]`` interpolate between (a range ending exactly on an
        entry does not reach the next one); 0 for an empty range (``vmin >
        vmax``). O(1) per range via the sparse table. ``u (N-1)`` is rounded
        as in `eval`, which keeps every evaluated alpha within the bound."""
        return self._range_alpha(self.sparse, dr.maximum, vmin, vmax, active)

    def range_min_alpha(self, vmin, vmax, active=True):
        """Minimum table alpha over the same entries as `range_max_alpha`:
        every alpha `eval` interpolates for a value of ``[vmin, vmax]`` lies
        between two of them, so it is at least this (up to the rounding of
        one interpolation); 0 for an empty range."""
        return self._range_alpha(self.sparse_min, dr.minimum, vmin, vmax, active)

    def _range_alpha(self, table, op, vmin, vmax, active):
        n1 = self.n - 1
        lo = dr.minimum(mi.UInt32(dr.floor(self._u(vmin) * mi.Float(n1))), n1)
        hi = dr.minimum(mi.UInt32(dr.ceil(self._u(vmax) * mi.Float(n1))), n1)
        valid = active & (vmin <= vmax)
        hi = dr.maximum(hi, lo)
        k = 31 - dr.lzcnt(hi - lo + 1)
        row = k * self.n
        m0 = dr.gather(mi.Float, table, row + lo, valid)
        m1 = dr.gather(mi.Float, table, row + hi + 1 - (mi.UInt32(1) << k), valid)
        return dr.select(valid, op(m0, m1), 0.0)
