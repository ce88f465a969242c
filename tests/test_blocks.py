"""The compact resident form (`BlockVolume`): equivalence with the cells it
came from, streaming load, point location on host and device, macrocell
ranges built from blocks, and what a medium keeps in memory."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.data.blocks import BlockVolume
from mi_amr.data.datasets import make_dataset, write_block_dataset
from mi_amr.data.io import (read_exabricks, read_exabricks_blocks, read_npz_blocks, write_exabricks,
                            write_npz)
from mi_amr.device.hash_sampler import DeviceReconstruction
from mi_amr.reconstruction import reconstruction_method
from mi_amr.structures.boxes import expand_boxes
from mi_amr.structures.macrocell_grid import MacrocellGrid, axis_resolution
from mi_amr.testing import brute_force
from mi_amr.data.volume import as_method, as_volume

from conftest import random_amr

DATA = {"random": lambda: random_amr(0), "cloud": lambda: make_dataset("cloud", 5000),
        "stadium": lambda: make_dataset("stadium", 5000, levels=7),
        "blocks": lambda: make_dataset("blocks", 40000, levels=4)}


def sorted_cells(c):
    order = np.lexsort((c.pos[:, 0], c.pos[:, 1], c.pos[:, 2], c.level))
    return c.pos[order], c.level[order], c.value[order]


@pytest.mark.parametrize("name", DATA)
@pytest.mark.parametrize("block", [None, 2, 8])
def test01_blocks_hold_exactly_the_cells(name, block):
    """Every cell comes back (position, level, value) and nothing else; host
    point location finds each cell and misses outside the data."""
    cells = DATA[name]()
    vol = BlockVolume.from_cells(cells, block)
    assert len(vol) == len(cells) and vol.value_range == cells.value_range
    for a, b in zip(sorted_cells(cells), sorted_cells(vol.to_cells())):
        np.testing.assert_array_equal(a, b)
    for L in cells.levels:
        sel = cells.level == L
        q = (cells.pos[sel] - vol.origin) >> int(L)
        value, found = vol.lookup(int(L), q)
        assert found.all() and np.array_equal(value, cells.value[sel])
        _, found = vol.lookup(int(L), q + (vol.hi - vol.lo))           # beyond the data
        assert not found.any()


@pytest.mark.parametrize("method", ["nearest", "tent"])
def test02_block_size_follows_the_data(llvm, method):
    """Block-structured data fill whole blocks (4 bytes per cell plus a
    small index); on octree-like data the chosen size needs at most 1.25x
    the bytes (values and index, measured) of the best size."""
    blocks = BlockVolume.from_cells(DATA["blocks"](), method=method)
    assert blocks.block >= 8 and blocks.nbytes / len(blocks) < 4.2

    def total(vol):
        return vol.nbytes + DeviceReconstruction(vol, as_method(method)).nbytes
    for name in ("cloud", "stadium"):
        cells = DATA[name]()
        chosen = total(BlockVolume.from_cells(cells, method=method))
        best = min(total(BlockVolume.from_cells(cells, b)) for b in (2, 4, 8, 16))
        assert chosen <= 1.25 * best, (name, chosen / len(cells), best / len(cells))


@pytest.mark.parametrize("chunk", [1000, 1 << 22])
def test03_streaming_load_equals_in_memory(tmp_path, chunk):
    """A .cells file or an .npz archive read in chunks gives the blocks of
    the whole data."""
    cells = DATA["blocks"]()
    write_exabricks(cells, tmp_path / "d.cells")
    streamed = read_exabricks_blocks(tmp_path / "d.cells", chunk=chunk)
    direct = BlockVolume.from_cells(cells, streamed.block)
    np.testing.assert_array_equal(streamed.coord, direct.coord)
    np.testing.assert_array_equal(streamed.level, direct.level)
    np.testing.assert_array_equal(streamed.values, direct.values)
    assert streamed.source.endswith("d.cells") and len(streamed) == len(cells)
    write_npz(cells, tmp_path / "d.npz")                       # compressed members, streamed too
    from_npz = read_npz_blocks(tmp_path / "d.npz", chunk=chunk)
    np.testing.assert_array_equal(from_npz.values, streamed.values)
    np.testing.assert_array_equal(from_npz.coord, streamed.coord)


@pytest.mark.parametrize("chunk", [100, 1 << 22])
def test04_streaming_load_finds_overlaps_across_chunks(tmp_path, chunk, monkeypatch):
    """A coarse cell over finer ones, and a duplicate, in different chunks
    or in one: a clear error naming the file (or, with overlap='finest',
    the cells AMRCells keeps; with small chunks the coarse cell covers fine
    cells of several chunks of the overlap check, which run in threads)."""
    import mi_amr.data.blocks
    if chunk == 100:
        monkeypatch.setattr(mi_amr.data.blocks, "CHUNK", 64)
    cells = random_amr(1)
    bad = [(np.concatenate([cells.pos, [[0, 0, 0]]]), np.r_[cells.level, 3], np.r_[cells.value, 1.0]),
           (np.concatenate([cells.pos, cells.pos[:1]]), np.r_[cells.level, cells.level[:1]],
            np.r_[cells.value, 5.0])]
    for i, (pos, level, value) in enumerate(bad):
        path = tmp_path / f"bad{i}.cells"
        write_exabricks(mi_amr.AMRCells(pos, level, value, validate=False), path)
        with pytest.raises(ValueError, match=rf"bad{i}.cells.*overlap finer or duplicate"):
            read_exabricks_blocks(path, chunk=chunk)
        kept_blocks = read_exabricks_blocks(path, chunk=chunk, overlap="finest")
        kept = kept_blocks.to_cells()
        ref = read_exabricks(path, overlap="finest")
        assert len(kept_blocks) == len(kept) == len(ref)
        for a, b in zip(sorted_cells(ref), sorted_cells(kept)):
            np.testing.assert_array_equal(a, b)


def test05_inconsistent_files_fail_before_reading(tmp_path):
    """(Huge files: test16 of test_stress_limits, for both readers.)"""
    write_exabricks(random_amr(0), tmp_path / "t.cells")
    with open(tmp_path / "t.scalars", "ab") as f:
        f.write(b"\0\0\0\0")
    with pytest.raises(ValueError, match="t.cells has .* cells but .*t.scalars has"):
        read_exabricks_blocks(tmp_path / "t.cells")


@pytest.mark.parametrize("block", [2, 8])
@pytest.mark.parametrize("method", ["nearest", "tent"])
def test06_device_reconstruction_matches_brute_force(variant, block, method):
    """Values at random points, cell corners and centres (stencils across
    block boundaries included) equal the brute-force oracle."""
    cells = random_amr(7, n=16, levels=4)
    dev = DeviceReconstruction(BlockVolume.from_cells(cells, block), as_method(method))
    rng = np.random.default_rng(3)
    x = rng.uniform(-2, 18, (4000, 3))
    x[:800] = np.round(x[:800] * 2) / 2
    ref, ref_found = brute_force(cells, x, method)
    bits = mi.UInt32(sum(1 << int(L) for L in cells.levels))
    val, found = dev.eval(mi.Vector3f((x - dev.origin).astype(np.float32).T), bits)
    np.testing.assert_array_equal(found.numpy(), ref_found)
    np.testing.assert_allclose(val.numpy(), np.where(ref_found, ref, 0.0), rtol=1e-5, atol=1e-6)


def fold_each_cell(cells, res, support):
    """Oracle: each cell's value and level folded into every macrocell its
    support overlaps."""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    r = axis_resolution(res, ext)
    n = int(np.prod(r))
    vmin, vmax, bits = np.full(n, np.inf, np.float32), np.full(n, -np.inf, np.float32), np.zeros(n, np.uint32)
    pos, w = (cells.pos - lo).astype(np.float64), cells.width[:, None].astype(np.float64)
    a, b = (pos - 0.5 * w, pos + 1.5 * w) if support == "tent" else (pos, pos + w)
    i0 = np.clip(np.floor(a * r / ext), 0, r - 1).astype(np.int64)
    i1 = np.clip(np.floor(b * r / ext), 0, r - 1).astype(np.int64)
    idx, owner = expand_boxes(i0, i1, r)
    np.minimum.at(vmin, idx, cells.value[owner])
    np.maximum.at(vmax, idx, cells.value[owner])
    np.bitwise_or.at(bits, idx, (np.uint32(1) << cells.level.astype(np.uint32))[owner])
    return vmin, vmax, bits


@pytest.mark.parametrize("name", ["random", "stadium", "blocks"])
@pytest.mark.parametrize("support", ["tent", "nearest"])
def test07_macrocell_ranges_from_blocks_are_exact(name, support, monkeypatch):
    """Ranges and level masks built from blocks (windowed per block, dense
    per coarse level) or from cells equal folding every cell into every
    macrocell its support touches, also when the blocks are reduced in
    small chunks by two threads at once; a pooled grid equals a direct build."""
    from mi_amr.structures import block_windows, macrocell_grid
    cells = DATA[name]()
    vol = BlockVolume.from_cells(cells)
    for res in (5, 8, 16, 37):                   # 8 and 16 align with the blocks
        ref = fold_each_cell(cells, res, support)
        for src in (as_volume(cells, support), vol):
            g = MacrocellGrid(src, res, support=as_method(support))
            for a, b in zip((g.vmin, g.vmax, g.level_bits), ref):
                np.testing.assert_array_equal(a, b)
        with monkeypatch.context() as m:
            m.setattr(macrocell_grid, "BLOCK_CHUNK", 8 * vol.block ** 3)       # eight blocks a chunk
            m.setattr(macrocell_grid, "build_threads", lambda: 2)          # as on a 2-core box
            m.setattr(block_windows, "WINDOW_PATTERNS", 0)           # every window gathered, not sliced
            g = MacrocellGrid(vol, res, support=as_method(support))
        for a, b in zip((g.vmin, g.vmax, g.level_bits), ref):
            np.testing.assert_array_equal(a, b)
    fine = MacrocellGrid(vol, 32, support=as_method(support))
    pooled, direct = fine.pooled(8), MacrocellGrid(vol, 8, support=as_method(support))
    if pooled is not None:
        np.testing.assert_array_equal(pooled.vmax, direct.vmax)
        np.testing.assert_array_equal(pooled.level_bits, direct.level_bits)


def test08_a_medium_from_a_file_keeps_only_blocks(llvm, tmp_path):
    """Loaded from a .cells file with the default structures, a medium keeps
    the blocks (4 bytes per cell on block-structured data, values shared
    with the device on the CPU) and small structures, no per-cell records."""
    path = write_block_dataset(tmp_path / "b.cells", 40000, levels=4)
    from conftest import volume_scene
    scene = mi.load_dict(volume_scene({"type": "amr", "filename": str(path), "transfer_function": "spiky",
                                       "density_scale": 20.0}, res=8, integrator="amrvolpath"))
    assert np.isfinite(mi.render(scene, spp=2).numpy()).all()
    med = mi_amr.amr_media(scene)[0]
    assert isinstance(med.volume, BlockVolume) and med._given_cells is None
    # brick structures build from the blocks, level by level, and keep no per-cell records
    bricked = mi.load_dict({"type": "amr", "filename": str(path), "traversal": "brick", "sampling": "brick"})
    from mi_amr.structures.cache import HOST_CACHE
    cached = [HOST_CACHE.peek(bricked.volume, k) for k in HOST_CACHE.keys(bricked.volume)]
    assert "bricks" in bricked.structures.host and cached
    assert not any(isinstance(v, mi_amr.AMRCells) for v in cached)
    assert med.volume.nbytes / len(med.volume) < 4.1
    # besides the blocks: the macrocell grid, and the block hash with (tent)
    # ghost blocks and each block's 7 upper neighbours, small beside the
    # values, which are not counted twice
    hash_bytes = med.structures.device["hash"].nbytes
    assert med.resident_bytes == med.volume.nbytes + med.grid.nbytes + hash_bytes
    assert hash_bytes < 0.25 * med.volume.nbytes


@pytest.mark.parametrize("name", ["cloud", "blocks"])
def test09_memory_estimates_within_2x_of_the_measured_peak(llvm, tmp_path, name):
    """The estimates that guard loading, the macrocell grid, the block hash,
    the bricks and the region trees (checked depth by depth) are within a
    factor 2 of the host peak measured with tracemalloc (numpy allocations),
    on octree-like and block-structured data."""
    import tracemalloc
    from mi_amr.memory import bricks_bytes, grid_bytes, hash_bytes, load_bytes
    from mi_amr.structures.bricks import Bricks
    from mi_amr.structures.region_tree import brick_region_tree
    cells = make_dataset("cloud", 300000) if name == "cloud" else make_dataset("blocks", 1_000_000, levels=4)
    path = write_exabricks(cells, tmp_path / "m.cells")[0]
    del cells

    def peak_of(build):
        tracemalloc.start()
        out = build()
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return out, peak
    vol, peak = peak_of(lambda: read_exabricks_blocks(path))
    assert 0.5 < load_bytes(len(vol)) / peak < 2.0, ("load", load_bytes(len(vol)) / peak)
    for res in (32, 128):
        g, peak = peak_of(lambda: MacrocellGrid(vol, res))
        est = grid_bytes(int(np.prod(g.res)), vol.values.size)
        assert 0.5 < est / peak < 2.0, ("grid", res, est / peak)
    for method in ("nearest", "tent"):
        _, peak = peak_of(lambda: DeviceReconstruction(vol, as_method(method)))
        est = hash_bytes(len(vol.level), reconstruction_method(method))
        assert 0.5 < est / peak < 2.0, ("hash", method, est / peak)
    bricks, peak = peak_of(lambda: Bricks(vol))
    est = bricks_bytes(len(vol), vol.partial_block_cells)
    assert 0.5 < est / peak < 2.0, ("bricks", est / peak)
    for over_domains in (True, False):                 # tent ABRs, brick tree
        tree, peak = peak_of(lambda: brick_region_tree(bricks, *vol.bounds, over_domains))
        assert 0.5 < tree.peak_estimate / peak < 2.0, ("region tree", over_domains, tree.peak_estimate / peak)


def test10_media_on_the_same_data_share_one_device_copy(llvm):
    """Two media (nearest and tent) over one BlockVolume upload its values
    once, and both still match brute force."""
    cells = random_amr(7, n=16, levels=3)
    vol = BlockVolume.from_cells(cells)
    a, b = DeviceReconstruction(vol, as_method("nearest")), DeviceReconstruction(vol, as_method("tent"))
    assert a.values.index == b.values.index
    x = np.random.default_rng(4).uniform(0, 16, (2000, 3))
    bits = mi.UInt32(sum(1 << int(L) for L in cells.levels))
    for dev, method in ((a, "nearest"), (b, "tent")):
        ref, ref_found = brute_force(cells, x, method)
        val, found = dev.eval(mi.Vector3f((x - dev.origin).astype(np.float32).T), bits)
        np.testing.assert_array_equal(found.numpy(), ref_found)
        np.testing.assert_allclose(val.numpy(), np.where(ref_found, ref, 0.0), rtol=1e-5, atol=1e-6)


def test11_from_dense_is_one_level_of_the_same_field(llvm):
    """A dense array (NaN: no cell) as one level of 16^3 blocks: the nearest
    field at random points equals the array's voxel, empty blocks are left
    out, and the bounds are the array's extent."""
    from mi_amr.structures.host_reconstruction import HostReconstruction
    rng = np.random.default_rng(4)
    dense = rng.random((20, 37, 18)).astype(np.float32)      # [z, y, x], sizes not multiples of 16
    dense[:, :16, :] = np.nan                                  # a slab without cells
    v = BlockVolume.from_dense(dense, 16)
    assert v.n_cells == int(np.count_nonzero(~np.isnan(dense)))
    assert v.hi.tolist() == [18, 37, 20] and len(v.level) == 2 * 2 * 2   # the y-slab's blocks are gone
    x = rng.random((5000, 3)) * np.array([18, 37, 20])
    val, found = HostReconstruction(v)(x, as_method("nearest"))
    i = np.floor(x).astype(np.int64)
    ref = dense[i[:, 2], i[:, 1], i[:, 0]]
    np.testing.assert_array_equal(found, ~np.isnan(ref))
    np.testing.assert_array_equal(val[found], ref[found])


