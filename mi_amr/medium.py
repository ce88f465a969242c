"""The ``amr`` medium: cell-centric AMR data as a Mitsuba participating medium."""

from __future__ import annotations

import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .cells import AMRCells
from .io import load_cells
from .brick_sampling import BrickListGrid, BrickSampler, DeviceBricks
from .bricks import Bricks
from .cell_hash import key_origin
from .kdtree_sah import build_sah_kdtree
from .local_tracking import span_majorant, track_segments
from .majorant_grid import MacrocellGrid, auto_resolution, axis_resolution, range_majorants_host
from .memory import default_memory_limit, require, structure_bytes
from .params import ParameterError, check_known, get_float, get_int, get_string
from .reconstruct import METHODS, DeviceReconstruction
from .region_tree import build_region_tree, exact_value_ranges
from .tracking import DeviceMacrocellGrid, flush_tiny, intersect_unit_cube, safe_rcp
from .traversal import DeviceTree, GridSegments, TreeSegments
from .transfer import TransferFunction
from .transfer_jit import DeviceTransferFunction

MAJORANTS = ("ray", "global")
TRAVERSALS = ("grid", "abr", "brick", "kdtree")
SAMPLINGS = ("hash", "abr", "brick")
#: Bound on the iterations of one tracking loop (reported by the counters).
MAX_TRACKING_ITERATIONS = 1 << 20
OVERLAPS = ("error", "finest")
#: Largest density_scale: majorants and their reciprocals stay normal float32
#: numbers (at 1e38 the reciprocal flushes to 0 and a medium turns clear).
MAX_DENSITY_SCALE = 1e30
#: Largest condition number of to_world's linear part (float32 precision).
MAX_CONDITION = 1e7
_KNOWN = {"filename", "scalars", "data", "transfer_function", "tf_min", "tf_max",
          "density_scale", "reconstruction", "majorant", "grid_resolution",
          "overlap", "to_world", "sample_emitters", "traversal", "sampling", "brick_size",
          "kdtree_leaves", "max_iterations", "memory_limit"}


def as_transform4f(t) -> "mi.ScalarTransform4f":
    """Any Mitsuba scalar transform (float or double) as ScalarTransform4f."""
    if t is None:
        return mi.ScalarTransform4f()
    if isinstance(t, mi.ScalarTransform4f):
        return t
    m = np.array(getattr(t, "matrix", t), dtype=np.float64)
    # the inverse in float64: a float32 inversion under- or overflows for
    # scales far from 1 (1e-20: the determinant is 1e-60)
    inv_t = np.linalg.inv(m).T
    return mi.ScalarTransform4f(mi.ScalarMatrix4f(m.astype(np.float32)), mi.ScalarMatrix4f(inv_t.astype(np.float32)))


