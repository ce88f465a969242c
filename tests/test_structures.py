"""Builders of the ExaBricks family against brute-force oracles."""

import mitsuba as mi
import numpy as np
import pytest

from mi_amr.structures.brick_lists import BrickLists
from mi_amr.device.bricks import BrickSampler, DeviceBrickLists, DeviceBricks
from mi_amr.structures.bricks import Bricks
from mi_amr.data.datasets import make_dataset
from mi_amr.data.volume import as_method, as_volume
from mi_amr.structures.kdtree_sah import build_sah_kdtree
from mi_amr.testing import brute_force
from mi_amr.structures.region_tree import (ABR_LEAF_CELLS, box_value_ranges, brick_region_tree, build_region_tree,
                                          exact_value_ranges)
from mi_amr.device.tree import DeviceTree

from conftest import random_amr


@pytest.fixture(scope="module", params=[0, 1])
def data(request):
    if request.param == 0:
        return random_amr(31, n=16, levels=4, quantize=5)
    return make_dataset("shell", cells=1500, seed=2)


def test01_bricks_are_complete_same_level_boxes(data):
    volume = as_volume(data)
    b = Bricks(volume, max_width=4)
    assert b.dims.prod(axis=1).sum() == len(data)
    assert np.all(b.dims <= 4)
    cells = {(tuple(p), int(l)): float(v) for p, l, v in zip(data.pos.tolist(), data.level, data.value)}
    seen = set()
    for i in range(len(b)):
        w = int(b.width[i])
        nx, ny, nz = b.dims[i]
        zz, yy, xx = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
        pos = b.lo[i] + np.stack([xx.ravel(), yy.ravel(), zz.ravel()], 1) * w
        vals = b.values[b.cell_index(i, xx.ravel(), yy.ravel(), zz.ravel())]
        for p, v in zip(pos.tolist(), vals):
            key = (tuple(p), int(b.level[i]))
            assert cells[key] == v            # every brick cell exists, same level, same value
            assert key not in seen            # and belongs to one brick only
            seen.add(key)
    assert len(seen) == len(data)


