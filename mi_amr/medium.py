"""The ``amr`` medium: cell-centric AMR data as a Mitsuba participating medium."""

from __future__ import annotations

import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .cells import AMRCells
from .io import load_cells
from .majorant_grid import MacrocellGrid
from .reconstruct import DeviceReconstruction, check_method
from .tracking import DeviceMacrocellGrid, intersect_unit_cube, safe_rcp
from .transfer import TransferFunction
from .transfer_jit import DeviceTransferFunction

MAJORANTS = ("ray", "global")
OVERLAPS = ("error", "finest")
_KNOWN = {"filename", "scalars", "data", "transfer_function", "tf_min", "tf_max",
          "density_scale", "reconstruction", "majorant", "grid_resolution",
          "overlap", "to_world", "sample_emitters"}


def as_transform4f(t) -> "mi.ScalarTransform4f":
    """Any Mitsuba scalar transform (float or double) as ScalarTransform4f."""
    if t is None:
        return mi.ScalarTransform4f()
    if isinstance(t, mi.ScalarTransform4f):
        return t
    m = getattr(t, "matrix", t)
    return mi.ScalarTransform4f(np.ascontiguousarray(np.array(m, dtype=np.float32)))


def require_jit_rgb_variant(what: str = "mi_amr"):
    """Raise a clear error unless the active Mitsuba variant is a JIT rgb one."""
    v = mi.variant()
    if v is None or not (v.startswith("llvm_") or v.startswith("cuda_")) or not v.endswith("_rgb"):
        raise RuntimeError(
            f"{what} needs a JIT rgb Mitsuba variant such as 'llvm_ad_rgb' or "
            f"'cuda_ad_rgb'; the active variant is {v!r}. Call "
            "mi.set_variant('llvm_ad_rgb') before loading the scene.")