def scene_media(scene) -> list:
    """Every medium of a scene (shape interiors and exteriors, sensors), each
    once as far as object identity tells."""
    found = []
    candidates = [m for shape in scene.shapes() for m in (shape.interior_medium(), shape.exterior_medium())]
    candidates += [s.medium() for s in scene.sensors() if hasattr(s, "medium")]
    for m in candidates:
        if m is not None and all(m is not f for f in found):
            found.append(m)
    return found


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
       - Macrocells along the longest axis. Default: chosen by a cost model
         of the data and the TF (`mi_amr.majorant_grid.auto_resolution`).
     * - traversal
       - |string|
       - Segments and majorants for ``amrvolpath`` (and the ray-wise
         majorant in ``volpath``): ``grid`` (default), ``abr``, ``brick``,
         ``kdtree`` (pre-classified SAH kd-tree, rebuilt on a TF change).
     * - sampling
       - |string|
       - Point location of density look-ups: ``hash`` (default), ``abr``
         (the ABR's brick list), ``brick`` (bricks whose extended domain
         contains the point).
     * - brick_size, kdtree_leaves
       - |int|
       - Largest brick side in cells (8); leaf budget of the kd-tree (4096).
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
     * - max_iterations
       - |int|
       - Bound on the iterations of one tracking loop (2^20); a ray that
         reaches it stops and is counted as ``capped``.
     * - memory_limit
       - |float|
       - Bytes a structure may need (``MI_AMR_MEMORY_LIMIT`` or half the
         physical memory); larger ones are refused before they are built.
    """

    def __init__(self, props: mi.Properties):
        require_jit_rgb_variant("the 'amr' medium")
        mi.Medium.__init__(self, props)
        self.m_is_homogeneous = False
        self.m_has_spectral_extinction = False
        check_known(props, "amr", _KNOWN, allow=lambda k, v: isinstance(v, mi.PhaseFunction))

        # ---- Data ----
        self.cells = self._load_data(props)
        self.reconstruction = get_string(props, "amr", "reconstruction", "tent", METHODS)
        self.majorant_mode = get_string(props, "amr", "majorant", "ray", MAJORANTS)
        self.density_scale = get_float(props, "amr", "density_scale", 1.0, minimum=0.0,
                                       maximum=MAX_DENSITY_SCALE)

        tf = props.get("transfer_function", "foggy")
        vlo, vhi = self.cells.value_range
        if vhi <= vlo:                 # constant data: centre the value in the TF domain
            pad = max(0.5, 1e-3 * abs(vlo))
            vlo, vhi = vlo - pad, vhi + pad
        domain = (get_float(props, "amr", "tf_min", vlo), get_float(props, "amr", "tf_max", vhi))
        if domain[1] <= domain[0]:
            raise ParameterError(f"amr: tf_min must be below tf_max, got {domain[0]} and {domain[1]}")
        if isinstance(tf, TransferFunction):
            self.tf = tf
        elif isinstance(tf, str):
            tf_path = tf
            if tf.endswith(".json"):
                tf_path = str(mi.file_resolver().resolve(tf))
            self.tf = TransferFunction.load(tf_path, domain)
        else:
            raise ParameterError(f"amr: transfer_function must be a preset name, a .json path "
                                 f"or a TransferFunction, got {type(tf).__name__}")

        self.grid_resolution = get_int(props, "amr", "grid_resolution", None, minimum=1)
        self.traversal = get_string(props, "amr", "traversal", "grid", TRAVERSALS)
        self.sampling = get_string(props, "amr", "sampling", "hash", SAMPLINGS)
        self.brick_size = get_int(props, "amr", "brick_size", 8, minimum=1, maximum=1024)
        self.kdtree_leaves = get_int(props, "amr", "kdtree_leaves", 4096, minimum=1)
        self.max_iterations = get_int(props, "amr", "max_iterations", MAX_TRACKING_ITERATIONS,
                                      minimum=1, maximum=2**31)
        self.memory_limit = get_float(props, "amr", "memory_limit", default_memory_limit(), positive=True)
        self.to_world_scalar = _to_world(props)

        # ---- Common device data ----
        lo, hi = self.cells.bounds
        self.origin = key_origin(self.cells)
        self._offset = mi.Vector3f(*[float(c) for c in lo - self.origin])
        self._extent = mi.Vector3f(*[float(c) for c in hi - lo])
        self._to_local = mi.Transform4f(self.to_world_scalar.inverse())
        self._scale = mi.Float(self.density_scale)
        self._max_iterations = mi.UInt32(self.max_iterations)
        dr.make_opaque(self._offset, self._extent, self._to_local, self._scale, self._max_iterations)
        self._tf = DeviceTransferFunction(self.tf)
        self._tf_rgba = mi.Float(self.tf.rgba.ravel())
        self._tf_domain = mi.Float(self.tf.domain)
        dr.make_opaque(self._tf_rgba, self._tf_domain)
        self._ray_mu = None
        self._structures = {}
        self.build_seconds = {}

        # ---- Structures the chosen traversal and sampling use ----
        self._segments()
        self._point_sampler()
        self.update_majorants()

    # ---- Construction helpers ---------------------------------------------
    @staticmethod
    def _load_data(props) -> AMRCells:
        overlap = get_string(props, "amr", "overlap", "error", OVERLAPS)
        has_file, has_data = "filename" in props.keys(), "data" in props.keys()
        if has_file == has_data:
            raise ValueError("amr: give exactly one of 'filename' (a .cells or .npz file) "
                             "or 'data' (an AMRCells object)")
        if has_data:
            data = props["data"]
            if not isinstance(data, AMRCells):
                raise ParameterError(f"amr: 'data' must be an mi_amr.AMRCells, got {type(data).__name__}")
            return data
        resolver = mi.file_resolver()
        path = Path(str(resolver.resolve(get_string(props, "amr", "filename", None))))
        scalars = get_string(props, "amr", "scalars", None)
        if scalars is not None:
            scalars = str(resolver.resolve(scalars))
        return load_cells(path, scalars, overlap=overlap)

    # ---- Structures (built on first use) ------------------------------------
    def _build(self, name, make, need: float = 0.0):
        """Build structure ``name`` once; ``need``: its estimated peak bytes,
        checked against ``memory_limit`` first."""
        if name not in self._structures:
            if dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(f"amr: structure '{name}' must be built before rendering")
            require(need, f"amr: the {name} structure of {self.cells.source} ({len(self.cells)} cells)",
                    self.memory_limit, "use fewer cells or raise the limit")
            t0 = time.perf_counter()
            self._structures[name] = make()
            self.build_seconds[name] = time.perf_counter() - t0
            if getattr(self, "_majorants_ready", False):
                self.update_majorants()
        return self._structures[name]

    @property
    def grid(self) -> MacrocellGrid:
        return self._grid.host

    @property
    def _grid(self) -> DeviceMacrocellGrid:
        def make():
            res = self.grid_resolution
            if res is None:                 # cost model of the data and the TF
                res, _ = auto_resolution(self.cells, self.tf, self.density_scale,
                                         self.world_scale, self.reconstruction)
            return DeviceMacrocellGrid(MacrocellGrid(self.cells, res, support=self.reconstruction,
                                                     memory_limit=self.memory_limit))
        return self._build("grid", make)

    @property
    def world_scale(self) -> float:
        """Geometric mean scale of ``to_world`` (local unit length in world units)."""
        m = np.array(self.to_world_scalar.matrix, dtype=np.float64)[:3, :3]
        return float(np.cbrt(abs(np.linalg.det(m)))) or 1.0

    def _host_cached(self, key, make):
        """Host structures depend only on the cells and build options: cache
        them on the AMRCells object so that media sharing data (a re-loaded
        scene, a benchmark) build them once."""
        cache = self.cells.__dict__.setdefault("_mi_amr_cache", {})
        if key not in cache:
            cache[key] = make()
        return cache[key]

    @property
    def bricks(self) -> Bricks:
        return self._build("bricks", lambda: self._host_cached(
            ("bricks", self.brick_size), lambda: Bricks(self.cells, self.brick_size)),
            need=structure_bytes("bricks", len(self.cells)))

    def _brick_tree(self, kind: str) -> DeviceTree:
        """kd-tree over brick domains (``abr``) or brick bounds (``brick``)."""
        def make_host():
            b = self.bricks
            lo, hi = self.cells.bounds
            if kind == "abr":
                blo, bhi = b.domains()
            else:
                blo, bhi = b.lo.astype(np.float64), b.hi.astype(np.float64)
            tree = build_region_tree(np.round(2 * blo).astype(np.int64), np.round(2 * bhi).astype(np.int64),
                                     2 * lo, 2 * hi)
            vmin, vmax = exact_value_ranges(tree.leaf_lo / 2, tree.leaf_hi / 2, b, self.reconstruction)
            return tree, vmin, vmax

        def make():
            lo, hi = self.cells.bounds
            tree, vmin, vmax = self._host_cached((f"{kind}_tree", self.brick_size, self.reconstruction),
                                                 make_host)
            return DeviceTree(tree, 2 * lo, 0.5 / (hi - lo), vmin, vmax)
        return self._build(f"{kind}_tree", make)

    def _kdtree(self) -> DeviceTree:
        """SAH kd-tree built for the current TF over a macrocell grid four
        times finer than the default one (at most 128 per axis)."""
        def make():
            from .majorant_grid import default_resolution
            res = int(min(128, 4 * default_resolution(self.cells).max()))
            g = self._host_cached(("kd_grid", res, self.reconstruction),
                                  lambda: MacrocellGrid(self.cells, res, support=self.reconstruction,
                                                        memory_limit=self.memory_limit))
            r = g.res
            shape = (r[2], r[1], r[0])
            maj = self._tf_host_majorants(g.vmin, g.vmax).reshape(shape).transpose(2, 1, 0)
            vmin = g.vmin.reshape(shape).transpose(2, 1, 0)
            vmax = g.vmax.reshape(shape).transpose(2, 1, 0)
            tree, lmin, lmax = build_sah_kdtree(maj, vmin, vmax, self.kdtree_leaves)
            return DeviceTree(tree, np.zeros(3), 1.0 / r, lmin, lmax)
        return self._build("kdtree", make)

    def _tf_host_majorants(self, vmin, vmax):
        """Host majorants in inverse local units, for the SAH build."""
        return range_majorants_host(self.tf, vmin, vmax, self.density_scale) * self.world_scale

    def _segments(self):
        """The segment iterator of the chosen traversal."""
        if self.traversal == "grid":
            return GridSegments(self._grid)
        if self.traversal == "kdtree":
            return TreeSegments(self._kdtree())
        return TreeSegments(self._brick_tree(self.traversal))

    def _point_sampler(self):
        if self.sampling == "hash":
            self._grid                      # its level masks limit the levels visited
            return self._build("hash", lambda: DeviceReconstruction(self.cells, self.reconstruction),
                               need=structure_bytes(f"hash_{self.reconstruction}", len(self.cells)))
        dev_bricks = self._build("device_bricks", lambda: DeviceBricks(self.bricks, self.origin))
        if self.sampling == "abr":
            return BrickSampler(dev_bricks, self.reconstruction, "abr", abr_tree=self._brick_tree("abr"))
        lo, hi = self.cells.bounds
        res = _list_grid_resolution(self.cells)
        lists = self._build("brick_lists", lambda: BrickListGrid(self.bricks, lo, hi - lo, res,
                                                                 memory_limit=self.memory_limit))
        return BrickSampler(dev_bricks, self.reconstruction, "brick", list_grid=lists)

    @property
    def structure_bytes(self) -> int:
        """Memory of every structure built so far (host arrays uploaded)."""
        total = 0
        for name, obj in self._structures.items():
            if name == "device_bricks":          # the same arrays as "bricks"
                continue
            host = getattr(obj, "host", obj)
            total += int(getattr(host, "nbytes", 0) or getattr(obj, "nbytes", 0))
        return total

    # ---- Transfer function / majorants ---------------------------------------
    def update_majorants(self):
        """Recompute the majorants of every built structure from its value
        ranges, the TF and the density scale (one Dr.Jit kernel each), and
        the global maximum."""
        self._majorants_ready = True
        dr.eval()        # pending work of others stays out of the majorant kernels,
        mus = []         # so that they are the same code at load time and after

        for name in ("grid", "abr_tree", "brick_tree", "kdtree"):
            if name in self._structures:
                self._structures[name].update_majorants(self._tf, self._scale)
                mus.append(dr.max(self._structures[name].majorant))
        self._global_mu = mus[0] if mus else mi.Float(0.0)
        for m in mus[1:]:
            self._global_mu = dr.maximum(self._global_mu, m)
        self._global_mu = mi.Float(dr.ravel(self._global_mu))
        dr.make_opaque(self._global_mu)

    @property
    def global_majorant(self) -> float:
        return float(self._global_mu[0])

    @property
    def majorant_grid(self) -> np.ndarray:
        """Macrocell majorants as a numpy array indexed ``[z, y, x]``."""
        r = self.grid.res
        return self._grid.majorant.numpy().reshape(r[2], r[1], r[0])

    # ---- Density ----------------------------------------------------------------
    def eval_local(self, u: mi.Vector3f, active=True):
        """``(albedo, sigma_t)`` at local point ``u`` (unit cube); sigma_t in
        inverse world units, 0 outside the data or where no value exists."""
        inside = mi.Bool(active) & dr.all((u >= 0.0) & (u <= 1.0))
        x = self._offset + u * self._extent
        sampler = self._point_sampler()
        if self.sampling == "hash":
            g = self._grid
            level_bits = dr.gather(mi.UInt32, g.level_bits, g.flat(g.cell_of(u)), inside)
            value, found = sampler.eval(x, level_bits, inside)
        else:
            value, found = sampler.eval(x, u, inside)
        rgb, alpha = self._tf.eval(value, found)
        sigma_t = dr.select(found, self._scale * alpha, 0.0)
        return rgb, sigma_t

    # ---- Local-majorant tracking (used by the amrvolpath integrator) ---------
    def local_ray(self, ray: mi.Ray3f):
        """``(o, d, s)``: the ray in the unit cube with a unit direction ``d``
        (negligible components flushed to 0, `flush_tiny`) and ``s``, local
        length per world ``t``: the point at world ``t`` is ``o + (s t) d``.
        Unit directions keep the traversal's float maths in range for any
        ``to_world`` scale (1e-20 to 1e20)."""
        o = self._to_local @ ray.o
        d = self._to_local @ ray.d
        m = dr.max(dr.abs(d))
        m = dr.select(m > 0.0, m, 1.0)
        s = m * dr.norm(d * dr.rcp(m))
        return o, flush_tiny(d * dr.rcp(s)), s

    def free_flight(self, ray: mi.Ray3f, t_max, sampler: mi.Sampler, active):
        """Delta tracking through local-majorant segments along ``ray`` up to
        ``t_max``. Returns ``(collided, t, albedo, sigma_t, counts)``."""
        return self._track(ray, t_max, sampler, active, ratio=False)

    def transmittance(self, ray: mi.Ray3f, t_max, sampler: mi.Sampler, active):
        """Ratio-tracking estimate of transmittance along ``ray`` over
        ``[0, t_max]``. Returns ``(T, counts)``."""
        _, _, _, T, counts = self._track(ray, t_max, sampler, active, ratio=True)
        return T, counts

    def _track(self, ray, t_max, sampler, active, ratio):
        o, d, s = self.local_ray(ray)
        hit, t0, t1 = intersect_unit_cube(o, safe_rcp(d))
        t_lo = dr.maximum(t0, 0.0)
        t_hi = dr.minimum(t1, t_max * s)
        active = mi.Bool(active) & hit & (s > 0.0) & (t_lo < t_hi) & (self._global_mu > 0.0)
        collided, t, albedo, result, counts = track_segments(
            self._segments(), self.eval_local, o, d, t_lo, t_hi, sampler, active, ratio,
            self._max_iterations, s)
        return collided, t * dr.rcp(dr.select(s > 0.0, s, 1.0)), albedo, result, counts

    # ---- Mitsuba medium interface -------------------------------------------
    def intersect_aabb(self, ray: mi.Ray3f):
        o, d, s = self.local_ray(ray)
        inv_s = dr.rcp(dr.select(s > 0.0, s, 1.0))
        hit, t0, t1 = intersect_unit_cube(o, safe_rcp(d))
        hit &= s > 0.0
        if self.majorant_mode == "global":
            self._ray_mu = None
            return hit & (self._global_mu > 0.0), t0 * inv_s, t1 * inv_s
        t_start = dr.maximum(t0, 0.0)
        t_end = dr.minimum(t1, ray.maxt * s)
        segments = self._segments()
        found, t_first, t_last, mu, _ = span_majorant(segments, o, d, t_start, t_end, hit,
                                                      segments.max_steps(), self._global_mu)
        self._ray_mu = mu
        return found, t_first * inv_s, t_last * inv_s

    def get_majorant(self, mei: mi.MediumInteraction3f, active=True):
        mu = self._current_majorant()
        return mi.Color3f(dr.select(mu > 0.0, mu, 1.0))

    def get_scattering_coefficients(self, mei: mi.MediumInteraction3f, active=True):
        mu = self._current_majorant()
        self._ray_mu = None          # consumed: sample_interaction calls this last
        rgb, sigma_t = self.eval_local(self._to_local @ mei.p, active)
        sigma_s = rgb * sigma_t
        sigma_n = dr.maximum(mu - sigma_t, 0.0)
        return mi.Color3f(sigma_s), mi.Color3f(sigma_n), mi.Color3f(sigma_t)

    # ---- Scene parameters (mi.traverse) ------------------------------------------
    def traverse(self, callback):
        """Expose ``density_scale``, the TF table ``tf_rgba``
        (flat float array, N x 4, row major) and ``tf_domain``
        ([lo, hi]); ``params.update()`` then recomputes the majorants."""
        callback.put("density_scale", self._scale, mi.ParamFlags.NonDifferentiable)
        callback.put("tf_rgba", self._tf_rgba, mi.ParamFlags.NonDifferentiable)
        callback.put("tf_domain", self._tf_domain, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys=None):
        """Validate the updated parameters (a bad value raises and the last
        valid ones are put back), then use them."""
        keys = set(keys or [])
        tf, scale = None, None
        try:
            if keys & {"tf_rgba", "tf_domain"}:
                rgba = np.asarray(self._tf_rgba.numpy(), dtype=np.float64)
                dom = self._tf_domain.numpy()
                if rgba.size % 4 or dom.size != 2:
                    raise ParameterError(f"amr: tf_rgba must hold N x 4 values and tf_domain 2, "
                                         f"got {rgba.size} and {dom.size}")
                tf = TransferFunction(rgba.reshape(-1, 4), (float(dom[0]), float(dom[1])))
            if "density_scale" in keys:
                scale = _check_density_scale(float(self._scale.numpy()[0]))
        except ValueError:
            self.set_transfer_function(self.tf, self.density_scale, update=False)
            raise
        if tf is not None:
            self.set_transfer_function(tf, update=False)
        if scale is not None:
            self.density_scale = scale
        self.update_majorants()

    def set_transfer_function(self, tf: TransferFunction, density_scale=None, update: bool = True):
        """Use a new TF (new table, domain or size) and/or density scale:
        uploads the small table and recomputes every majorant; the kernels are
        not recompiled (all TF data are opaque). The pre-classified kd-tree is
        rebuilt, since its topology was chosen for the old TF."""
        if not isinstance(tf, TransferFunction):
            raise ValueError(f"amr: expected a TransferFunction, got {type(tf).__name__}")
        self.tf = tf
        self._tf.set(tf)
        # the traversed parameters are updated in place (SceneParameters hold them)
        mi.set_property(self._tf_rgba, mi.Float(tf.rgba.ravel()))
        mi.set_property(self._tf_domain, mi.Float(tf.domain))
        if density_scale is not None:
            self.density_scale = _check_density_scale(density_scale)
            mi.set_property(self._scale, mi.Float(self.density_scale))
        dr.make_opaque(self._tf_rgba, self._tf_domain, self._scale)
        if "kdtree" in self._structures:
            t0 = time.perf_counter()
            del self._structures["kdtree"]
            self._kdtree()
            self.build_seconds["kdtree_rebuild"] = time.perf_counter() - t0
        if update:
            self.update_majorants()

    def _current_majorant(self):
        return self._ray_mu if self._ray_mu is not None else self._global_mu

    def to_string(self):
        return (f"AMRMedium[\n  cells = {len(self.cells)},\n  levels = "
                f"{self.cells.levels.tolist()},\n  reconstruction = {self.reconstruction},\n"
                f"  majorant = {self.majorant_mode},\n  traversal = {self.traversal},\n  sampling = {self.sampling},\n"
                f"  structures = {sorted(self._structures)},\n"
                f"  density_scale = {self.density_scale},\n  transfer_function = {self.tf}\n]")


def _list_grid_resolution(cells):
    """Brick-list grid: about two finest cells per list cell (short lists),
    at most 128 along the longest axis."""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    return axis_resolution(int(np.clip(ext.max() / 2, 1, 128)), ext)


def _check_density_scale(v) -> float:
    v = float(v)
    if not (np.isfinite(v) and 0 <= v <= MAX_DENSITY_SCALE):
        raise ParameterError(f"amr: density_scale must be a finite number in [0, {MAX_DENSITY_SCALE:g}], got {v:g}")
    return v


def _to_world(props) -> "mi.ScalarTransform4f":
    """``to_world`` as a finite, invertible ScalarTransform4f."""
    if "to_world" not in props.keys():
        return mi.ScalarTransform4f()
    t = props["to_world"]
    if not hasattr(t, "matrix"):
        raise ParameterError(f"amr: to_world must be a transform, got {t!r} ({type(t).__name__})")
    m = np.array(t.matrix, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise ParameterError("amr: to_world has non-finite entries")
    a = m[:3, :3]
    cond = np.linalg.cond(a)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise ParameterError(f"amr: to_world is singular or too ill-conditioned for float32 "
                             f"(condition number {cond:.3g} > {MAX_CONDITION:.0e})")
    return as_transform4f(t)
