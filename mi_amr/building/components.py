"""How each structure of a medium is built: one function per component.

A *component* is one structure a traversal or a sampling needs: the
macrocell grid, the bricks, the region trees over them, the SAH kd-tree,
the block hash, the bricks' device copy and the brick lists. Each entry of
`COMPONENTS` says how to build it from a `mi_amr.building.pipeline.Structures`
(which gives the data, the build options, the classification and the
host-structure cache), what it needs first, its estimated peak bytes
(checked against the memory budget before the build), whether its leaves
carry majorants (recomputed on every TF or density-scale change), and
whether its shape depends on the classification (rebuilt on a change).

Spaces: host structures in finest-level cell units; device structures in
the medium's local space, where the data bounds are the unit cube.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..device.bricks import DeviceBrickLists, DeviceBricks
from ..device.grid import DeviceMacrocellGrid, DeviceThinningGrid, DeviceTwoLevelGrid
from ..device.hash_sampler import DeviceReconstruction
from ..device.grid_revalue import GridRevaluer
from ..device.tree import DeviceTree
from ..memory import bricks_bytes, hash_bytes
from ..structures.footprint import GRID_BYTES_PER_MACROCELL, THINNING_BYTES_PER_MACROCELL
from ..structures.brick_lists import BrickLists
from ..structures.bricks import Bricks
from ..structures.cost_model import REFINEMENTS, GridPlan, auto_grid, thinning_candidate
from ..structures.kdtree_sah import build_sah_kdtree
from ..structures.macrocell_grid import MacrocellGrid, axis_resolution, default_resolution, finest_levels_in_boxes
from ..structures.region_tree import brick_region_tree, exact_value_ranges, finest_levels


@dataclass(frozen=True)
class Component:
    """How one structure is built (see the module docstring).

    ``build(s)``: the structure, for `Structures` ``s`` (its dependencies
    built first through ``s.require``); ``need(s)``: estimated peak bytes;
    ``device``: a device struct (kept where ``dr.freeze`` sees it) rather
    than a host-only one; ``majorants``: it has ``update_majorants(tf,
    density_scale, minorants)``; ``minorants``: its minorants are used
    (else they stay 0 and cost nothing on a TF change); ``classified``:
    built for the current TF and scale, so rebuilt when they change;
    ``shares``: its memory is another component's (not counted again);
    ``revalue(s, old_volume, volume, values)``: its own update on new values
    of the same cells (docs/design.md section 13), True when done in place,
    False (having changed nothing) where it cannot; None: it depends on
    the values in a way it cannot update, so the medium rebuilds."""
    build: Callable
    need: Callable = lambda s: 0.0
    device: bool = True
    majorants: bool = False
    minorants: bool = True
    classified: bool = False
    shares: str | None = None
    revalue: Callable | None = None


# ---- The components ------------------------------------------------------------
def build_grid(s):
    """The macrocell grid: resolution and refinement as given, else from the
    cost model of the data and the classification (`auto_grid`)."""
    o = s.options
    res, f = o.grid_resolution, o.grid_refinement
    host = None
    if res is None:
        grids = {}
        c = s.classification
        plan, _ = auto_grid(s.volume, c.tf, c.density_scale, s.world_scale, o.method, grids=grids,
                            masks=o.grid_masks, refinements=(f,) if f else (1,) + REFINEMENTS)
        res, f = plan.resolution, plan.refinement
        s.finest_grid = next(iter(grids.values()), None)       # the thinning's, pooled (`build_thinning`)
        # the chosen grid from the finest one, if they tile
        host = next((p for p in (g.pooled(res) for g in grids.values()) if p is not None), None)
    f = f or 1
    if host is None:
        host = MacrocellGrid(s.volume, res, support=o.method, memory_limit=o.memory_limit,
                             masks=o.grid_masks)
    if f == 1:
        return DeviceMacrocellGrid(host)
    return DeviceTwoLevelGrid(host, f, s.world_scale, GridPlan(int(res), f).step_costs())


def thinning_resolution(s) -> int:
    """The resolution (longest axis) of the finer majorants that thin the
    walks' tentative collisions (docs/design.md section 5d): as given
    (``thinning_resolution``; 0: none), else, for a grid traversal,
    `thinning_candidate` where it is finer than the walked grid's finest
    level, and none otherwise."""
    o = s.options
    if o.thinning_resolution is not None:
        return o.thinning_resolution
    if o.traversal != "grid":
        return 0
    res = thinning_candidate(s.volume)
    return res if res > int(np.max(s.require("grid").host.res)) else 0


def build_thinning(s):
    """The finer majorants (`thinning_resolution`): a uniform macrocell
    grid, pooled from the finest grid the cost model built where it tiles
    it, else built."""
    o = s.options
    res = thinning_resolution(s)
    host = s.finest_grid.pooled(res) if s.finest_grid is not None else None
    if host is None:
        host = MacrocellGrid(s.volume, res, support=o.method, memory_limit=o.memory_limit, masks=o.grid_masks)
    return DeviceThinningGrid(host)


def _need_thinning(s) -> float:
    # the host grid while it is built or pooled, and the device copy
    lo, hi = s.volume.bounds
    n = float(np.prod(axis_resolution(max(thinning_resolution(s), 1), hi - lo), dtype=np.float64))
    return n * (GRID_BYTES_PER_MACROCELL + 8 + THINNING_BYTES_PER_MACROCELL)


def build_bricks(s) -> Bricks:
    size = s.options.brick_size
    return s.cache.get(s.volume, ("bricks", size), lambda: Bricks(s.volume, size))


def _need_bricks(s) -> float:
    return bricks_bytes(len(s.volume), s.volume.partial_block_cells)


def _region_tree(over_domains: bool, name: str):
    """A kd-tree over the bricks' domains (``over_domains``: the regions
    their cells reconstruct under a method whose support reaches past the
    cell) or over their bounds; leaves carry the exact value ranges of the
    method's supports."""
    def build(s) -> DeviceTree:
        bricks = s.require("bricks")
        method = s.options.method
        lo, hi = s.volume.bounds

        def make_host():
            tree = brick_region_tree(bricks, lo, hi, over_domains, memory_limit=s.options.memory_limit,
                                     what=f"amr: the {name} structure of {s.volume.source} ({len(s.volume)} cells)",
                                     method=method)
            # the tree is over the supports of the method unless it is the bounds tree of a wider method
            own = over_domains or not s.support_beyond_cell
            vmin, vmax = exact_value_ranges(tree, bricks, method, own_lists=own)
            return tree, vmin, vmax, finest_levels(tree, bricks, method, own_lists=own)

        tree, vmin, vmax, levels = s.cache.get(s.volume, (name, s.options.brick_size, method.name, "levels"),
                                               make_host)
        return DeviceTree(tree, 2 * lo, 0.5 / (hi - lo), vmin, vmax, finest_level=levels)
    return build


