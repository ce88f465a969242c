"""The one owner of a medium's classification: its transfer function and density scale.

``sigma_t(x) = density_scale * alpha(f(x))`` (inverse world units) and the
albedo ``rgb(f(x))`` come from two pieces of state, the TF and the density
scale. `Classification` holds both, in every form the code needs:

* host: the `TransferFunction` and the scale as a Python float (for host
  builds whose shape depends on them: the SAH kd-tree, the grid cost model);
* device: the `DeviceTransferFunction` tables and the scale as an opaque
  Dr.Jit variable (the kernels read these);
* scene parameters: ``tf_rgba``, ``tf_domain`` and ``density_scale``,
  exposed to ``mi.traverse`` (`traverse`).

A medium that glows also has an *emission* TF over its emission field
(the same field or another one on the same cells) and an emission scale:
the radiance of the absorbing gas is ``L_e(g) = emission_scale *
rgb(g) * alpha(g)`` (``alpha`` an intensity in [0, 1]), emitted per unit
length as ``sigma_a L_e`` with ``sigma_a = sigma_t (1 - albedo)``
(docs/design.md section 12). Whether a medium glows is fixed at load (it
decides the kernel); the emission TF and scale change like the others
(``emission_rgba``, ``emission_domain``, ``emission_scale``) and move no
majorant.

Every change goes through `set` (a direct call) or `apply_parameters`
(after ``params.update()`` wrote new values into the traversed variables),
which validate and then call `set`: one update path. Whoever depends on the
classification (the medium's structures) is told through the listener given
to the constructor, after the new state is in place.

All Dr.Jit variables are opaque and the tables live in memory of their own
(`mi_amr.core.jit_struct.owned`), so no change recompiles a kernel or
records a frozen function again.

Gradients (docs/design.md section 13): ``density_scale``, ``tf_rgba``,
``emission_scale`` and ``emission_rgba`` are differentiable scene
parameters. A traversed variable with gradients enabled is kept as it is
on an update (not replaced by a fresh copy) and the kernels read that very
variable (the TF table of ``device`` is then the traversed array itself),
so the collision terms carry its gradient; majorants and minorants are
computed from host tables and `majorant_scale`, detached.
"""

from __future__ import annotations

import weakref
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..core.jit_struct import jit_struct, owned
from ..params import ParameterError
from .device import DeviceTransferFunction
from .function import TransferFunction, range_majorants_host
from .spectra import blackbody_radiance, blackbody_table

#: The scene parameters a classification exposes.
PARAMETERS = ("density_scale", "tf_rgba", "tf_domain")
#: ... and those of a medium that glows.
EMISSION_PARAMETERS = ("emission_scale", "emission_rgba", "emission_domain")
#: ... and those of a medium that glows as a blackbody (no emission TF).
BLACKBODY_PARAMETERS = ("emission_scale",)
#: The emission table of a medium that does not glow (never read).
_DARK = TransferFunction(np.zeros((2, 4)), (0.0, 1.0))
#: How a glowing medium's emission field becomes radiance: an emission TF
#: (``tf``), or Planck's law at the field read as kelvin (``blackbody``;
#: `mi_amr.transfer.spectra`).
EMISSION_MODELS = ("tf", "blackbody")


@jit_struct(scale="Float", tf_rgba="Float", tf_domain="Float", device=DeviceTransferFunction,
            emission_scale="Float", emission_rgba="Float", emission_domain="Float",
            emission_device=DeviceTransferFunction, blackbody="Float")