def test12_mixed_block_sizes_tile_the_domain(tmp_path):
    """``blocks`` with several sizes (``--nxb 8,16,32``): same-level blocks
    of each size that tile the domain exactly; the streamed file loads
    without overlaps, holds every block's cells and the field at their
    centres."""
    from mi_amr.data.datasets import _field, block_leaves
    from mi_amr.tools.cli import build_parser
    lo, level, size, n_fine, seed = block_leaves(300_000, 3, nxb=(8, 16, 32))
    assert set(np.unique(size).tolist()) == {8, 16, 32}
    w = np.int64(1) << level.astype(np.int64)
    assert np.all(lo % (size * w)[:, None] == 0)                    # aligned to their own size
    assert int(((size * w) ** 3).sum()) == n_fine ** 3              # volumes add up to the domain
    args = build_parser().parse_args(["dataset", "blocks", str(tmp_path / "m.cells"), "--cells", "3e5",
                                      "--levels", "3", "--nxb", "8,16,32"])
    assert args.cells == 300_000 and args.nxb == (8, 16, 32)
    path = write_block_dataset(tmp_path / "m.cells", 300_000, 3, nxb=(8, 16, 32))
    vol = read_exabricks_blocks(path, chunk=50_000)                 # overlaps are errors by default
    assert len(vol) == int((size ** 3).sum()) and vol.covers_bounds
    cells = vol.to_cells()
    pick = np.random.default_rng(0).choice(len(cells), 2000, replace=False)
    f, _ = _field("cloud", seed)
    wc = (np.int64(1) << cells.level[pick].astype(np.int64))[:, None]
    expected = f((cells.pos[pick] + 0.5 * wc) / n_fine).astype(np.float32)
    np.testing.assert_array_equal(cells.value[pick], expected)