class AMRMedium(mi.Medium):
    r"""
    AMR medium (:monosp:`amr`)
    --------------------------

    Cell-centric adaptive-mesh-refinement data, coloured by an RGBA transfer
    function: ``sigma_t(x) = density_scale * alpha(f(x))`` (inverse world
    units) and albedo ``rgb(f(x))``. The AMR bounding box fills the unit cube
    and ``to_world`` places it, as with ``gridvolume``. Enclose it in a shape
    (usually a ``cube`` with the same ``to_world``) whose ``interior`` is this
    medium.

    .. pluginparameters::

     * - filename
       - |string|
       - ExaBricks ``.cells`` file (or ``.npz``); the scalars are the
         sibling ``.scalars`` file unless ``scalars`` names another.
     * - scalars
       - |string|
       - Scalars file for ``filename`` (optional).
     * - data
       - ``AMRCells``
       - The cells themselves (Python scene dictionaries only).
     * - transfer_function
       - |string| or ``TransferFunction``
       - Preset name (``spiky``, ``foggy``, ``ramp``, ``constant``) or a
         ``.json`` file. Default: ``foggy``.
     * - tf_min, tf_max
       - |float|
       - Value domain of a preset TF. Default: the data's value range.
     * - density_scale
       - |float|
       - Extinction of opacity 1, in inverse world units. Default: 1.
     * - reconstruction
       - |string|
       - ``tent`` (default; continuous) or ``nearest`` (finest cell).
     * - majorant
       - |string|
       - ``ray`` (default): walk the macrocell grid along each ray, trim empty
         space at both ends, use the maximum over the rest; ``global``: one
         maximum for the whole volume.
     * - grid_resolution
       - |int|
       - Macrocells along the longest axis. Default: chosen from the data.
     * - overlap
       - |string|
       - ``error`` (default) rejects overlapping cells; ``finest`` keeps the
         finer ones.
     * - to_world
       - |transform|
       - Placement of the unit cube in the scene.
     * - (nested phase function)
       - |phase|
       - Default: isotropic.
     * - sample_emitters
       - |bool|
       - Next-event estimation in the medium. Default: true.
    """

    def __init__(self, props: mi.Properties):
        require_jit_rgb_variant("the 'amr' medium")
        mi.Medium.__init__(self, props)
        self.m_is_homogeneous = False
        self.m_has_spectral_extinction = False
        self._check_unknown(props)

        # ---- Data ----
        self.cells = self._load_data(props)
        self.reconstruction = check_method(str(props.get("reconstruction", "tent")))
        self.majorant_mode = str(props.get("majorant", "ray"))
        if self.majorant_mode not in MAJORANTS:
            raise ValueError(f"amr: unknown majorant {self.majorant_mode!r} "
                             f"(choose from {', '.join(MAJORANTS)})")
        self.density_scale = _positive_float(props, "density_scale", 1.0)

        tf = props.get("transfer_function", "foggy")
        vlo, vhi = self.cells.value_range
        if vhi <= vlo:
            vhi = vlo + 1.0
        domain = (float(props.get("tf_min", vlo)), float(props.get("tf_max", vhi)))
        if isinstance(tf, TransferFunction):
            self.tf = tf
        elif isinstance(tf, str):
            tf_path = tf
            if tf.endswith(".json"):
                tf_path = str(mi.file_resolver().resolve(tf))
            self.tf = TransferFunction.load(tf_path, domain)
        else:
            raise ValueError(f"amr: transfer_function must be a preset name, a .json path "
                             f"or a TransferFunction, got {type(tf).__name__}")

        grid_res = props.get("grid_resolution", None)
        if grid_res is not None and int(grid_res) < 1:
            raise ValueError(f"amr: grid_resolution must be >= 1, got {grid_res}")

        self.to_world_scalar = as_transform4f(props.get("to_world", None))

        # ---- Structures (host build, then upload) ----
        t0 = time.perf_counter()
        self._sampler = DeviceReconstruction(self.cells, self.reconstruction)
        self.grid = MacrocellGrid(self.cells, grid_res, support=self.reconstruction)
        self.build_seconds = time.perf_counter() - t0
        self._grid = DeviceMacrocellGrid(self.grid)
        self._tf = DeviceTransferFunction(self.tf)

        lo, hi = self.cells.bounds
        self._offset = mi.Vector3f(*[float(c) for c in lo - self._sampler.origin])
        self._extent = mi.Vector3f(*[float(c) for c in hi - lo])
        self._to_local = mi.Transform4f(self.to_world_scalar.inverse())
        self._scale = mi.Float(self.density_scale)
        dr.make_opaque(self._offset, self._extent, self._to_local, self._scale)
        self._ray_mu = None
        self.update_majorants()

    # ---- Construction helpers ---------------------------------------------
    @staticmethod
    def _check_unknown(props):
        for k in props.keys():
            if k in _KNOWN:
                continue
            if props.type(k) == mi.Properties.Type.Object and isinstance(props[k], mi.PhaseFunction):
                continue
            raise ValueError(f"amr: unknown parameter {k!r} (known: {', '.join(sorted(_KNOWN))}, "
                             "and a nested phase function)")

    @staticmethod
    def _load_data(props) -> AMRCells:
        overlap = str(props.get("overlap", "error"))
        if overlap not in OVERLAPS:
            raise ValueError(f"amr: overlap must be one of {OVERLAPS}, got {overlap!r}")
        has_file, has_data = "filename" in props.keys(), "data" in props.keys()
        if has_file == has_data:
            raise ValueError("amr: give exactly one of 'filename' (a .cells or .npz file) "
                             "or 'data' (an AMRCells object)")
        if has_data:
            data = props["data"]
            if not isinstance(data, AMRCells):
                raise ValueError(f"amr: 'data' must be an mi_amr.AMRCells, got {type(data).__name__}")
            return data
        resolver = mi.file_resolver()
        path = Path(str(resolver.resolve(str(props["filename"]))))
        scalars = props.get("scalars", None)
        if scalars is not None:
            scalars = str(resolver.resolve(str(scalars)))
        return load_cells(path, scalars, overlap=overlap)

    # ---- Transfer function / majorants ---------------------------------------
    def update_majorants(self):
        """Recompute every macrocell majorant from the value ranges, the TF
        and the density scale (one Dr.Jit kernel), and the global maximum."""
        self._grid.update_majorants(self._tf, self._scale)
        self._global_mu = dr.max(self._grid.majorant)
        dr.make_opaque(self._global_mu)

    @property
    def global_majorant(self) -> float:
        return float(self._global_mu[0])

    @property
    def majorant_grid(self) -> np.ndarray:
        """Macrocell majorants as a numpy array indexed ``[z, y, x]``."""
        r = self.grid.res
        return self._grid.majorant.numpy().reshape(r[2], r[1], r[0])

    # ---- Mitsuba medium interface -------------------------------------------
    def intersect_aabb(self, ray: mi.Ray3f):
        o = self._to_local @ ray.o
        d = self._to_local @ ray.d
        hit, t0, t1 = intersect_unit_cube(o, safe_rcp(d))
        if self.majorant_mode == "global":
            self._ray_mu = None
            return hit & (self._global_mu > 0.0), t0, t1
        t_start = dr.maximum(t0, 0.0)
        t_end = dr.minimum(t1, ray.maxt)
        found, t_first, t_last, mu = self._grid.ray_majorant(o, d, t_start, t_end, hit)
        self._ray_mu = mu
        return found, t_first, t_last

    def get_majorant(self, mei: mi.MediumInteraction3f, active=True):
        mu = self._current_majorant()
        return mi.Color3f(dr.select(mu > 0.0, mu, 1.0))

    def get_scattering_coefficients(self, mei: mi.MediumInteraction3f, active=True):
        mu = self._current_majorant()
        self._ray_mu = None          # consumed: sample_interaction calls this last
        u = self._to_local @ mei.p
        inside = mi.Bool(active) & dr.all((u >= 0.0) & (u <= 1.0))
        level_bits = dr.gather(mi.UInt32, self._grid.level_bits,
                               self._grid.flat(self._grid.cell_of(u)), inside)
        x = self._offset + u * self._extent
        value, found = self._sampler.eval(x, level_bits, inside)
        rgb, alpha = self._tf.eval(value, found)
        sigma_t = dr.select(found, self._scale * alpha, 0.0)
        sigma_s = rgb * sigma_t
        sigma_n = dr.maximum(mu - sigma_t, 0.0)
        return mi.Color3f(sigma_s), mi.Color3f(sigma_n), mi.Color3f(sigma_t)

    def _current_majorant(self):
        return self._ray_mu if self._ray_mu is not None else self._global_mu

    def to_string(self):
        return (f"AMRMedium[\n  cells = {len(self.cells)},\n  levels = "
                f"{self.cells.levels.tolist()},\n  reconstruction = {self.reconstruction},\n"
                f"  majorant = {self.majorant_mode},\n  grid_resolution = {self.grid.res.tolist()},\n"
                f"  density_scale = {self.density_scale},\n  transfer_function = {self.tf}\n]")


def _positive_float(props, name, default):
    v = float(props.get(name, default))
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"amr: {name} must be a finite non-negative number, got {v}")
    return v