def build_kdtree(s) -> DeviceTree:
    """SAH kd-tree built for the current classification over a macrocell grid
    four times finer than the default one (at most 128 per axis)."""
    res = int(min(128, 4 * default_resolution(s.volume).max()))
    o = s.options
    g = s.cache.get(s.volume, ("kd_grid", res, o.reconstruction),
                    lambda: MacrocellGrid(s.volume, res, support=o.method, memory_limit=o.memory_limit))
    r = g.res
    shape = (r[2], r[1], r[0])
    # host majorants in inverse local units, for the SAH cost
    mu = s.classification.host_majorants(g.vmin, g.vmax) * s.world_scale
    maj = mu.reshape(shape).transpose(2, 1, 0)
    vmin = g.vmin.reshape(shape).transpose(2, 1, 0)
    vmax = g.vmax.reshape(shape).transpose(2, 1, 0)
    tree, lmin, lmax = build_sah_kdtree(maj, vmin, vmax, o.kdtree_leaves)
    bits = g.level_bits.reshape(shape).transpose(2, 1, 0)
    return DeviceTree(tree, np.zeros(3), 1.0 / r, lmin, lmax, finest_level=finest_levels_in_boxes(bits, tree))


def build_hash(s) -> DeviceReconstruction:
    return DeviceReconstruction(s.volume, s.options.method)


def _need_hash(s) -> float:
    return hash_bytes(len(s.volume.level), s.options.method) + s.volume.values.nbytes


def build_device_bricks(s) -> DeviceBricks:
    return DeviceBricks(s.require("bricks"), s.volume.origin)


def build_brick_lists(s) -> DeviceBrickLists:
    lo, hi = s.volume.bounds
    return DeviceBrickLists(BrickLists(s.require("bricks"), lo, hi - lo, _list_grid_resolution(s.volume),
                                       memory_limit=s.options.memory_limit, method=s.options.method))


def _list_grid_resolution(volume):
    """Brick-list grid: about two finest cells per list cell (short lists),
    at most 128 along the longest axis."""
    lo, hi = volume.bounds
    ext = (hi - lo).astype(np.float64)
    return axis_resolution(int(np.clip(ext.max() / 2, 1, 128)), ext)


#: Every component by name; the order is the order majorants are updated in.
# ---- Updates on new values of the same cells (`Structures.revalue`) --------------
def _revalue_grid(s, old_volume, volume, values) -> bool:
    """The macrocell grid's ranges and masks from the new values (its
    `GridRevaluer`, kept with the structures for the next call)."""
    revaluer = s.revaluers.get("grid")
    if revaluer is None:
        revaluer = s.revaluers["grid"] = GridRevaluer(s.device["grid"], s.options.method, s.options.memory_limit)
    return revaluer(old_volume, volume, values)


def _reads_values_only(s, old_volume, volume, values) -> bool:
    """Nothing but the ``values`` array, which `Structures.revalue` swaps."""
    return True


def _drop_thinning(s, old_volume, volume, values) -> bool:
    """The finer majorants hold the old values' ranges: the walks go on
    without thinning (differentiable walks never thin: docs/design.md
    section 5d)."""
    s.device.pop("thinning", None)
    return True


COMPONENTS = {
    "grid": Component(build_grid, majorants=True, revalue=_revalue_grid),
    "thinning": Component(build_thinning, need=_need_thinning, majorants=True, minorants=False,
                          revalue=_drop_thinning),
    "abr_tree": Component(_region_tree(True, "abr_tree"), majorants=True),
    "brick_tree": Component(_region_tree(False, "brick_tree"), majorants=True),
    "kdtree": Component(build_kdtree, majorants=True, classified=True),
    "bricks": Component(build_bricks, need=_need_bricks, device=False),
    "hash": Component(build_hash, need=_need_hash, revalue=_reads_values_only),
    "device_bricks": Component(build_device_bricks, shares="bricks"),
    "brick_lists": Component(build_brick_lists),
}
