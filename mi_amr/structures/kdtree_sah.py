"""A pre-classified SAH kd-tree over the macrocell grid (the paper's
non-interactive reference structure).

Built for one transfer function: leaves are boxes of macrocells, split with
a binned surface-area heuristic whose cost of a leaf is

    C(leaf) = c_trav * SA(leaf) + mu_max(leaf) * V(leaf)

(rays hit a leaf with probability proportional to its surface area and then
take ``mu * chord`` density look-ups; ``SA * mean chord = V``). A priority
queue always splits the most expensive leaf, at the binned plane that
minimises the children's summed cost, until ``max_leaves`` leaves exist or
every leaf is one macrocell. (Splitting only on a positive cost reduction
stalls: with range majorants both halves of a region often keep the same
maximum until the boxes are small.) Leaves keep the min/max value
range of their macrocells, so majorants stay valid for any TF; the topology
is only good for the TF it was built with, and is rebuilt when it changes.
"""

from __future__ import annotations

import heapq

import numpy as np

from ..progress import progress
from .region_tree import RegionTree, split_node


def build_sah_kdtree(majorant: np.ndarray, vmin: np.ndarray, vmax: np.ndarray,
                     max_leaves: int = 4096, c_trav: float = 0.05):
    """Build from per-macrocell arrays indexed ``[x, y, z]`` (local units:
    the grid spans the unit cube, ``majorant`` in inverse local units).

    Returns ``(tree, leaf_vmin, leaf_vmax)`` with leaf boxes and splits in
    macrocell units.
    """
    res = np.array(majorant.shape, dtype=np.int64)
    cell = 1.0 / res

    def cost(lo, hi, mu):
        e = (hi - lo) * cell
        sa = 2 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2])
        return c_trav * sa + mu * e.prod()

    def best_split(lo, hi):
        sub = majorant[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        mu = float(sub.max())
        parent = cost(lo, hi, mu)
        best = (None, None, None)
        for a in range(3):
            n = hi[a] - lo[a]
            if n < 2:
                continue
            other = tuple(i for i in range(3) if i != a)
            slab = sub.max(axis=other)                      # max per slab along a
            left = np.maximum.accumulate(slab)[:-1]
            right = np.maximum.accumulate(slab[::-1])[::-1][1:]
            e = (hi - lo) * cell
            k = np.arange(1, n)
            ea = k * cell[a]
            er_a = (n - k) * cell[a]
            o0, o1 = e[other[0]], e[other[1]]
            sa_l = 2 * (ea * o0 + ea * o1 + o0 * o1)
            sa_r = 2 * (er_a * o0 + er_a * o1 + o0 * o1)
            c = (c_trav * (sa_l + sa_r) + left * ea * o0 * o1 + right * er_a * o0 * o1)
            i = int(np.argmin(c))
            if best[0] is None or c[i] < best[0]:
                best = (float(c[i]), a, int(lo[a] + k[i]))
        return parent, best[1], best[2]

    root = (np.zeros(3, np.int64), res.copy())
    nodes = {0: root}
    axis, split, child = [3], [0.0], [0]
    heap = []
    g, a, s = best_split(*root)
    if a is not None:
        heapq.heappush(heap, (-g, 0, a, s))        # most expensive leaf first
    n_leaves = 1
    bar = progress(max_leaves, "SAH kd-tree", unit="leaf")
    while heap and n_leaves < max_leaves:
        bar.update(1)
        _, node, a, s = heapq.heappop(heap)
        lo, hi = nodes.pop(node)
        left, lbox, rbox = split_node(axis, split, child, node, a, s, lo, hi)
        for nid, box in ((left, lbox), (left + 1, rbox)):
            nodes[nid] = box
            g, ax, sp = best_split(*box)
            if ax is not None:
                heapq.heappush(heap, (-g, nid, ax, sp))
        n_leaves += 1
    bar.close()
    leaf_ids = sorted(nodes)
    leaf_lo, leaf_hi, lists, lmin, lmax = [], [], [], [], []
    for k, nid in enumerate(leaf_ids):
        lo, hi = nodes[nid]
        child[nid] = k
        leaf_lo.append(lo)
        leaf_hi.append(hi)
        lists.append(np.zeros(0, np.int64))
        lmin.append(vmin[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].min())
        lmax.append(vmax[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].max())
    tree = RegionTree(axis, split, child, leaf_lo, leaf_hi, lists)
    return tree, np.array(lmin, np.float32), np.array(lmax, np.float32)
