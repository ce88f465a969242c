"""The structures pipeline: from AMR data and options to device structures.

The data are kept in their compact form, a `BlockVolume` (docs/design.md
section 9). `Structures` is the glue between a medium and its structures:
it resolves the chosen traversal and sampling in their registries
(`mi_amr.building.strategies`), builds the components they need on an explicit
`build` call (`mi_amr.building.components`; host structures come from a cache keyed by
data identity and options, `mi_amr.structures.cache`, so media sharing data
build them once), checks each build against the memory budget, and
recomputes every majorant when the classification (the TF and the density
scale, `mi_amr.transfer.classification`) changes (docs/design.md sections 4
and 6).

Spaces: host structures work in finest-level cell units; device structures
in the medium's local space, where the data bounds are the unit cube.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .components import COMPONENTS, thinning_resolution
from ..data.blocks import BlockVolume
from ..data.volume import as_method
from ..core.jit_struct import jit_struct
from ..data.device_values import device_field
from ..memory import require
from ..reconstruction import Reconstruction
from .strategies import SAMPLINGS, TRAVERSALS
from ..structures.cache import HOST_CACHE, StructureCache
from ..transfer.classification import Classification


@dataclass(frozen=True)
class StructureOptions:
    """Build options of the structures (parsed once from the medium's
    properties; see the ``amr`` plugin's parameter table)."""
    reconstruction: str = "tent"
    traversal: str = "grid"
    sampling: str = "hash"
    grid_resolution: int | None = None
    grid_refinement: int | None = None
    thinning_resolution: int | None = None
    brick_size: int = 8
    kdtree_leaves: int = 4096
    memory_limit: float | None = None
    value_masks: bool = True

    @property
    def method(self) -> Reconstruction:
        """The reconstruction method (`mi_amr.reconstruction`), resolved once."""
        return as_method(self.reconstruction)

    @property
    def grid_masks(self) -> bool:
        """Whether macrocell grids carry value masks (where the method's
        fields let them tighten the ranges' majorants: docs/design.md
        section 4)."""
        return self.value_masks and self.method.value_masks_tighten


@jit_struct(offset="Vector3f", extent="Vector3f", global_majorant="Float", device=dict, carried_fields=dict)
class Structures:
    """Device structures of one medium, and the host structures behind them.

    Dr.Jit state: ``offset``/``extent`` (the data bounds in finest units
    relative to the hash key origin), ``global_majorant`` (the largest
    majorant of any leaf, inverse world units) and ``device`` (name ->
    device struct). Nothing is built before `build`; `segments` and
    `sampler` return views over what it built.
    """

    def __init__(self, volume: BlockVolume, options: StructureOptions,
                 classification: Classification, world_scale: float, cache: StructureCache = HOST_CACHE):
        self.cache = cache
        self.options = options
        self.classification = classification
        self.world_scale = world_scale
        self.traversal = TRAVERSALS[options.traversal]
        self.sampling = SAMPLINGS[options.sampling]
        self.volume = data = volume
        self.device = {}                # device structs (seen by dr.freeze)
        self.carried_fields = {}          # further fields' device values (`field_values`)
        self.host = {}                  # host-only structures (bricks)
        self.build_seconds = {}
        lo, hi = data.bounds
        self.origin = data.origin
        self.offset = mi.Vector3f(*[float(c) for c in lo - self.origin])
        self.extent = mi.Vector3f(*[float(c) for c in hi - lo])
        self.global_majorant = mi.Float(0.0)
        self.revaluers = {}              # components' updates on new values that keep state (`revalue`)
        self.finest_grid = None          # the cost model's finest grid, kept while building (`build_thinning`)
        dr.make_opaque(self.offset, self.extent)

    @property
    def support_beyond_cell(self) -> bool:
        """Whether a cell's reconstruction support reaches past the cell:
        region trees over the bricks' domains differ from trees over their
        bounds then."""
        return self.options.method.support_beyond_cell

    # ---- Building -------------------------------------------------------------
    def build(self):
        """Build every component the traversal and the sampling need (each once)."""
        for name in self.traversal.needs(self) + self.sampling.needs(self):
            self.require(name)
        if thinning_resolution(self):
            self.require("thinning")
        self.finest_grid = None
        return self

    def require(self, name: str):
        """Component ``name`` (`mi_amr.building.components.COMPONENTS`), built now if it was
        not: its estimated peak bytes are checked against the memory budget
        first. Building inside a kernel recording is an error."""
        component = COMPONENTS[name]
        store = self.device if component.device else self.host
        if name not in store:
            if dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(f"amr: structure '{name}' must be built before rendering")
            require(component.need(self), f"amr: the {name} structure of {self.volume.source} "
                    f"({len(self.volume)} cells)", self.options.memory_limit, "use fewer cells or raise the limit")
            t0 = time.perf_counter()
            store[name] = component.build(self)
            self.build_seconds[name] = time.perf_counter() - t0
        return store[name]

    @property
    def grid(self):
        """The device macrocell grid (`DeviceMacrocellGrid` or
        `DeviceTwoLevelGrid`), once built."""
        return self._built("grid")

    def _built(self, name):
        store = self.device if COMPONENTS[name].device else self.host
        if name not in store:
            raise RuntimeError(f"amr: the {name} structure was not built for this medium "
                               f"(traversal {self.options.traversal!r}, sampling {self.options.sampling!r})")
        return store[name]

    # ---- Views used by the tracking kernels --------------------------------
    def segments(self, levels: bool = False, ranges: bool = False):
        """The segment walker of the chosen traversal; with ``levels``, one
        that reports each segment's finest level (`Segment.level`); with
        ``ranges``, each segment's value range (`Segment.vmin`, ``vmax``)."""
        return self.traversal.walker(self._built(self.traversal.structure(self)), levels, ranges)

    def thinning(self):
        """``thin(u, active) -> mu_f``: the finer majorant at local points
        ``u`` (inverse world units) that thins the walks' tentative
        collisions (docs/design.md section 5d), or None where none was built."""
        grid = self.device.get("thinning")
        return None if grid is None else grid.majorant_at

    def sampler(self, carried: mi.Float | None = None):
        """The point sampler of the chosen sampling: ``eval(u, active) ->
        (value, found)`` at local points ``u``. With a ``carried`` field
        (`field_values`) one look-up reconstructs both: ``value`` is then a
        ``Vector2f`` (main, carried) (docs/design.md section 12)."""
        for name in self.sampling.needs(self):
            self._built(name)
        return self.sampling.sampler(self, carried)

    def field_values(self, name: str | None, transform: str = "none") -> mi.Float:
        """A further field of the data (`BlockVolume.field`; None: the main
        values) with ``transform``, as a device array in the values' layout
        (made once; kept in a struct field, so that dr.freeze sees it): the
        ``carried`` field of `sampler`."""
        key = f"{name}:{transform}"
        if key not in self.carried_fields:
            self.carried_fields[key] = device_field(self.volume, name, transform)
        return self.carried_fields[key]

    # ---- Classification changes ----------------------------------------------
    def reclassify(self, classification: Classification | None = None):
        """After a TF or density-scale change: rebuild the components built
        for the old classification (the SAH kd-tree, whose topology was
        chosen by its majorants), then recompute every majorant."""
        if classification is not None:
            self.classification = classification
        for name, component in COMPONENTS.items():
            if component.classified and name in self.device:
                t0 = time.perf_counter()
                del self.device[name]
                self.require(name)
                self.build_seconds[f"{name}_rebuild"] = time.perf_counter() - t0
        self.update_majorants()

    def revalue(self, volume: BlockVolume, values: mi.Float) -> bool:
        """New values of the same cells, in place (docs/design.md section
        13): ``volume`` from `BlockVolume.with_values`, ``values`` its device
        array (the medium's ``values`` parameter). Each built component
        takes them by its own update (`Component.revalue`: the macrocell
        grid's ranges by scatter-reductions, the hash reads the new array,
        the thinning grid is dropped), then every majorant is recomputed as
        after a TF change: milliseconds, no build. False where a component
        cannot (no update of its own, host structures or a carried field
        built on the old values): the caller rebuilds."""
        components = [COMPONENTS[name] for name in self.device]
        if self.host or self.carried_fields or any(c.revalue is None for c in components):
            return False
        t0 = time.perf_counter()
        old = self.volume
        for component in components:
            if not component.revalue(self, old, volume, values):
                return False
        self.volume = volume
        for struct in self.device.values():
            if "values" in getattr(struct, "JIT_FIELDS", {}):
                struct.values = values
        self.update_majorants()
        self.build_seconds["revalue"] = time.perf_counter() - t0
        return True

    def update_majorants(self):
        """Recompute the majorants and minorants of every built structure
        from its value ranges and the classification (one Dr.Jit kernel
        each), and the global maximum. Minorants are 0 unless the cells
        fill their bounding box."""
        c = self.classification
        dr.eval()        # pending work of others stays out of the majorant kernels,
        mus = []         # so that they are the same code at load time and after
        minorants = self.volume.covers_bounds          # else a point may have no value (sigma_t = 0)
        for name, component in COMPONENTS.items():
            if component.majorants and name in self.device:
                self.device[name].update_majorants(c.device, c.majorant_scale, minorants and component.minorants)
                mus.append(dr.max(self.device[name].majorant))
        g = mus[0] if mus else mi.Float(0.0)
        for m in mus[1:]:
            g = dr.maximum(g, m)
        self.global_majorant = mi.Float(dr.ravel(g))
        dr.make_opaque(self.global_majorant)

    def minorant_fraction(self) -> float:
        """The share of the majorant that the minorant carries over the
        traversal structure, volume-weighted: ``sum(V mu_min) / sum(V mu_max)``
        over its leaves (0 with no majorant). Read back on the host."""
        lo, hi, vol = self.segments().leaf_bounds()
        # elementwise sums, not np.dot: a BLAS dot of this length wakes
        # OpenBLAS's worker threads, which then spin on a core and slow the
        # first frames after a load (docs/performance/frame-cost.md)
        total = float(np.sum(vol * hi, dtype=np.float64))
        return float(np.sum(vol * lo, dtype=np.float64)) / total if total > 0 else 0.0

    @property
    def built(self) -> set:
        """Names of the structures built so far."""
        return set(self.device) | set(self.host)

    @property
    def nbytes(self) -> int:
        """Memory of every structure built so far (host arrays uploaded;
        a component whose arrays are another's is counted once)."""
        total = 0
        for name, obj in {**self.host, **self.device}.items():
            if COMPONENTS[name].shares is not None:
                continue
            host = getattr(obj, "host", obj)
            total += int(getattr(host, "nbytes", 0) or getattr(obj, "nbytes", 0))
        return total