class Classification:
    """TF and density scale of one medium, and its emission TF and scale
    (see the module docstring).

    Dr.Jit state: ``scale`` (density scale), ``tf_rgba`` (the table, N x 4
    row major) and ``tf_domain`` ([lo, hi]) as traversed scene parameters,
    and ``device``, the tables the kernels read; the same for emission
    (``emission_scale``, ``emission_rgba``, ``emission_domain``,
    ``emission_device``).
    """

    def __init__(self, tf: TransferFunction, density_scale: float,
                 on_change: Callable[["Classification"], None] | None = None,
                 emission: TransferFunction | None = None, emission_scale: float = 1.0,
                 emission_model: str = "tf"):
        self.on_change = on_change
        self.tf = _check_tf(tf)
        self.density_scale = check_density_scale(density_scale)
        self.scale = mi.Float(self.density_scale)
        self.tf_rgba = owned(mi.Float, self.tf.rgba)
        self.tf_domain = mi.Float(self.tf.domain)
        self.device = DeviceTransferFunction(self.tf)
        dr.make_opaque(self.scale, self.tf_rgba, self.tf_domain)
        #: whether the medium glows (fixed at load: it shapes the kernel)
        if emission_model not in EMISSION_MODELS:
            raise ParameterError(f"amr: emission_model must be one of {', '.join(EMISSION_MODELS)}, "
                                 f"got {emission_model!r}")
        #: ``tf`` or ``blackbody`` (fixed at load: it shapes the kernel)
        self.emission_model = emission_model
        self.glows = emission is not None or emission_model == "blackbody"
        self.emission = _check_tf(emission) if emission is not None else None
        self.emission_scale_value = check_emission_scale(emission_scale)
        self.emission_scale = mi.Float(self.emission_scale_value)
        table = self.emission if self.emission is not None else _DARK
        self.emission_rgba = owned(mi.Float, table.rgba)
        self.emission_domain = mi.Float(table.domain)
        self.emission_device = DeviceTransferFunction(table)
        dr.make_opaque(self.emission_scale, self.emission_rgba, self.emission_domain)
        # the blackbody's XYZ table over temperature (rgb and mono variants)
        self.blackbody = None
        if emission_model == "blackbody":
            self.blackbody = owned(mi.Float, blackbody_table().ravel())
            dr.make_opaque(self.blackbody)

    # ---- The one update path --------------------------------------------------
    def set(self, tf: TransferFunction | None = None, density_scale: float | None = None,
            emission: TransferFunction | None = None, emission_scale: float | None = None,
            keep_gradients: bool = True):
        """Use a new TF and/or density scale, emission TF and/or emission
        scale (None keeps the current one): validated first (a bad value
        raises and changes nothing), then uploaded, then the listener is
        told (when extinction changed: emission moves no majorant).

        ``keep_gradients``: a traversed variable with gradients enabled
        already holds the new value (``params.update()`` wrote it) and stays
        as it is, so that the kernels read it and its gradient reaches the
        caller; False replaces it too (the last valid state put back)."""
        only_emission = tf is None and density_scale is None and (emission is not None or emission_scale is not None)
        tf = self.tf if tf is None else _check_tf(tf)
        scale = self.density_scale if density_scale is None else check_density_scale(density_scale)
        if (emission is not None or emission_scale is not None) and not self.glows:
            raise ParameterError("amr: this medium was loaded without emission; give it an 'emission' TF "
                                 "at load to change its emission later")
        if emission is not None and self.emission_model == "blackbody":
            raise ParameterError("amr: this medium glows as a blackbody (emission_model='blackbody'), which "
                                 "has no emission TF; only emission_scale changes")
        emission = self.emission if emission is None else _check_tf(emission)
        e_scale = self.emission_scale_value if emission_scale is None else check_emission_scale(emission_scale)
        self.tf, self.density_scale = tf, scale
        _upload(self.tf_rgba, self.tf_domain, self.scale, tf, scale, keep_gradients)
        self.device.set(tf, _attached(self.tf_rgba))
        if self.glows:
            self.emission, self.emission_scale_value = emission, e_scale
            table = _DARK if emission is None else emission          # a blackbody has no TF
            _upload(self.emission_rgba, self.emission_domain, self.emission_scale, table, e_scale, keep_gradients)
            self.emission_device.set(table, _attached(self.emission_rgba))
        listener = self._listener() if self._listener is not None else None
        if listener is not None and not only_emission:
            listener(self)

    @property
    def on_change(self):
        """Called with this object after every change (held weakly: the
        listener's owner usually holds this object, and a reference cycle
        would leave both, with their device arrays, to the garbage collector)."""
        return self._listener() if self._listener is not None else None

    @on_change.setter
    def on_change(self, listener):
        if listener is None:
            self._listener = None
        elif hasattr(listener, "__self__"):
            self._listener = weakref.WeakMethod(listener)
        else:
            self._listener = weakref.ref(listener)

    def apply_parameters(self, keys=None):
        """Take the values ``params.update()`` wrote into the traversed
        variables (``keys``: the names that changed; None: all) through
        `set`. A bad value raises a `ParameterError`, and the last valid
        state is put back into the variables."""
        names = self.parameter_names
        keys = set(names if keys is None else keys) & set(names)
        if not keys:
            return
        try:
            tf = self._tf_from(self.tf_rgba, self.tf_domain, "tf") if keys & {"tf_rgba", "tf_domain"} else None
            scale = float(self.scale.numpy()[0]) if "density_scale" in keys else None
            if scale is not None:
                check_density_scale(scale)
            emission = (self._tf_from(self.emission_rgba, self.emission_domain, "emission")
                        if keys & {"emission_rgba", "emission_domain"} else None)
            e_scale = float(self.emission_scale.numpy()[0]) if "emission_scale" in keys else None
            if e_scale is not None:
                check_emission_scale(e_scale)
        except ValueError:
            self.set(keep_gradients=False)  # the last valid state, back into the variables
            raise
        self.set(tf, scale, emission, e_scale)

    @property
    def parameter_names(self) -> tuple:
        """The scene parameters of this classification (`traverse`)."""
        if self.emission_model == "blackbody":
            return PARAMETERS + BLACKBODY_PARAMETERS
        return PARAMETERS + (EMISSION_PARAMETERS if self.glows else ())

    @staticmethod
    def _tf_from(rgba_var, domain_var, prefix: str) -> TransferFunction:
        rgba = np.asarray(rgba_var.numpy(), dtype=np.float64)
        dom = domain_var.numpy()
        if rgba.size % 4 or dom.size != 2:
            raise ParameterError(f"amr: {prefix}_rgba must hold N x 4 values and {prefix}_domain 2, "
                                 f"got {rgba.size} and {dom.size}")
        return TransferFunction(rgba.reshape(-1, 4), (float(dom[0]), float(dom[1])))

    # ---- Views ----------------------------------------------------------------
    def traverse(self, callback):
        """Expose ``density_scale`` and ``tf_rgba`` (differentiable) and
        ``tf_domain`` (not: it moves the table's entries) to
        ``mi.traverse``; for a medium that glows also ``emission_scale``,
        ``emission_rgba`` (differentiable) and ``emission_domain``."""
        callback.put("density_scale", self.scale, mi.ParamFlags.Differentiable)
        callback.put("tf_rgba", self.tf_rgba, mi.ParamFlags.Differentiable)
        callback.put("tf_domain", self.tf_domain, mi.ParamFlags.NonDifferentiable)
        if self.glows:
            callback.put("emission_scale", self.emission_scale, mi.ParamFlags.Differentiable)
        if self.emission is not None:
            callback.put("emission_rgba", self.emission_rgba, mi.ParamFlags.Differentiable)
            callback.put("emission_domain", self.emission_domain, mi.ParamFlags.NonDifferentiable)

    @property
    def majorant_scale(self):
        """The density scale without its gradient: majorants and minorants
        are bounds, not terms of the estimate, and stay detached."""
        return dr.detach(self.scale)

    def host_majorants(self, vmin, vmax) -> np.ndarray:
        """``density_scale * max alpha`` over each value range (numpy, inverse
        world units; 0 for empty ranges), as the device update computes it."""
        return range_majorants_host(self.tf, vmin, vmax, self.density_scale)

    def sigma_t(self, value, found):
        """Extinction at reconstructed values (inverse world units; 0 where
        no value was found)."""
        return dr.select(found, self.scale * self.device.eval_alpha(value, found), 0.0)

    def emitted_radiance(self, value, found, wavelengths=None):
        """``L_e`` at emission-field values as the active variant's
        unpolarized spectrum at ``wavelengths`` (radiance; 0 where no value
        was found): ``emission_scale * colour * alpha`` of the emission TF
        (the colour an emitted spectrum, `DeviceTransferFunction.eval_colour`),
        or for a blackbody ``emission_scale`` times Planck's law at the
        value in kelvin, normalised (`mi_amr.transfer.spectra`)."""
        if self.emission_model == "blackbody":
            return dr.select(found, self.emission_scale * blackbody_radiance(self.blackbody, value, wavelengths,
                                                                             found), 0.0)
        alpha = self.emission_device.eval_alpha(value, found)
        colour = self.emission_device.eval_colour(value, found, wavelengths, emitted=True)
        return dr.select(found, self.emission_scale * alpha * colour, 0.0)

    def albedo_and_sigma_t(self, value, found, wavelengths=None):
        """``(albedo, sigma_t)`` at reconstructed values, the albedo the
        active variant's unpolarized spectrum at ``wavelengths``."""
        alpha = self.device.eval_alpha(value, found)
        return (self.device.eval_colour(value, found, wavelengths),
                dr.select(found, self.scale * alpha, 0.0))


