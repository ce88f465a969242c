"""kd-trees whose leaves are boxes with a constant list of overlapping boxes.

`build_region_tree` splits a root box at faces of the input boxes that lie
strictly inside a node, until no face is left inside: every leaf then
overlaps a fixed set of input boxes, each of which covers the leaf
completely. Over brick *domains* the leaves are the active brick regions
(ABRs); over brick *bounds* (which do not overlap) each leaf lies in at most
one brick. The leaves partition the root box.

Coordinates are exact: the caller passes integer boxes (finest units times
two, so that domain faces at half cells stay integers).
"""

from __future__ import annotations

import numpy as np

from ..progress import progress


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
        """``(box, leaf)`` index pairs of boxes (K, 3), in the tree's units,
        and the leaves they overlap (closed intervals), found by descending
        all boxes through the tree together, one depth at a time."""
        box_lo, box_hi = np.asarray(box_lo, np.float64), np.asarray(box_hi, np.float64)
        flat_lo, flat_hi = box_lo.ravel(), box_hi.ravel()
        axis, split, child = self.axis.astype(np.int64), self.split, self.child.astype(np.int64)
        bi = np.arange(len(box_lo))
        node = np.zeros(len(box_lo), dtype=np.int64)
        out_b, out_l = [], []
        while len(bi):
            ax = np.take(axis, node)
            leaf = ax == 3
            if leaf.any():
                lb, ln = bi[leaf], np.take(child, node[leaf])
                ok = np.all((np.take(box_lo, lb, axis=0) <= np.take(self.leaf_hi, ln, axis=0))
                            & (np.take(box_hi, lb, axis=0) >= np.take(self.leaf_lo, ln, axis=0)), axis=1)
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
        return np.concatenate(out_b), np.concatenate(out_l)

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


def build_region_tree(box_lo, box_hi, root_lo, root_hi) -> RegionTree:
    """Build the tree over integer boxes ``[box_lo, box_hi]`` (K, 3) inside
    the root box; see the module docstring.

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
    return RegionTree(ax_n, sp_n, ch_n, leaf_lo, leaf_hi, lists, depth)


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


def exact_value_ranges(tree: RegionTree, bricks, method: str = "tent", own_lists: bool = False,
                       chunk: int = 1 << 20):
    """Exact value range of each leaf of ``tree`` (built over boxes in
    doubled finest units): min/max over the cells whose tent support
    (``tent``) or cell box (``nearest``) overlaps the leaf's interior.
    Candidate bricks are those whose domain overlaps the leaf: the leaves'
    own lists when the tree was built over the brick domains
    (``own_lists``, ABRs), else a box query of each domain down the tree
    (`RegionTree.overlapping_leaves`). Within each brick only the sub-box
    of cells that reach the leaf is visited (vectorised over all pairs)."""
    from .boxes import enumerate_boxes
    n = tree.n_leaves
    leaf_lo, leaf_hi = tree.leaf_lo / 2, tree.leaf_hi / 2
    out_min = np.full(n, np.inf, dtype=np.float32)
    out_max = np.full(n, -np.inf, dtype=np.float32)
    dlo, dhi = bricks.domains()
    w_all = bricks.width.astype(np.float64)
    ext = (1.5, 0.5) if method == "tent" else (1.0, 0.0)    # support reach below / above, in cells
    if own_lists:
        li, b = np.repeat(np.arange(n), tree.list_count), tree.items.astype(np.int64)
    else:
        b, li = tree.overlapping_leaves(2 * dlo, 2 * dhi)
    with progress(len(li), "leaf value ranges", unit="pair") as bar:
        for s in range(0, len(li), chunk):
            _fold_pairs(li[s:s + chunk], b[s:s + chunk], leaf_lo, leaf_hi, bricks, w_all, ext,
                        out_min, out_max, enumerate_boxes)
            bar.update(len(li[s:s + chunk]))
    return out_min, out_max


def _fold_pairs(li, b, leaf_lo, leaf_hi, bricks, w_all, ext, out_min, out_max, enumerate_boxes):
    """Fold the cells of brick ``b[k]`` that reach leaf ``li[k]`` into its range."""
    w = np.take(w_all, b)[:, None]
    lo = np.take(bricks.lo, b, axis=0).astype(np.float64)
    dims = np.take(bricks.dims, b, axis=0)
    i0 = np.floor((np.take(leaf_lo, li, axis=0) - lo) / w - ext[0]).astype(np.int64) + 1
    i1 = np.ceil((np.take(leaf_hi, li, axis=0) - lo) / w + ext[1]).astype(np.int64) - 1
    i0 = np.maximum(i0, 0)
    i1 = np.minimum(i1, dims - 1)
    keep = np.all(i0 <= i1, axis=1)
    li, b, i0, i1, dims = li[keep], b[keep], i0[keep], i1[keep], dims[keep]
    if not len(li):
        return
    x, y, z, owner = enumerate_boxes(i0, i1)      # every (pair, cell) of the sub-boxes
    # value index = offset + x + dx (y + dy z), with per-pair strides
    sy, sz, base = dims[:, 0], dims[:, 0] * dims[:, 1], np.take(bricks.offset, b)
    v = np.take(bricks.values, np.take(base, owner) + x + np.take(sy, owner) * y + np.take(sz, owner) * z)
    leaf = np.take(li, owner)
    np.minimum.at(out_min, leaf, v)
    np.maximum.at(out_max, leaf, v)