@pytest.mark.parametrize("max_width", [8, 3])
def test01b_bricks_read_the_volume_in_place(max_width):
    """Bricks cut from blocks (full blocks cut evenly, partial ones split)
    stay inside one block, cover every cell once and carry their own min/max;
    they keep no copy of the values."""
    from mi_amr.data.blocks import BlockVolume
    cells = make_dataset("blocks", cells=6000, seed=4)
    vol = BlockVolume.from_cells(cells, block=8)
    b = Bricks(vol, max_width=max_width)
    assert b.values is vol.values
    assert np.all(b.dims <= min(max_width, vol.block))
    B = vol.block
    blk, local = np.divmod(b.offset, B ** 3)
    corner = np.stack([local % B, (local // B) % B, local // B ** 2], 1)
    assert np.all(corner + b.dims <= B)                               # inside one block
    assert np.array_equal(b.level, vol.level[blk])
    want = ((vol.coord[blk].astype(np.int64) * B + corner) << b.level[:, None].astype(np.int64)) + vol.origin
    assert np.array_equal(b.lo, want)
    seen = np.zeros(len(vol.values), np.int64)
    for i in range(len(b)):
        nx, ny, nz = b.dims[i]
        zz, yy, xx = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
        idx = b.cell_index(i, xx.ravel(), yy.ravel(), zz.ravel())
        seen[idx] += 1
        assert b.vmin[i] == np.min(vol.values[idx]) and b.vmax[i] == np.max(vol.values[idx])
    assert np.array_equal(seen, (~np.isnan(vol.values)).astype(np.int64))   # every cell once, no holes
    assert b.nbytes < 8 * len(vol)                                    # headers only


def test02_abrs_partition_space_with_exact_brick_lists(data):
    volume = as_volume(data)
    b = Bricks(volume)
    dlo, dhi = b.domains()
    lo, hi = data.bounds
    tree = build_region_tree(np.round(2 * dlo).astype(np.int64), np.round(2 * dhi).astype(np.int64), 2 * lo, 2 * hi)
    # partition: leaf volumes add up to the root, and random points lie in exactly one leaf
    vol = np.prod(tree.leaf_hi - tree.leaf_lo, axis=1)
    assert vol.sum() == np.prod(2 * (hi - lo))
    rng = np.random.default_rng(0)
    p = 2 * lo + rng.random((3000, 3)) * 2 * (hi - lo)
    inside = np.all((p[:, None] > tree.leaf_lo[None]) & (p[:, None] < tree.leaf_hi[None]), axis=2)
    assert np.all(inside.sum(axis=1) == 1)
    assert np.array_equal(np.argmax(inside, axis=1), tree.locate(p))
    # each leaf's list is exactly the bricks whose domain overlaps it
    for L in range(tree.n_leaves):
        ov = np.nonzero(np.all((2 * dlo < tree.leaf_hi[L]) & (2 * dhi > tree.leaf_lo[L]), axis=1))[0]
        got = tree.items[tree.list_offset[L]:tree.list_offset[L] + tree.list_count[L]]
        assert np.array_equal(np.sort(got), ov)


def test02b_abr_leaf_floor_keeps_lists_complete(data):
    """With a leaf floor (no split once a node's longest side is at most
    ``leaf_extent`` of the boxes in it) the leaves still partition the box,
    every leaf lists exactly the domains overlapping it, and only leaves at
    or under the floor keep a face inside."""
    volume = as_volume(data)
    b = Bricks(volume)
    dlo, dhi = b.domains()
    lo, hi = data.bounds
    floor = 2 * 2 * b.width                       # two cells of each brick, in doubled units
    tree = build_region_tree(np.round(2 * dlo).astype(np.int64), np.round(2 * dhi).astype(np.int64),
                             2 * lo, 2 * hi, floor)
    exact = build_region_tree(np.round(2 * dlo).astype(np.int64), np.round(2 * dhi).astype(np.int64), 2 * lo, 2 * hi)
    assert tree.n_leaves < exact.n_leaves
    vol = np.prod(tree.leaf_hi - tree.leaf_lo, axis=1)
    assert vol.sum() == np.prod(2 * (hi - lo))
    for L in range(tree.n_leaves):
        llo, lhi = tree.leaf_lo[L], tree.leaf_hi[L]
        ov = np.nonzero(np.all((2 * dlo < lhi) & (2 * dhi > llo), axis=1))[0]
        got = tree.items[tree.list_offset[L]:tree.list_offset[L] + tree.list_count[L]]
        assert np.array_equal(np.sort(got), ov)
        faces = np.concatenate([2 * dlo[ov], 2 * dhi[ov]])
        if np.any((faces > llo) & (faces < lhi)):
            assert np.max(lhi - llo) <= floor[ov].min()


@pytest.mark.parametrize("method", ["tent", "nearest"])
def test03_leaf_ranges_contain_reconstructed_values(variant, data, method):
    volume = as_volume(data)
    b = Bricks(volume)
    dlo, dhi = b.domains()
    lo, hi = data.bounds
    rng = np.random.default_rng(1)
    x = lo + rng.random((20000, 3)) * (hi - lo)
    val, found = brute_force(data, x, method)
    for boxes in ((dlo, dhi), (b.lo.astype(float), b.hi.astype(float))):
        tree = build_region_tree(np.round(2 * boxes[0]).astype(np.int64), np.round(2 * boxes[1]).astype(np.int64),
                                 2 * lo, 2 * hi)
        leaf = tree.locate(2 * x)
        exact = exact_value_ranges(tree, b, as_method(method))
        # over the method's supports (ABRs), the leaves' own brick lists give the same ranges
        if (boxes[0] is dlo) == (method == "tent"):
            own = exact_value_ranges(tree, b, as_method(method), own_lists=True)
            np.testing.assert_array_equal(own[0], exact[0])
            np.testing.assert_array_equal(own[1], exact[1])
        for vmin, vmax in (box_value_ranges(tree.leaf_lo / 2, tree.leaf_hi / 2, dlo, dhi, b.vmin, b.vmax), exact):
            assert np.all(vmin[leaf][found] <= val[found] + 1e-6)
            assert np.all(vmax[leaf][found] >= val[found] - 1e-6)


@pytest.mark.parametrize("mode", ["abr", "brick"])
@pytest.mark.parametrize("method", ["tent", "nearest"])
@pytest.mark.parametrize("leaf_cells", [0, ABR_LEAF_CELLS])
def test04_brick_sampling_matches_brute_force(variant, data, mode, method, leaf_cells):
    if leaf_cells and (mode != "abr" or method != "tent"):
        pytest.skip("the leaf floor applies to tent ABRs only")
    volume = as_volume(data)
    b = Bricks(volume)
    origin = data.origin
    lo, hi = data.bounds
    dev = DeviceBricks(b, origin)
    frame = (mi.Vector3f(*[float(c) for c in lo - origin]), mi.Vector3f(*[float(c) for c in hi - lo]))
    if mode == "abr":                   # over the supports the pipeline uses: domains (tent), bounds (nearest)
        tree = brick_region_tree(b, lo, hi, method == "tent", leaf_cells)
        if method == "nearest":
            assert tree.list_count.max() == 1
        sampler = BrickSampler(dev, as_method(method), *frame, over_bounds=method == "nearest",
                               abr_tree=DeviceTree(tree, 2 * lo, 0.5 / (hi - lo), np.zeros(tree.n_leaves), np.zeros(tree.n_leaves)))
    else:
        sampler = BrickSampler(dev, as_method(method), *frame, lists=DeviceBrickLists(BrickLists(b, lo, hi - lo, [7, 5, 6])))
    rng = np.random.default_rng(3)
    x = lo + rng.random((4000, 3)) * (hi - lo)
    x[:400] = np.round(x[:400] * 2) / 2                  # cell faces and centres
    ref, ref_found = brute_force(data, x, method)
    u = (x - lo) / (hi - lo)
    val, found = sampler.eval_at(mi.Vector3f((x - origin).T.astype(np.float32)), mi.Vector3f(u.T.astype(np.float32)))
    np.testing.assert_array_equal(found.numpy(), ref_found)
    np.testing.assert_allclose(val.numpy(), ref, atol=2e-6)


def test05_sah_kdtree_partitions_the_grid_within_budget():
    rng = np.random.default_rng(4)
    maj = np.zeros((16, 12, 10), np.float32)
    maj[3:6, 2:9, 4:7] = 5.0
    maj[10:15, 1:3, 1:9] = rng.random((5, 2, 8)) * 3
    vmin = rng.random(maj.shape).astype(np.float32)
    vmax = vmin + 1
    tree, lmin, lmax = build_sah_kdtree(maj, vmin, vmax, max_leaves=40)
    assert 2 <= tree.n_leaves <= 40
    vol = np.prod(tree.leaf_hi - tree.leaf_lo, axis=1)
    assert vol.sum() == maj.size
    cover = np.zeros(maj.shape, int)
    for L in range(tree.n_leaves):
        a, b = tree.leaf_lo[L].astype(int), tree.leaf_hi[L].astype(int)
        cover[a[0]:b[0], a[1]:b[1], a[2]:b[2]] += 1
        assert lmin[L] == vmin[a[0]:b[0], a[1]:b[1], a[2]:b[2]].min()
        assert lmax[L] == vmax[a[0]:b[0], a[1]:b[1], a[2]:b[2]].max()
    assert np.all(cover == 1)
    # the SAH separates the empty space from the dense block
    centre = tree.locate(np.array([[4.5, 5.5, 5.5]]))[0]
    empty = tree.locate(np.array([[0.5, 11.5, 0.5]]))[0]
    assert centre != empty


def test06_medium_structures_are_built_only_when_used(llvm):
    c = random_amr(5)
    m = mi.load_dict({"type": "amr", "data": c, "traversal": "grid", "sampling": "hash"})
    assert sorted(m.structures.built) == ["grid", "hash"]
    m = mi.load_dict({"type": "amr", "data": c, "traversal": "abr", "sampling": "brick"})
    assert "grid" not in m.structures.built and "hash" not in m.structures.built
    assert {"abr_tree", "bricks", "brick_lists"} <= set(m.structures.built)
    with pytest.raises(Exception, match="unknown traversal 'octree'"):
        mi.load_dict({"type": "amr", "data": c, "traversal": "octree"})
    with pytest.raises(Exception, match="unknown sampling"):
        mi.load_dict({"type": "amr", "data": c, "sampling": "cells"})


def test07_range_fold_keys_sort_as_the_values(llvm):
    """Leaf ranges are folded as integer keys (min/max atomics on every
    backend): the keys sort as the float values do, negatives and infinities
    included, the same on host and device, and map back exactly."""
    from mi_amr.structures.region_tree import _from_order_keys, _order_keys
    rng = np.random.default_rng(8)
    v = np.concatenate([[-np.inf, -0.0, 0.0, np.inf, 1e-38, -1e-38],
                        rng.normal(0, 1e3, 1000), rng.normal(0, 1e-3, 1000)]).astype(np.float32)
    k = _order_keys(v)
    order = np.argsort(v, kind="stable")
    assert np.all(np.diff(k[order].astype(np.int64)) >= 0)
    np.testing.assert_array_equal(_from_order_keys(k), v)
    np.testing.assert_array_equal(_order_keys(mi.Float(v)).numpy(), k)
