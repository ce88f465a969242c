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


class RegionTree:
    """A kd-tree built by `build_region_tree` (host, numpy).

    Nodes: ``axis`` (0-2, or 3 for a leaf), ``split`` (the plane, same units
    as the boxes), ``child`` (index of the left child, right = left + 1; for a
    leaf, the leaf index). Leaves: ``leaf_lo``/``leaf_hi`` (L, 3) and a CSR
    list of input box ids (``list_offset``, ``list_count``, ``items``).
    """

    def __init__(self, axis, split, child, leaf_lo, leaf_hi, lists):
        self.axis = np.asarray(axis, dtype=np.uint32)
        self.split = np.asarray(split, dtype=np.float64)
        self.child = np.asarray(child, dtype=np.uint32)
        self.leaf_lo = np.asarray(leaf_lo, dtype=np.float64).reshape(-1, 3)
        self.leaf_hi = np.asarray(leaf_hi, dtype=np.float64).reshape(-1, 3)
        self.list_count = np.array([len(x) for x in lists], dtype=np.uint32)
        self.list_offset = np.concatenate([[0], np.cumsum(self.list_count)[:-1]]).astype(np.uint32)
        self.items = (np.concatenate(lists) if len(lists) else np.zeros(0)).astype(np.uint32)
        self.depth = _depth(self.axis, self.child)

    @property
    def n_leaves(self) -> int:
        return len(self.leaf_lo)

    @property
    def nbytes(self) -> int:
        return (self.axis.nbytes + 4 * len(self.split) + self.child.nbytes
                + 4 * 6 * self.n_leaves + self.list_count.nbytes * 2 + self.items.nbytes)

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
    the root box; see the module docstring."""
    box_lo = np.asarray(box_lo, dtype=np.int64)
    box_hi = np.asarray(box_hi, dtype=np.int64)
    axis, split, child = [3], [0.0], [0]
    leaf_lo, leaf_hi, lists = [], [], []
    root_lo = np.asarray(root_lo, dtype=np.int64)
    root_hi = np.asarray(root_hi, dtype=np.int64)
    cand0 = np.nonzero(np.all((box_lo < root_hi) & (box_hi > root_lo), axis=1))[0]
    stack = [(0, root_lo, root_hi, cand0)]
    while stack:
        node, lo, hi, cand = stack.pop()
        best = None
        if len(cand):
            # a face strictly inside the node, on its longest axis that has
            # one, nearest to the middle (balanced, shallow trees)
            blo, bhi = box_lo[cand], box_hi[cand]
            for a in np.argsort(-(hi - lo), kind="stable"):
                faces = np.concatenate([blo[:, a], bhi[:, a]])
                faces = faces[(faces > lo[a]) & (faces < hi[a])]
                if len(faces):
                    mid = 0.5 * (lo[a] + hi[a])
                    best = (int(a), int(faces[np.argmin(np.abs(faces - mid))]))
                    break
        if best is None:
            axis[node], child[node] = 3, len(leaf_lo)
            leaf_lo.append(lo)
            leaf_hi.append(hi)
            lists.append(cand)
            continue
        a, s = best
        left, (llo, lhi), (rlo, rhi) = split_node(axis, split, child, node, a, s, lo, hi)
        cl = cand[box_lo[cand, a] < s]
        cr = cand[box_hi[cand, a] > s]
        stack.append((left + 1, rlo, rhi, cr))
        stack.append((left, llo, lhi, cl))
    return RegionTree(axis, split, child, leaf_lo, leaf_hi, lists)


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


def exact_value_ranges(leaf_lo, leaf_hi, bricks, method: str = "tent", chunk: int = 4096):
    """Exact value range of each leaf box (finest units): min/max over the
    cells whose tent support (``tent``) or cell box (``nearest``) overlaps
    the leaf's interior. Candidate bricks come from a conservative domain
    test; within each brick only the sub-box of cells that reach the leaf
    is visited (vectorised over all leaf-brick pairs)."""
    from .boxes import enumerate_boxes
    n = len(leaf_lo)
    out_min = np.full(n, np.inf, dtype=np.float32)
    out_max = np.full(n, -np.inf, dtype=np.float32)
    dlo, dhi = bricks.domains()
    order = np.argsort(dlo[:, 0], kind="stable")
    w_all = bricks.width.astype(np.float64)
    ext = (1.5, 0.5) if method == "tent" else (1.0, 0.0)    # support reach below / above, in cells
    for s in range(0, n, chunk):
        llo, lhi = leaf_lo[s:s + chunk], leaf_hi[s:s + chunk]
        a = np.searchsorted(dlo[order, 0], lhi[:, 0].max(), side="right")
        sel = order[:a][dhi[order[:a], 0] >= llo[:, 0].min()]
        if not len(sel):
            continue
        ov = np.all((dlo[sel][None] <= lhi[:, None]) & (dhi[sel][None] >= llo[:, None]), axis=2)
        li, bj = np.nonzero(ov)
        b = sel[bj]
        w = w_all[b][:, None]
        lo = bricks.lo[b].astype(np.float64)
        dims = bricks.dims[b]
        i0 = np.floor((llo[li] - lo) / w - ext[0]).astype(np.int64) + 1
        i1 = np.ceil((lhi[li] - lo) / w + ext[1]).astype(np.int64) - 1
        i0 = np.maximum(i0, 0)
        i1 = np.minimum(i1, dims - 1)
        keep = np.all(i0 <= i1, axis=1)
        li, b, i0, i1, dims = li[keep], b[keep], i0[keep], i1[keep], dims[keep]
        if not len(li):
            continue
        x, y, z, owner = enumerate_boxes(i0, i1)      # every (pair, cell) of the sub-boxes
        d = dims[owner]
        v = bricks.values[bricks.offset[b[owner]] + x + d[:, 0] * (y + d[:, 1] * z)]
        np.minimum.at(out_min, s + li[owner], v)
        np.maximum.at(out_max, s + li[owner], v)
    return out_min, out_max
