"""kd-trees whose leaves are boxes with a constant list of overlapping boxes.

`build_region_tree` splits a root box at faces of the input boxes that lie
strictly inside a node, until no face is left inside: every leaf then
overlaps a fixed set of input boxes, each of which covers the leaf
completely. With a leaf floor (``leaf_extent``) small nodes stop early and
list every box that overlaps them, some only in part. Over brick *domains*
the leaves are the active brick regions (ABRs); over brick *bounds* (which
do not overlap) each leaf lies in at most one brick. The leaves partition
the root box.

Coordinates are exact: the caller passes integer boxes (finest units times
two, so that domain faces at half cells stay integers).
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from ..data.device_values import device_values
from ..memory import BYTES_PER_TREE_ITEM, BYTES_PER_TREE_NODE, BYTES_PER_TREE_PAIR, require
from ..progress import progress
from ..reconstruction import DEFAULT_METHOD, Reconstruction
from .macrocell_grid import NO_LEVEL


#: Tent ABR leaves are not split once no side is longer than this many cells
#: of the finest brick they touch (docs/design.md section 4).
ABR_LEAF_CELLS = 4


class RegionTree:
    """A kd-tree built by `build_region_tree` (host, numpy).

    Nodes: ``axis`` (0-2, or 3 for a leaf), ``split`` (the plane, same units
    as the boxes), ``child`` (index of the left child, right = left + 1; for a
    leaf, the leaf index). Leaves: ``leaf_lo``/``leaf_hi`` (L, 3) and a CSR
    list of input box ids (``list_offset``, ``list_count``, ``items``).
    """

    def __init__(self, axis, split, child, leaf_lo, leaf_hi, lists, depth: int | None = None):
        """``lists``: one array of box ids per leaf, or ``(count, items)``
        (CSR: items of leaf 0 first)."""
        self.axis = np.asarray(axis, dtype=np.uint32)
        self.split = np.asarray(split, dtype=np.float64)
        self.child = np.asarray(child, dtype=np.uint32)
        self.leaf_lo = np.asarray(leaf_lo, dtype=np.float64).reshape(-1, 3)
        self.leaf_hi = np.asarray(leaf_hi, dtype=np.float64).reshape(-1, 3)
        if isinstance(lists, tuple):
            count, items = lists
        else:
            count = [len(x) for x in lists]
            items = np.concatenate(lists) if len(lists) else np.zeros(0)
        self.list_count = np.asarray(count, dtype=np.uint32)
        self.list_offset = np.concatenate([[0], np.cumsum(self.list_count)[:-1]]).astype(np.uint32)
        self.items = np.asarray(items).astype(np.uint32)
        self.depth = _depth(self.axis, self.child) if depth is None else int(depth)

    @property
    def n_leaves(self) -> int:
        return len(self.leaf_lo)

    @property
    def nbytes(self) -> int:
        return (self.axis.nbytes + 4 * len(self.split) + self.child.nbytes
                + 4 * 6 * self.n_leaves + self.list_count.nbytes * 2 + self.items.nbytes)

    def overlapping_leaves(self, box_lo, box_hi):
        """``(box, leaf)`` index pairs of integer boxes (K, 3), in the tree's
        units, and the leaves they overlap (closed intervals), found by
        descending all boxes through the tree together, one depth at a time
        (int32 coordinates where they fit)."""
        span = max(np.abs(a).max(initial=0) for a in (box_lo, box_hi, self.leaf_lo, self.leaf_hi))
        ctype = np.int32 if span < 2**30 else np.int64
        box_lo, box_hi = np.asarray(box_lo).astype(ctype), np.asarray(box_hi).astype(ctype)
        leaf_lo, leaf_hi = self.leaf_lo.astype(ctype), self.leaf_hi.astype(ctype)
        flat_lo, flat_hi = box_lo.ravel(), box_hi.ravel()
        axis, split = self.axis.astype(np.int32), self.split.astype(ctype)
        child = self.child.astype(np.int32 if len(self.child) < 2**31 else np.int64)
        bi = np.arange(len(box_lo), dtype=child.dtype)
        node = np.zeros(len(box_lo), dtype=child.dtype)
        out_b, out_l = [], []
        while len(bi):
            ax = np.take(axis, node)
            leaf = ax == 3
            if leaf.any():
                lb, ln = bi[leaf], np.take(child, node[leaf])
                ok = np.all((np.take(box_lo, lb, axis=0) <= np.take(leaf_hi, ln, axis=0))
                            & (np.take(box_hi, lb, axis=0) >= np.take(leaf_lo, ln, axis=0)), axis=1)
                out_b.append(lb[ok])
                out_l.append(ln[ok])
                inner = ~leaf
                bi, node, ax = bi[inner], node[inner], ax[inner]
            s = np.take(split, node)
            at = 3 * bi + ax
            go_l = np.take(flat_lo, at) <= s
            go_r = np.take(flat_hi, at) >= s
            c = np.take(child, node)
            bi, node = np.concatenate([bi[go_l], bi[go_r]]), np.concatenate([c[go_l], c[go_r] + 1])
        if not out_b:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(out_b).astype(np.int64), np.concatenate(out_l).astype(np.int64)

    def locate(self, p: np.ndarray) -> np.ndarray:
        """Leaf index of each point (M, 3) (host; ties go right)."""
        node = np.zeros(len(p), dtype=np.int64)
        for _ in range(self.depth + 1):
            ax = self.axis[node]
            inner = ax < 3
            if not inner.any():
                break
            i = np.nonzero(inner)[0]
            go_right = p[i, ax[i]] >= self.split[node[i]]
            node[i] = self.child[node[i]] + go_right
        return self.child[node].astype(np.int64)


def build_region_tree(box_lo, box_hi, root_lo, root_hi, leaf_extent=None, memory_limit=None,
                      what: str = "region tree") -> RegionTree:
    """Build the tree over integer boxes ``[box_lo, box_hi]`` (K, 3) inside
    the root box; see the module docstring. ``leaf_extent`` (K,): a node
    whose longest side is at most the smallest ``leaf_extent`` of its boxes
    is a leaf even with faces inside (its list still holds every box that
    overlaps it). Before each depth's pairs are made, their bytes and the
    leaf lists so far are checked against ``memory_limit`` (an error names
    ``what``); the largest such estimate is kept as ``peak_estimate``.

    Built level by level, all nodes of a depth at once: the (node, box)
    pairs of the level, sorted by node, are the state. A node splits on its
    longest axis that has an input-box face strictly inside it, at the face
    nearest its middle (the smaller face on a tie); left takes the boxes
    starting below the plane, right those ending above it. Children are
    numbered consecutively (left, left + 1) after all nodes of the previous
    depths. Coordinates are int32 when they fit (halves the memory traffic).
    """
    span = max(np.abs(np.asarray(a, dtype=np.int64)).max(initial=0) for a in (box_lo, box_hi, root_lo, root_hi))
    ctype = np.int32 if 2 * span + 2 < 2**31 else np.int64
    box_lo = np.asarray(box_lo).astype(ctype)
    box_hi = np.asarray(box_hi).astype(ctype)
    root_lo = np.asarray(root_lo).astype(ctype)
    root_hi = np.asarray(root_hi).astype(ctype)
    axis, split, child = [None], [None], [None]
    leaf_nodes, leaf_lo, leaf_hi, leaf_pairs = [], [], [], []
    # frontier: node ids, boxes; pairs: (frontier index, input box), sorted by
    # frontier index and, within a node, by box
    ids = np.zeros(1, dtype=np.int64)
    lo, hi = root_lo[None].copy(), root_hi[None].copy()
    pb = np.nonzero(np.all((box_lo < root_hi) & (box_hi > root_lo), axis=1))[0]
    pn = np.zeros(len(pb), dtype=np.int64)
    n_nodes, n_leaves, depth = 1, 0, 0
    never = np.iinfo(np.int64).max
    stored, peak_estimate = 0, BYTES_PER_TREE_PAIR * len(pb)
    require(peak_estimate, what, memory_limit, "use fewer cells or raise the limit")
    bar = progress(None, "region tree", unit="node")
    while len(ids):
        F = len(ids)
        bar.update(F)
        # ---- Faces strictly inside each pair's node, per axis ----
        per_node = np.bincount(pn, minlength=F)
        nlo, nhi = np.repeat(lo, per_node, axis=0), np.repeat(hi, per_node, axis=0)
        blo, bhi = np.take(box_lo, pb, axis=0), np.take(box_hi, pb, axis=0)
        in_lo = (blo > nlo) & (blo < nhi)
        in_hi = (bhi > nlo) & (bhi < nhi)
        starts = np.flatnonzero(np.r_[True, pn[1:] != pn[:-1]]) if len(pn) else np.zeros(0, np.int64)
        has = np.zeros((F, 3), dtype=bool)
        if len(pn):
            has[pn[starts]] = np.logical_or.reduceat(in_lo | in_hi, starts, axis=0)
        # ---- Chosen axis: the longest with a face strictly inside ----
        order = np.argsort(-(hi - lo), axis=1, kind="stable")        # axes by extent, stable
        has_sorted = np.take_along_axis(has, order, axis=1)
        splits = has_sorted.any(axis=1)
        if leaf_extent is not None and len(pn):
            small = np.zeros(F, dtype=bool)
            small[pn[starts]] = (hi - lo)[pn[starts]].max(axis=1) <= np.minimum.reduceat(
                np.take(leaf_extent, pb), starts)
            splits &= ~small
        ax = np.where(splits, order[np.arange(F), np.argmax(has_sorted, axis=1)], 3)
        # ---- Chosen plane: the inside face nearest the middle, then the smaller ----
        best = np.zeros(F, dtype=np.int64)
        if len(pn):
            pa = ax[pn]
            ok = pa < 3
            pa = np.where(ok, pa, 0)[:, None]
            a_lo = np.take_along_axis(nlo, pa, 1)[:, 0].astype(np.int64)
            mid2 = a_lo + np.take_along_axis(nhi, pa, 1)[:, 0]           # twice the middle, exact
            key = np.full(len(pn), never)
            for faces, inside in ((blo, in_lo), (bhi, in_hi)):
                f = np.take_along_axis(faces, pa, 1)[:, 0].astype(np.int64)
                inn = ok & np.take_along_axis(inside, pa, 1)[:, 0]
                # (distance, face) compared as one integer: face - node lo < 2^32
                np.minimum(key, np.where(inn, (np.abs(2 * f - mid2) << 32) | (f - a_lo), never), out=key)
            k = np.minimum.reduceat(key, starts)
            node = pn[starts]
            good = k < never
            best[node[good]] = (k[good] & 0xFFFFFFFF) + lo[node[good], ax[node[good]]]
        # ---- Leaves ----
        leaf = ~splits
        if leaf.any():
            li = np.nonzero(leaf)[0]
            leaf_index = np.full(F, -1, dtype=np.int64)
            leaf_index[li] = n_leaves + np.arange(len(li))
            leaf_nodes.append(ids[li])
            leaf_lo.append(lo[li])
            leaf_hi.append(hi[li])
            sel = leaf[pn]
            leaf_pairs.append((leaf_index[pn[sel]], pb[sel]))
            stored += int(sel.sum())
            axis.append(np.full(len(li), 3, np.uint32))
            split.append(np.zeros(len(li)))
            child.append(leaf_index[li])
            n_leaves += len(li)
        # ---- Inner nodes and their children ----
        si = np.nonzero(splits)[0]
        if not len(si):
            break
        left = n_nodes + 2 * np.arange(len(si))
        axis.append(ax[si].astype(np.uint32))
        split.append(best[si].astype(np.float64))
        child.append(left)
        leaf_nodes.append(ids[si])                                   # (node ids of these rows)
        n_nodes += 2 * len(si)
        slot = np.full(F, -1, dtype=np.int64)
        slot[si] = np.arange(len(si))
        s_ax, s_pl = ax[si], best[si].astype(ctype)
        rows = np.arange(len(si))
        new_lo = np.repeat(lo[si], 2, axis=0)
        new_hi = np.repeat(hi[si], 2, axis=0)
        new_hi[2 * rows, s_ax] = s_pl                                # left child ends at the plane
        new_lo[2 * rows + 1, s_ax] = s_pl                            # right child starts there
        keep = np.flatnonzero(splits[pn])
        pn_k, pb_k = slot[pn[keep]], pb[keep]
        a_k, s_k = s_ax[pn_k], s_pl[pn_k]
        to_left = np.take(box_lo.ravel(), 3 * pb_k + a_k) < s_k
        to_right = np.take(box_hi.ravel(), 3 * pb_k + a_k) > s_k
        need = (BYTES_PER_TREE_PAIR * float(to_left.sum() + to_right.sum()) + BYTES_PER_TREE_ITEM * stored
                + BYTES_PER_TREE_NODE * float(n_nodes))
        peak_estimate = max(peak_estimate, need)
        require(need, what, memory_limit, "use fewer cells or raise the limit")
        pn = np.concatenate([2 * pn_k[to_left], 2 * pn_k[to_right] + 1])
        pb = np.concatenate([pb_k[to_left], pb_k[to_right]])
        o = np.argsort(pn, kind="stable")
        pn, pb = pn[o], pb[o]
        ids, lo, hi = left.repeat(2) + np.tile([0, 1], len(si)), new_lo, new_hi
        depth += 1
    bar.close()
    # ---- Node arrays in node-id order (row 0 of the lists is a placeholder) ----
    node_ids = np.concatenate(leaf_nodes)
    ax_n = np.full(n_nodes, 3, np.uint32)
    sp_n = np.zeros(n_nodes)
    ch_n = np.zeros(n_nodes, np.int64)
    ax_n[node_ids] = np.concatenate(axis[1:])
    sp_n[node_ids] = np.concatenate(split[1:])
    ch_n[node_ids] = np.concatenate(child[1:])
    leaf_lo = np.concatenate(leaf_lo) if leaf_lo else np.zeros((0, 3))
    leaf_hi = np.concatenate(leaf_hi) if leaf_hi else np.zeros((0, 3))
    li = np.concatenate([p[0] for p in leaf_pairs]) if leaf_pairs else np.zeros(0, np.int64)
    bi = np.concatenate([p[1] for p in leaf_pairs]) if leaf_pairs else np.zeros(0, np.int64)
    # leaves are numbered in the order their pairs were appended, and a
    # node's boxes stay in ascending order through every split: no sort
    lists = (np.bincount(li, minlength=n_leaves), bi)
    tree = RegionTree(ax_n, sp_n, ch_n, leaf_lo, leaf_hi, lists, depth)
    tree.peak_estimate = peak_estimate
    return tree


def brick_region_tree(bricks, lo, hi, over_domains: bool, leaf_cells: int | None = None,
                      memory_limit=None, what: str = "region tree", method: Reconstruction = DEFAULT_METHOD) -> RegionTree:
    """The region tree of ``bricks`` over the data bounds ``[lo, hi]``
    (finest units): over the brick domains (``over_domains``: the ABRs of
    ``tent``), leaves not split below ``leaf_cells`` cells of the finest
    brick in them (default `ABR_LEAF_CELLS`; 0: exact ABRs), or over the
    disjoint brick bounds (the brick tree, and the ABRs of ``nearest``). Tree units: finest cells
    times two. ``memory_limit``, ``what``: see `build_region_tree`."""
    leaf_cells = ABR_LEAF_CELLS if leaf_cells is None else leaf_cells
    if over_domains:
        blo, bhi = bricks.domains(method)
        floor = 2 * leaf_cells * bricks.width if leaf_cells else None
    else:
        blo, bhi, floor = bricks.lo.astype(np.float64), bricks.hi.astype(np.float64), None
    # in half cells, grown outwards where a support does not end on one
    return build_region_tree(np.floor(2 * blo).astype(np.int64), np.ceil(2 * bhi).astype(np.int64),
                             2 * np.asarray(lo), 2 * np.asarray(hi), floor, memory_limit, what)


def split_node(axis: list, split: list, child: list, node: int, a: int, s, lo, hi):
    """Turn leaf ``node`` into an inner node split at ``s`` on axis ``a``:
    appends its two children (leaves for now) to the node lists and returns
    ``(left_index, (left_lo, left_hi), (right_lo, right_hi))``."""
    left = len(axis)
    axis[node], split[node], child[node] = a, float(s), left
    axis += [3, 3]
    split += [0.0, 0.0]
    child += [0, 0]
    lhi = hi.copy()
    lhi[a] = s
    rlo = lo.copy()
    rlo[a] = s
    return left, (lo, lhi), (rlo, hi)


def box_value_ranges(leaf_lo, leaf_hi, dom_lo, dom_hi, vmin, vmax, chunk: int = 512):
    """Value range of each leaf box: min/max over the input boxes (domains,
    with per-box ranges ``vmin``/``vmax``) that overlap it, closed intervals.
    Empty leaves get ``(+inf, -inf)``."""
    n = len(leaf_lo)
    out_min = np.full(n, np.inf, dtype=np.float32)
    out_max = np.full(n, -np.inf, dtype=np.float32)
    order = np.argsort(dom_lo[:, 0], kind="stable")
    dlo, dhi = dom_lo[order], dom_hi[order]
    bmin, bmax = vmin[order], vmax[order]
    for s in range(0, n, chunk):
        llo, lhi = leaf_lo[s:s + chunk], leaf_hi[s:s + chunk]
        # restrict to domains whose x-interval can overlap the chunk
        a = np.searchsorted(dlo[:, 0], lhi[:, 0].max(), side="right")
        sel = np.nonzero(dhi[:a, 0] >= llo[:, 0].min())[0]
        if not len(sel):
            continue
        ov = np.all((dlo[sel][None] <= lhi[:, None]) & (dhi[sel][None] >= llo[:, None]), axis=2)
        li, bi = np.nonzero(ov)
        np.minimum.at(out_min, s + li, bmin[sel][bi])
        np.maximum.at(out_max, s + li, bmax[sel][bi])
    return out_min, out_max


def _depth(axis, child) -> int:
    depth = np.zeros(len(axis), dtype=np.int64)
    best = 0
    for n in range(len(axis)):            # children always follow their parent
        if axis[n] < 3:
            c = int(child[n])
            depth[c] = depth[c + 1] = depth[n] + 1
            best = max(best, depth[n] + 1)
    return int(best)


def exact_value_ranges(tree: RegionTree, bricks, method: Reconstruction = DEFAULT_METHOD, own_lists: bool = False,
                       chunk: int = 1 << 22):
    """Exact value range of each leaf of ``tree`` (built over boxes in
    doubled finest units): min/max over the cells whose support box
    (`Reconstruction.support_box` of ``method``: the tent support for
    ``tent``, the cell box for ``nearest``) overlaps the leaf's interior.
    Candidate bricks are those whose domain overlaps the leaf: the leaves'
    own lists when the tree was built over the supports of ``method``
    (``own_lists``: the brick domains for ``tent``, the ABRs; the brick
    bounds for ``nearest``, where a cell reaches only its own brick), else a
    box query of each domain down the tree (`RegionTree.overlapping_leaves`).
    The (leaf, brick) pairs are folded by one Dr.Jit kernel per chunk, in
    the current variant, on every core: a brick whose cells all reach the
    leaf gives its own range, of the others only the sub-box of cells that
    reach the leaf is read."""
    below, above = _support_half_cells(method)
    n = tree.n_leaves
    li, b = _leaf_brick_pairs(tree, bricks, method, own_lists)
    values = device_values(bricks.volume)
    Float = type(values)
    Int64, Int32, UInt32 = dr.int64_array_t(Float), dr.int32_array_t(Float), dr.uint32_array_t(Float)
    dev = {
        "leaf_lo": [Int64(tree.leaf_lo[:, a].astype(np.int64)) for a in range(3)],   # doubled units
        "leaf_hi": [Int64(tree.leaf_hi[:, a].astype(np.int64)) for a in range(3)],
        "lo": [Int64(2 * bricks.lo[:, a]) for a in range(3)],
        "dims": [Int32(bricks.dims[:, a].astype(np.int32)) for a in range(3)],
        "level": Int32(bricks.level.astype(np.int32)),
        "offset": UInt32(bricks.offset.astype(np.uint32)),
        "vmin": Float(bricks.vmin), "vmax": Float(bricks.vmax), "values": values,
        "block": int(bricks.stride[1]),
        "ext": (above, below),          # support reach above / below a cell's lower corner, half cells
    }
    # ranges are folded as order-preserving integer keys of the float values:
    # integer min/max atomics exist on every backend and GPU
    out_min = dr.full(UInt32, int(_order_keys(np.float32(np.inf))), n)
    out_max = dr.full(UInt32, int(_order_keys(np.float32(-np.inf))), n)
    with progress(len(li), "leaf value ranges", unit="pair") as bar:
        for s in range(0, len(li), chunk):
            _fold_pairs(UInt32(np.ascontiguousarray(li[s:s + chunk], dtype=np.uint32)),
                        UInt32(np.ascontiguousarray(b[s:s + chunk], dtype=np.uint32)), dev, out_min, out_max)
            dr.eval(out_min, out_max)
            bar.update(len(li[s:s + chunk]))
    return _from_order_keys(out_min.numpy()), _from_order_keys(out_max.numpy())


def _leaf_brick_pairs(tree: RegionTree, bricks, method, own_lists: bool):
    """``(leaf, brick)`` index arrays of the bricks whose domain under
    ``method`` overlaps each leaf (`exact_value_ranges` says when the
    leaves' own lists are those)."""
    if own_lists:
        return np.repeat(np.arange(tree.n_leaves, dtype=np.uint32), tree.list_count), tree.items
    dlo, dhi = bricks.domains(method)
    b, li = tree.overlapping_leaves(np.floor(2 * dlo).astype(np.int64), np.ceil(2 * dhi).astype(np.int64))
    return li, b


def finest_levels(tree: RegionTree, bricks, method: Reconstruction = DEFAULT_METHOD,
                  own_lists: bool = False) -> np.ndarray:
    """The finest level whose cells' supports reach each leaf (uint32 per
    leaf; `NO_LEVEL` where none does): the ray marcher's step under the leaf
    (docs/design.md section 14). The candidate bricks are those of
    `exact_value_ranges`, so a leaf's level is never coarser than a cell
    that reaches it."""
    li, b = _leaf_brick_pairs(tree, bricks, method, own_lists)
    out = np.full(tree.n_leaves, NO_LEVEL, np.int64)
    np.minimum.at(out, np.asarray(li, np.int64), bricks.level[np.asarray(b, np.int64)].astype(np.int64))
    return out.astype(np.uint32)


def _support_half_cells(method) -> tuple[int, int]:
    """How far a cell's support reaches below and above its lower corner,
    in half cells (the region trees count in doubled finest units)."""
    a, b = method.support_box(0.0, 2.0)             # a cell of two units at 0
    if a != round(a) or b != round(b):
        raise ValueError(f"reconstruction {method}: support radius {method.support_radius} "
                         "is not a multiple of half a cell")
    return -int(round(a)), int(round(b))


def _order_keys(v):
    """uint32 keys of float32 values that sort as the values do (numpy, or
    a Dr.Jit Float): the sign bit set for positives, all bits flipped for
    negatives."""
    if isinstance(v, (np.ndarray, np.floating)):
        bits = np.asarray(v, np.float32).view(np.uint32)
        return np.where(bits >> 31 != 0, ~bits, bits | np.uint32(0x80000000)).astype(np.uint32)
    bits = dr.reinterpret_array(dr.uint32_array_t(type(v)), v)
    return dr.select((bits >> 31) != 0, ~bits, bits | 0x80000000)


def _from_order_keys(k: np.ndarray) -> np.ndarray:
    """The float32 values of `_order_keys` keys (numpy)."""
    k = np.asarray(k, np.uint32)
    return np.where(k >> 31 != 0, k & np.uint32(0x7FFFFFFF), ~k).astype(np.uint32).view(np.float32)


@dr.syntax
def _fold_pairs(li, b, dev, out_min, out_max):
    """Fold the cells of brick ``b[k]`` that reach leaf ``li[k]`` into the
    leaf's range: with ``(e0, e1) = ext``, the reach of a cell's support
    above and below its lower corner in half cells, cells ``i`` with
    ``lo + (i - e1/2) w < leaf_hi`` and ``lo + (i + e0/2) w > leaf_lo``
    (``w = 2^level``; in doubled units, by integer shifts)."""
    Float, Int64, Int32 = type(dev["values"]), type(dev["lo"][0]), type(dev["level"])
    UInt32 = type(li)
    level = Int64(dr.gather(Int32, dev["level"], b))
    shift, w = level + 1, Int64(1) << level
    e0, e1 = dev["ext"]
    i0, size = [], []
    whole = dr.full(dr.mask_t(Float), True, dr.width(b))
    count = Int32(1)
    for a in range(3):
        lo2 = dr.gather(Int64, dev["lo"][a], b)
        dims = dr.gather(Int32, dev["dims"][a], b)
        a0 = Int32(dr.maximum(((dr.gather(Int64, dev["leaf_lo"][a], li) - lo2 - e0 * w) >> shift) + 1, 0))
        a1 = Int32(dr.minimum(-((lo2 - dr.gather(Int64, dev["leaf_hi"][a], li) - e1 * w) >> shift) - 1,
                              Int64(dims) - 1))
        whole &= (a0 == 0) & (a1 == dims - 1)
        i0.append(a0)
        size.append(dr.maximum(a1 - a0 + 1, 0))
        count *= size[-1]
    dr.scatter_reduce(dr.ReduceOp.Min, out_min, _order_keys(dr.gather(Float, dev["vmin"], b, whole)), li, whole)
    dr.scatter_reduce(dr.ReduceOp.Max, out_max, _order_keys(dr.gather(Float, dev["vmax"], b, whole)), li, whole)
    count = dr.select(whole, 0, count)
    off = dr.gather(UInt32, dev["offset"], b)
    B = dev["block"]
    nx, ny = dr.maximum(size[0], 1), dr.maximum(size[1], 1)      # no division by 0 in idle lanes
    k = Int32(0)
    while k < count:
        t = k // nx
        x, y, z = i0[0] + (k - t * nx), i0[1] + t % ny, i0[2] + t // ny
        v = _order_keys(dr.gather(Float, dev["values"], off + UInt32(x + B * (y + B * z))))
        dr.scatter_reduce(dr.ReduceOp.Min, out_min, v, li)
        dr.scatter_reduce(dr.ReduceOp.Max, out_max, v, li)
        k += 1