def _check_tf(tf) -> TransferFunction:
    if not isinstance(tf, TransferFunction):
        raise ParameterError(f"amr: expected a TransferFunction, got {type(tf).__name__}")
    return tf


def check_emission_scale(v) -> float:
    """``v`` as a valid emission scale (a radiance: finite, >= 0), or a
    `ParameterError`."""
    v = float(v)
    if not (np.isfinite(v) and 0 <= v <= 1e30):
        raise ParameterError(f"amr: emission_scale must be a finite number in [0, 1e30], got {v:g}")
    return v


#: Largest density_scale: majorants and their reciprocals stay normal float32
#: numbers (at 1e38 the reciprocal flushes to 0 and a medium turns clear).
MAX_DENSITY_SCALE = 1e30


def check_density_scale(v) -> float:
    """``v`` as a valid density scale, or a `ParameterError`."""
    v = float(v)
    if not (np.isfinite(v) and 0 <= v <= MAX_DENSITY_SCALE):
        raise ParameterError(f"amr: density_scale must be a finite number in [0, {MAX_DENSITY_SCALE:g}], got {v:g}")
    return v


def _upload(rgba, domain, scale, tf: TransferFunction, value: float, keep_gradients: bool = True) -> None:
    """Write ``tf``'s table and domain and the scale ``value`` into the
    traversed variables in place (SceneParameters hold them), opaque so that
    a new value never recompiles a kernel. With ``keep_gradients``, a
    variable with gradients enabled holds its value already and is left as
    it is: replacing it would cut the caller's gradient."""
    if not (keep_gradients and dr.grad_enabled(rgba)):
        mi.set_property(rgba, owned(mi.Float, tf.rgba))
    mi.set_property(domain, mi.Float(tf.domain))
    if not (keep_gradients and dr.grad_enabled(scale)):
        mi.set_property(scale, mi.Float(value))
    dr.make_opaque(scale, rgba, domain)


def _attached(table):
    """``table`` where it carries gradients (the kernels must read that very
    variable), else None (the device TF uploads a copy of its own)."""
    return table if dr.grad_enabled(table) else None