@pytest.mark.parametrize("method", ["tent", "nearest"])
def test13_any_cell_order_builds_the_same_blocks(tmp_path, method):
    """The same cells written in every layout of `LAYOUTS` that keeps the
    cell set (this generator's, z fastest inside blocks, blocks sorted by
    space, shuffled), and octree-like data shuffled, stream (in chunks of
    a few thousand cells) into identical blocks: the block size, the block
    list and every value; the block counts behind the choice are exact, so
    the size is the one of the in-order file."""
    ref = None
    from mi_amr.tools.cli import main
    for layout in ("blocks", "zfast", "space", "shuffled"):
        path = tmp_path / f"{layout}.cells"
        if layout == "shuffled":                                   # as a user writes one
            main(["dataset", "blocks", str(path), "--cells", "60000", "--levels", "4", "--layout", layout])
        else:
            write_block_dataset(path, 60_000, 4, layout=layout)
        vol = read_exabricks_blocks(path, chunk=4096, method=method)
        if ref is None:
            ref = vol
            assert vol.block >= 8 and vol.nbytes / len(vol) < 4.2
            continue
        assert vol.block == ref.block and len(vol) == len(ref), layout
        np.testing.assert_array_equal(vol.coord, ref.coord)
        np.testing.assert_array_equal(vol.level, ref.level)
        np.testing.assert_array_equal(vol.values, ref.values)
    cells = DATA["cloud"]()
    perm = np.random.default_rng(3).permutation(len(cells))
    shuffled = mi_amr.AMRCells(cells.pos[perm], cells.level[perm], cells.value[perm])
    a, b = BlockVolume.from_cells(cells, method=method), BlockVolume.from_cells(shuffled, method=method)
    assert a.block == b.block
    np.testing.assert_array_equal(a.coord, b.coord)
    np.testing.assert_array_equal(a.values, b.values)


