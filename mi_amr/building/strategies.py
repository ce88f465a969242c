"""The registries of traversals and samplings, by the names the ``amr`` medium takes.

A *traversal* turns a ray into segments with a majorant each (what tracking
walks); a *sampling* locates a point and reconstructs the value there (what
a density look-up runs). Each entry names the components it needs
(`mi_amr.building.components.COMPONENTS`: host build, device upload, memory estimate,
majorant and minorant update) and makes its device view from them: the
segment walker (`mi_amr.device.segments`) or the point sampler.

Adding a traversal or a sampling is one entry here (plus its walker or
sampler and components where they are new); nothing else names them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..device.bricks import BrickSampler
from ..device.grid import DeviceTwoLevelGrid
from ..device.hash_sampler import HashSampler
from ..device.segments import GridSegments, TreeSegments, TwoLevelGridSegments


@dataclass(frozen=True)
class Traversal:
    """``structure(s)``: the name of the component whose leaves are the
    segments (for `mi_amr.building.pipeline.Structures` ``s``); ``walker(device,
    levels, ranges)``: the segment walker over its device struct (``levels``:
    it reports each segment's finest level; ``ranges``: its value range)."""
    structure: Callable
    walker: Callable

    def needs(self, s) -> tuple:
        return (self.structure(s),)


@dataclass(frozen=True)
class Sampling:
    """``needs``: the components the sampler reads; ``sampler(s, carried)``:
    the point sampler, ``eval(u, active) -> (value, found)`` at local points
    (``value`` a ``Vector2f`` when a further field is ``carried``)."""
    needs_: tuple
    sampler: Callable

    def needs(self, s) -> tuple:
        return tuple(c(s) if callable(c) else c for c in self.needs_)


def _grid_walker(grid, levels=False, ranges=False):
    return (TwoLevelGridSegments if isinstance(grid, DeviceTwoLevelGrid) else GridSegments)(grid, levels, ranges)


def _abr_tree(s) -> str:
    """The ABR tree: over the bricks' domains where the method's support
    reaches past the cell, else the bounds tree (one tree for both)."""
    return "abr_tree" if s.support_beyond_cell else "brick_tree"


#: Traversals by name (the ``traversal`` parameter).
TRAVERSALS = {
    "grid": Traversal(lambda s: "grid", _grid_walker),
    "abr": Traversal(_abr_tree, TreeSegments),
    "brick": Traversal(lambda s: "brick_tree", TreeSegments),
    "kdtree": Traversal(lambda s: "kdtree", TreeSegments),
}


def _hash_sampler(s, carried=None):
    # the macrocell grid's level masks limit the levels probed
    return HashSampler(s.device["hash"], s.device["grid"], s.offset, s.extent, carried=carried)


def _abr_sampler(s, carried=None):
    return BrickSampler(s.device["device_bricks"], s.options.method, s.offset, s.extent,
                        abr_tree=s.device[_abr_tree(s)], over_bounds=not s.support_beyond_cell, carried=carried)


def _brick_sampler(s, carried=None):
    return BrickSampler(s.device["device_bricks"], s.options.method, s.offset, s.extent,
                        lists=s.device["brick_lists"], carried=carried)


#: Samplings by name (the ``sampling`` parameter).
SAMPLINGS = {
    "hash": Sampling(("grid", "hash"), _hash_sampler),
    "abr": Sampling(("bricks", "device_bricks", _abr_tree), _abr_sampler),
    "brick": Sampling(("bricks", "device_bricks", "brick_lists"), _brick_sampler),
}
