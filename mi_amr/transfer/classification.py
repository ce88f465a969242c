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

Every change goes through `set` (a direct call) or `apply_parameters`
(after ``params.update()`` wrote new values into the traversed variables),
which validate and then call `set`: one update path. Whoever depends on the
classification (the medium's structures) is told through the listener given
to the constructor, after the new state is in place.

All Dr.Jit variables are opaque and the tables live in memory of their own
(`mi_amr.device.structs.owned`), so no change recompiles a kernel or
records a frozen function again.
"""

from __future__ import annotations

import weakref
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..device.structs import jit_struct, owned
from ..params import ParameterError
from .device import DeviceTransferFunction
from .function import TransferFunction, range_majorants_host

#: The scene parameters a classification exposes.
PARAMETERS = ("density_scale", "tf_rgba", "tf_domain")


@jit_struct(scale="Float", tf_rgba="Float", tf_domain="Float", device=DeviceTransferFunction)
class Classification:
    """TF and density scale of one medium (see the module docstring).

    Dr.Jit state: ``scale`` (density scale), ``tf_rgba`` (the table, N x 4
    row major) and ``tf_domain`` ([lo, hi]) as traversed scene parameters,
    and ``device``, the tables the kernels read.
    """

    def __init__(self, tf: TransferFunction, density_scale: float,
                 on_change: Callable[["Classification"], None] | None = None):
        self.on_change = on_change
        self.tf = _check_tf(tf)
        self.density_scale = check_density_scale(density_scale)
        self.scale = mi.Float(self.density_scale)
        self.tf_rgba = owned(mi.Float, self.tf.rgba)
        self.tf_domain = mi.Float(self.tf.domain)
        self.device = DeviceTransferFunction(self.tf)
        dr.make_opaque(self.scale, self.tf_rgba, self.tf_domain)

    # ---- The one update path --------------------------------------------------
    def set(self, tf: TransferFunction | None = None, density_scale: float | None = None):
        """Use a new TF and/or density scale (None keeps the current one):
        validated first (a bad value raises and changes nothing), then
        uploaded, then the listener is told."""
        tf = self.tf if tf is None else _check_tf(tf)
        scale = self.density_scale if density_scale is None else check_density_scale(density_scale)
        self.tf, self.density_scale = tf, scale
        self.device.set(tf)
        # the traversed variables are updated in place (SceneParameters hold them)
        mi.set_property(self.tf_rgba, owned(mi.Float, tf.rgba))
        mi.set_property(self.tf_domain, mi.Float(tf.domain))
        mi.set_property(self.scale, mi.Float(scale))
        dr.make_opaque(self.scale, self.tf_rgba, self.tf_domain)
        listener = self._listener() if self._listener is not None else None
        if listener is not None:
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
        keys = set(PARAMETERS if keys is None else keys) & set(PARAMETERS)
        if not keys:
            return
        try:
            tf = self._tf_from_parameters() if keys & {"tf_rgba", "tf_domain"} else None
            scale = float(self.scale.numpy()[0]) if "density_scale" in keys else None
            if scale is not None:
                check_density_scale(scale)
        except ValueError:
            self.set()                      # the last valid state, back into the variables
            raise
        self.set(tf, scale)

    def _tf_from_parameters(self) -> TransferFunction:
        rgba = np.asarray(self.tf_rgba.numpy(), dtype=np.float64)
        dom = self.tf_domain.numpy()
        if rgba.size % 4 or dom.size != 2:
            raise ParameterError(f"amr: tf_rgba must hold N x 4 values and tf_domain 2, "
                                 f"got {rgba.size} and {dom.size}")
        return TransferFunction(rgba.reshape(-1, 4), (float(dom[0]), float(dom[1])))

    # ---- Views ----------------------------------------------------------------
    def traverse(self, callback):
        """Expose ``density_scale``, ``tf_rgba`` and ``tf_domain`` (not
        differentiable) to ``mi.traverse``."""
        callback.put("density_scale", self.scale, mi.ParamFlags.NonDifferentiable)
        callback.put("tf_rgba", self.tf_rgba, mi.ParamFlags.NonDifferentiable)
        callback.put("tf_domain", self.tf_domain, mi.ParamFlags.NonDifferentiable)

    def host_majorants(self, vmin, vmax) -> np.ndarray:
        """``density_scale * max alpha`` over each value range (numpy, inverse
        world units; 0 for empty ranges), as the device update computes it."""
        return range_majorants_host(self.tf, vmin, vmax, self.density_scale)

    def sigma_t(self, value, found):
        """Extinction at reconstructed values (inverse world units; 0 where
        no value was found)."""
        return dr.select(found, self.scale * self.device.eval_alpha(value, found), 0.0)

    def albedo_and_sigma_t(self, value, found):
        """``(albedo, sigma_t)`` at reconstructed values."""
        rgb, alpha = self.device.eval(value, found)
        return rgb, dr.select(found, self.scale * alpha, 0.0)


def _check_tf(tf) -> TransferFunction:
    if not isinstance(tf, TransferFunction):
        raise ParameterError(f"amr: expected a TransferFunction, got {type(tf).__name__}")
    return tf


def check_density_scale(v) -> float:
    """``v`` as a valid density scale, or a `ParameterError` (the bound is
    `mi_amr.plugins.options.MAX_DENSITY_SCALE`)."""
    from ..plugins.options import check_density_scale as check
    return check(v)