def test14_dense_block_counts_equal_the_sorted_ones(monkeypatch):
    """The block and ghost counts found on the dense tile index (any cell
    order) equal those of sorting block keys (`ghost_blocks`), for every
    block size, on octree-like, sparse and block-structured data; with the
    dense index over its budget, loads fall back to sorting and give the
    same blocks."""
    import mi_amr.data.blocks as blocks
    from mi_amr.core.block_keys import ghost_blocks, level_coords
    from mi_amr.data.blocks import TileIndex, _dense_ghosts, _pool
    for name in ("cloud", "stadium", "blocks"):
        cells = DATA[name]()
        lo, hi = cells.bounds
        lmax = int(cells.level.max())
        origin = (lo >> lmax) << lmax
        tiles = TileIndex(lo, hi, origin, lmax)
        q = level_coords(cells.pos, cells.level, origin)
        occupied = np.zeros(tiles.total, np.uint8)
        occupied[tiles.index(q, cells.level)] = 1
        tiles.set_occupied(occupied)
        fine = np.zeros((tiles.count, 8, 8, 8), bool)
        r = tiles.rank[tiles.index(q, cells.level)]
        fine[r, (q[2] >> 1) & 7, (q[1] >> 1) & 7, (q[0] >> 1) & 7] = True
        for b in (2, 4, 8, 16):
            grid = _pool(fine, 16 // b)
            keys = np.unique(np.stack([cells.level.astype(np.int64)] + [c.astype(np.int64) >> (b.bit_length() - 1)
                                                                      for c in q], axis=1), axis=0)
            assert np.count_nonzero(grid) == len(keys), (name, b)
            ghosts = ghost_blocks(keys[:, 1:], keys[:, 0])[1]
            assert _dense_ghosts(tiles, grid) == len(ghosts), (name, b)
    # wide keys (an axis beyond 2^19 blocks), whose order (z first) is not the tiles' (level first)
    local = np.argwhere(np.ones((16, 16, 16), bool))[:, ::-1]
    pos = np.concatenate([[0, 0, 16] + local, [1 << 20, 0, 0] + 2 * local])
    level = np.repeat(np.array([0, 1], np.int32), len(local))
    perm = np.random.default_rng(1).permutation(len(pos))
    spread = mi_amr.AMRCells(pos[perm], level[perm], np.arange(len(pos), dtype=np.float32)[perm])
    for cells in [DATA[name]() for name in ("cloud", "stadium", "blocks")] + [spread]:
        dense = BlockVolume.from_cells(cells)
        for a, b in zip(sorted_cells(cells), sorted_cells(dense.to_cells())):
            np.testing.assert_array_equal(a, b)
        dense = BlockVolume.from_cells(cells, dense.block)       # same candidates, so the same key packing
        monkeypatch.setattr(blocks, "DENSE_ENTRIES", 0)
        monkeypatch.setattr(blocks, "TILE", 1)                    # no dense index: sorted keys
        sorted_ = BlockVolume.from_cells(cells, dense.block)
        monkeypatch.undo()
        np.testing.assert_array_equal(sorted_.coord, dense.coord)
        np.testing.assert_array_equal(sorted_.values, dense.values)


def test15_packed_ghosts_and_stencils_equal_the_general_ones(monkeypatch):
    """`ghost_blocks` and `BlockVolume.stencil_index` work in key space when
    block coordinates fit packed keys (an offset is a constant added to a
    key); forced onto the general path (16-byte keys, coordinates offset
    one by one) they give the same ghosts and the same neighbours of every
    block and ghost, on octree-like, sparse and block-structured data (the
    two key kinds sort differently, so ghosts are compared as sets and
    neighbours by the blocks they name)."""
    import mi_amr.core.block_keys as block_keys
    import mi_amr.data.blocks as blocks

    def named(volume, index):
        ghost_coord, ghost_level, neighbours = index
        coord = np.concatenate([volume.coord, ghost_coord]).astype(np.int64)
        level = np.concatenate([volume.level, ghost_level]).astype(np.int64)
        rows = {}
        for k in range(len(level)):
            nb = neighbours[k]
            rows[(int(level[k]), *coord[k].tolist())] = tuple(
                None if j == 0xFFFFFFFF else (int(level[j]), *coord[j].tolist()) for j in nb)
        return rows

    for name in ("cloud", "stadium", "blocks"):
        volume = BlockVolume.from_cells(DATA[name](), method="tent")
        fast = volume.stencil_index()
        ghost_fast = block_keys.ghost_blocks(volume.coord, volume.level)
        with monkeypatch.context() as m:
            m.setattr(block_keys, "fits_packed", lambda coord, margin=0: False)
            m.setattr(blocks, "fits_packed", lambda coord, margin=0: False)
            slow = volume.stencil_index()
            ghost_slow = block_keys.ghost_blocks(volume.coord, volume.level)
        assert len(ghost_fast[1]) > 0, name
        assert ghost_fast[1].dtype == ghost_slow[1].dtype == volume.level.dtype, name
        as_set = [set(zip(g[1].tolist(), map(tuple, g[0].tolist()))) for g in (ghost_fast, ghost_slow)]
        assert as_set[0] == as_set[1], name
        assert named(volume, fast) == named(volume, slow), name
