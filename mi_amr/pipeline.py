"""The structures pipeline: from AMR data and options to device structures.

The data are kept in their compact form, a `BlockVolume` (docs/design.md
section 9). `Structures` builds, once per medium, exactly what the chosen
traversal and sampling need (host structures are cached on the data object,
so media sharing data build them once), checks each build against the memory budget,
uploads the device structs and recomputes every majorant when the transfer
function or the density scale changes (docs/design.md sections 4 and 6).

Spaces: host structures work in finest-level cell units; device structures
in the medium's local space, where the data bounds are the unit cube.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .data.blocks import BlockVolume
from .data.cells import AMRCells
from .device.bricks import BrickSampler, DeviceBrickLists, DeviceBricks
from .device.grid import DeviceMacrocellGrid, DeviceTwoLevelGrid
from .device.hash_sampler import DeviceReconstruction, HashSampler
from .device.segments import GridSegments, TreeSegments, TwoLevelGridSegments
from .device.structs import jit_struct
from .device.tree import DeviceTree
from .memory import bricks_bytes, hash_bytes, require
from .structures.brick_lists import BrickLists
from .structures.bricks import Bricks
from .structures.cost_model import REFINEMENTS, GridPlan, auto_grid
from .structures.kdtree_sah import build_sah_kdtree
from .structures.macrocell_grid import MacrocellGrid, axis_resolution, default_resolution
from .structures.region_tree import brick_region_tree, exact_value_ranges
from .transfer.function import TransferFunction, range_majorants_host

TRAVERSALS = ("grid", "abr", "brick", "kdtree")
SAMPLINGS = ("hash", "abr", "brick")
#: Structures whose leaves carry majorants, in the order they are updated.
MAJORANT_STRUCTURES = ("grid", "abr_tree", "brick_tree", "kdtree")


@dataclass(frozen=True)
class StructureOptions:
    """Build options of the structures (parsed once from the medium's
    properties; see the ``amr`` plugin's parameter table)."""
    reconstruction: str = "tent"
    traversal: str = "grid"
    sampling: str = "hash"
    grid_resolution: int | None = None
    grid_refinement: int | None = None
    brick_size: int = 8
    kdtree_leaves: int = 4096
    memory_limit: float | None = None
    value_masks: bool = True

    @property
    def grid_masks(self) -> bool:
        """Whether macrocell grids carry value masks (``nearest`` only:
        docs/design.md section 4)."""
        return self.value_masks and self.reconstruction == "nearest"


@jit_struct(offset="Vector3f", extent="Vector3f", global_majorant="Float", device=dict)
class Structures:
    """Device structures of one medium, and the host structures behind them.

    Dr.Jit state: ``offset``/``extent`` (the data bounds in finest units
    relative to the hash key origin), ``global_majorant`` (the largest
    majorant of any leaf, inverse world units) and ``device`` (name ->
    device struct). `segments` and `sampler` return views over them.
    """

    def __init__(self, data: AMRCells | BlockVolume, options: StructureOptions, tf: TransferFunction,
                 density_scale: float, world_scale: float):
        if isinstance(data, AMRCells):
            # blocks of the cells, made once per AMRCells object (their block
            # size weighed for the first medium's reconstruction): media on
            # the same cells share the blocks and their device copy
            self._given_cells = data
            cache = data.__dict__.setdefault("_mi_amr_cache", {})
            if "volume" not in cache:
                cache["volume"] = BlockVolume.from_cells(data, method=options.reconstruction)
            data = cache["volume"]
        else:
            self._given_cells = None
        self.volume = data
        self.options = options
        self.world_scale = world_scale
        self._tf, self._density_scale = tf, density_scale
        self.device = {}
        self.host = {}                  # host-only structures (bricks)
        self.build_seconds = {}
        lo, hi = data.bounds
        self.origin = data.origin
        self.offset = mi.Vector3f(*[float(c) for c in lo - self.origin])
        self.extent = mi.Vector3f(*[float(c) for c in hi - lo])
        self.global_majorant = mi.Float(0.0)
        dr.make_opaque(self.offset, self.extent)
        self._majorant_inputs = None    # (device TF, density scale) once majorants exist
        self.segments()
        self.sampler()

    # ---- Building (each structure once) ------------------------------------
    def _build(self, name, make, need: float = 0.0, store=None):
        """Build structure ``name`` once into ``store`` (default: the device
        structs); ``need``: its estimated peak bytes, checked against the
        memory budget first."""
        store = self.device if store is None else store
        if name not in store:
            if dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(f"amr: structure '{name}' must be built before rendering")
            require(need, f"amr: the {name} structure of {self.volume.source} ({len(self.volume)} cells)",
                    self.options.memory_limit, "use fewer cells or raise the limit")
            t0 = time.perf_counter()
            store[name] = make()
            self.build_seconds[name] = time.perf_counter() - t0
            if name in MAJORANT_STRUCTURES and self._majorant_inputs is not None:
                self.update_majorants(*self._majorant_inputs)
        return store[name]

    def _host_cached(self, key, make):
        """Host structures depend only on the data and build options: cache
        them on the data object (a re-loaded scene builds nothing)."""
        cache = self.volume.__dict__.setdefault("_mi_amr_cache", {})
        if key not in cache:
            cache[key] = make()
        return cache[key]

    @property
    def cells(self) -> AMRCells:
        """Per-cell records (for tools and tests; no build needs them): the
        `AMRCells` given, or made from the blocks for the caller, not kept
        (the blocks stay the only resident copy)."""
        if self._given_cells is not None:
            return self._given_cells
        return self.volume.to_cells()

    @property
    def grid(self) -> DeviceMacrocellGrid | DeviceTwoLevelGrid:
        """The macrocell grid: resolution and refinement as given, else from
        the cost model of the data and the TF (`auto_grid`)."""
        def make():
            res, f = self.options.grid_resolution, self.options.grid_refinement
            host = None
            if res is None:
                grids = {}
                plan, _ = auto_grid(self.volume, self._tf, self._density_scale, self.world_scale,
                                    self.options.reconstruction, grids=grids, masks=self.options.grid_masks,
                                    refinements=(f,) if f else (1,) + REFINEMENTS)
                res, f = plan.resolution, plan.refinement
                # the chosen grid from the finest one, if they tile
                host = next((p for p in (g.pooled(res) for g in grids.values()) if p is not None), None)
            f = f or 1
            if host is None:
                host = MacrocellGrid(self.volume, res, support=self.options.reconstruction,
                                     memory_limit=self.options.memory_limit, masks=self.options.grid_masks)
            if f == 1:
                return DeviceMacrocellGrid(host)
            return DeviceTwoLevelGrid(host, f, self.world_scale, GridPlan(int(res), f).step_costs())
        return self._build("grid", make)

    @property
    def bricks(self) -> Bricks:
        size = self.options.brick_size
        return self._build("bricks", lambda: self._host_cached(("bricks", size), lambda: Bricks(self.volume, size)),
                           need=bricks_bytes(len(self.volume), self.volume.partial_block_cells), store=self.host)

    def brick_tree(self, kind: str) -> DeviceTree:
        """kd-tree over the bricks' supports (``abr``: the regions their cells
        reconstruct, so domains for ``tent`` and bounds for ``nearest``) or
        over their bounds (``brick``). With ``nearest`` both are one tree."""
        method = self.options.reconstruction
        over_domains = kind == "abr" and method == "tent"

        def make_host():
            b = self.bricks
            tree = brick_region_tree(b, *self.volume.bounds, over_domains, memory_limit=self.options.memory_limit,
                                     what=f"amr: the {key} structure of {self.volume.source} ({len(self.volume)} cells)")
            # the tree is over the supports of ``method`` unless it is the tent brick tree
            vmin, vmax = exact_value_ranges(tree, b, method, own_lists=over_domains or method == "nearest")
            return tree, vmin, vmax

        key = "abr_tree" if over_domains else "brick_tree"

        def make():
            lo, hi = self.volume.bounds
            tree, vmin, vmax = self._host_cached((key, self.options.brick_size, method), make_host)
            return DeviceTree(tree, 2 * lo, 0.5 / (hi - lo), vmin, vmax)
        return self._build(key, make)

    def kdtree(self) -> DeviceTree:
        """SAH kd-tree built for the current TF over a macrocell grid four
        times finer than the default one (at most 128 per axis)."""
        def make():
            res = int(min(128, 4 * default_resolution(self.volume).max()))
            g = self._host_cached(("kd_grid", res, self.options.reconstruction),
                                  lambda: MacrocellGrid(self.volume, res, support=self.options.reconstruction,
                                                        memory_limit=self.options.memory_limit))
            r = g.res
            shape = (r[2], r[1], r[0])
            # host majorants in inverse local units, for the SAH cost
            mu = range_majorants_host(self._tf, g.vmin, g.vmax, self._density_scale) * self.world_scale
            maj = mu.reshape(shape).transpose(2, 1, 0)
            vmin = g.vmin.reshape(shape).transpose(2, 1, 0)
            vmax = g.vmax.reshape(shape).transpose(2, 1, 0)
            tree, lmin, lmax = build_sah_kdtree(maj, vmin, vmax, self.options.kdtree_leaves)
            return DeviceTree(tree, np.zeros(3), 1.0 / r, lmin, lmax)
        return self._build("kdtree", make)

    # ---- Views used by the tracking kernels --------------------------------
    def segments(self):
        """The segment walker of the chosen traversal."""
        traversal = self.options.traversal
        if traversal == "grid":
            grid = self.grid
            return TwoLevelGridSegments(grid) if isinstance(grid, DeviceTwoLevelGrid) else GridSegments(grid)
        if traversal == "kdtree":
            return TreeSegments(self.kdtree())
        return TreeSegments(self.brick_tree(traversal))

    def sampler(self):
        """The point sampler of the chosen sampling: ``eval(u, active) ->
        (value, found)`` at local points ``u``."""
        method, sampling = self.options.reconstruction, self.options.sampling
        if sampling == "hash":
            grid = self.grid                       # its level masks limit the levels visited
            table = self._build("hash", lambda: DeviceReconstruction(self.volume, method),
                                need=hash_bytes(len(self.volume.level), method) + self.volume.values.nbytes)
            return HashSampler(table, grid, self.offset, self.extent)
        bricks = self._build("device_bricks", lambda: DeviceBricks(self.bricks, self.origin))
        if sampling == "abr":
            return BrickSampler(bricks, method, self.offset, self.extent, abr_tree=self.brick_tree("abr"),
                                over_bounds=method == "nearest")
        lo, hi = self.volume.bounds
        res = _list_grid_resolution(self.volume)
        lists = self._build("brick_lists", lambda: DeviceBrickLists(BrickLists(
            self.bricks, lo, hi - lo, res, memory_limit=self.options.memory_limit)))
        return BrickSampler(bricks, method, self.offset, self.extent, lists=lists)

    # ---- Majorants -------------------------------------------------------------
    def update_majorants(self, tf_device, density_scale):
        """Recompute the majorants and minorants of every built structure
        from its value ranges, the TF and the density scale (one Dr.Jit
        kernel each), and the global maximum. Minorants are 0 unless the
        cells fill their bounding box."""
        self._majorant_inputs = (tf_device, density_scale)
        dr.eval()        # pending work of others stays out of the majorant kernels,
        mus = []         # so that they are the same code at load time and after
        minorants = self.volume.covers_bounds          # else a point may have no value (sigma_t = 0)
        for name in MAJORANT_STRUCTURES:
            if name in self.device:
                self.device[name].update_majorants(tf_device, density_scale, minorants)
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
        walker = self.segments()
        if isinstance(walker, TreeSegments):
            t = walker.tree
            lo, hi = t.minorant.numpy(), t.majorant.numpy()
            vol = np.prod(t.host.leaf_hi - t.host.leaf_lo, axis=1)
        else:                                          # grids: equal macrocells (the fine ones)
            lo, hi = walker.grid.minorant.numpy(), walker.grid.majorant.numpy()
            vol = np.ones(len(hi))
        # elementwise sums, not np.dot: a BLAS dot of this length wakes
        # OpenBLAS's worker threads, which then spin on a core for about
        # 0.1 s and halve the speed of the first frames after a load
        total = float(np.sum(vol * hi, dtype=np.float64))
        return float(np.sum(vol * lo, dtype=np.float64)) / total if total > 0 else 0.0

    def set_transfer_function(self, tf: TransferFunction, density_scale: float, rebuild: bool = True):
        """Use a new TF and scale for the builds that depend on them: the
        pre-classified kd-tree is rebuilt (its topology was chosen for the
        old TF) unless ``rebuild`` is false."""
        self._tf, self._density_scale = tf, density_scale
        if rebuild and "kdtree" in self.device:
            t0 = time.perf_counter()
            del self.device["kdtree"]
            self.kdtree()
            self.build_seconds["kdtree_rebuild"] = time.perf_counter() - t0

    @property
    def built(self) -> set:
        """Names of the structures built so far."""
        return set(self.device) | set(self.host)

    @property
    def nbytes(self) -> int:
        """Memory of every structure built so far (host arrays uploaded)."""
        total = 0
        for name, obj in {**self.host, **self.device}.items():
            if name == "device_bricks":          # the same arrays as "bricks"
                continue
            host = getattr(obj, "host", obj)
            total += int(getattr(host, "nbytes", 0) or getattr(obj, "nbytes", 0))
        return total


def _list_grid_resolution(cells):
    """Brick-list grid: about two finest cells per list cell (short lists),
    at most 128 along the longest axis."""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    return axis_resolution(int(np.clip(ext.max() / 2, 1, 128)), ext)
