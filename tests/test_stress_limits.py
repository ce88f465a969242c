"""Stress tests of limits (marker ``stress``): determinism, loop bounds
and memory budgets."""

import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.data.io import read_exabricks, read_exabricks_blocks, read_npz_blocks

from stress_oracles import constant_cells, ratio_tracking

pytestmark = pytest.mark.stress


def test02_same_seed_gives_bit_identical_images(llvm):
    cells = mi_amr.data.datasets.make_dataset("cloud", cells=2000, seed=3)
    from conftest import volume_scene
    for integrator in ("volpath", "amrvolpath"):
        scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "spiky",
                                           "density_scale": 50.0}, res=24, integrator=integrator))
        a = np.array(mi.render(scene, spp=4, seed=11))
        b = np.array(mi.render(scene, spp=4, seed=11))
        np.testing.assert_array_equal(a, b)


def test09_loop_bounds_trigger_finite_and_reported(llvm):
    """The tracking loop stops at `max_iterations` (counted as capped, the
    estimate stays finite and in [0, 1]); the ray-majorant walk stops at its
    step bound with a conservative span (to the end, global majorant); an
    amrvolpath render with a tiny bound stays finite and reports the caps.
    The other loops are bounded by their data: reconstruction by levels x
    longest probe, kd descent by the tree depth, brick lists by the longest
    list, the shadow walk by 4096 surfaces."""
    from conftest import volume_scene
    from mi_amr.device.tracking import LocalRay, SpanMajorant, walk_segments
    from mi_amr.device.ray import intersect_unit_cube, safe_rcp
    cells = constant_cells(16)
    med = mi.load_dict({"type": "amr", "data": cells, "transfer_function": "constant", "density_scale": 0.5,
                        "grid_resolution": 16, "max_iterations": 4})
    n = 1000
    rng = np.random.default_rng(0)
    o = np.column_stack([rng.random(n), rng.random(n), np.full(n, -1.0)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    T, counts = ratio_tracking(med, o, d, 1)
    assert np.isfinite(T).all() and ((T >= 0) & (T <= 1)).all()
    capped = counts.capped.numpy()
    assert capped.sum() > n // 2                     # 16 macrocells to cross, 4 iterations
    assert counts.steps.numpy().max() <= 4
    # the ray-majorant walk: a bound of 2 steps over 16 macrocells
    ray_o = mi.Vector3f(o.T.astype(np.float32))
    ray_d = mi.Vector3f(d.T.astype(np.float32))
    hit, t0, t1 = intersect_unit_cube(ray_o, safe_rcp(ray_d))
    seg = med.structures.segments()
    span = walk_segments(seg, LocalRay(o=ray_o, d=ray_d, t_lo=dr.maximum(t0, 0.0), t_hi=t1, scale=mi.Float(1.0)),
                         hit, SpanMajorant(mi.Float(med.global_majorant)), 2)
    assert span.capped.numpy().all() and span.found.numpy().all()
    np.testing.assert_allclose(span.t_last.numpy(), t1.numpy())
    np.testing.assert_allclose(span.mu.numpy(), med.global_majorant)
    # a whole render with the tiny bound
    scene = mi.load_dict(dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "constant",
                                            "density_scale": 0.5, "grid_resolution": 16, "max_iterations": 4},
                                           res=8, integrator="amrvolpath", emitters="env"),
                              integrator={"type": "amrvolpath", "counters": True}))
    img = np.array(mi.render(scene, spp=4))
    assert np.isfinite(img).all()
    assert scene.integrator().counters()["capped"] > 0


def test09b_shadow_ray_bound_blocks_and_reports(llvm, monkeypatch):
    """A shadow ray that would cross more surfaces than the bound counts as
    blocked (no light leaks) and is reported in the counters; here a bound
    of 1 stops every shadow ray at the medium's boundary."""
    import mi_amr.plugins.integrator as integ
    from conftest import random_amr, volume_scene
    cells = random_amr(seed=1)
    means = []
    for bound in (integ.MAX_SHADOW_CROSSINGS, 1):
        monkeypatch.setattr(integ, "MAX_SHADOW_CROSSINGS", bound)
        d = volume_scene({"type": "amr", "data": cells, "transfer_function": "ramp", "density_scale": 4.0},
                         res=12, integrator="amrvolpath", emitters="sun")
        d["integrator"]["counters"] = True
        scene = mi.load_dict(d)
        img = np.array(mi.render(scene, spp=16, seed=1))
        assert np.isfinite(img).all()
        means.append(img.mean())
        capped = scene.integrator().counters()["shadow_capped"]
        assert (capped > 0) == (bound == 1)
    # sun light reaches the medium only through shadow rays: blocked -> black
    assert means[0] > 1e-3 and means[1] == 0.0


def test16_structures_that_do_not_fit_fail_before_allocating(llvm, tmp_path, monkeypatch):
    """A macrocell grid of 10^12 cells, structures above a small memory limit
    and a 100 GiB (sparse) .cells file give a clear error at once, before
    any large allocation (the process's peak memory grows by less than
    1 GiB over all of them; no clock involved)."""
    import resource
    from mi_amr.memory import MemoryLimitError, parse_bytes
    cells = constant_cells(8)
    peak0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss          # KiB on Linux
    with pytest.raises(Exception, match=r"macrocell grid of 10000x10000x10000 cells needs about .* TiB"):
        mi.load_dict({"type": "amr", "data": cells, "grid_resolution": 10000})
    # a limit between what the grid needs and what the hash needs
    from conftest import random_amr
    from mi_amr.data.blocks import BlockVolume
    from mi_amr.memory import format_bytes, grid_bytes, hash_bytes
    from mi_amr.reconstruction import reconstruction_method
    data = random_amr(0)
    vol = BlockVolume.from_cells(data, method="tent")
    grid_need = grid_bytes(8, vol.values.size)
    hash_need = hash_bytes(len(vol.level), reconstruction_method("tent")) + vol.values.nbytes
    assert grid_need < hash_need
    limit = 0.5 * (grid_need + hash_need)
    with pytest.raises(Exception, match=r"the hash structure .* needs about .*memory limit of "
                       + re.escape(format_bytes(limit))):
        mi.load_dict({"type": "amr", "data": data, "grid_resolution": 2, "memory_limit": limit})
    # a limit that the bricks fit and the ABR tree does not: refused by the
    # tree build's own depth-by-depth check, naming the structure and data
    from mi_amr.memory import bricks_bytes
    from mi_amr.structures.bricks import Bricks
    from mi_amr.structures.region_tree import brick_region_tree
    bricks_need = bricks_bytes(len(vol), vol.partial_block_cells)
    tree_need = brick_region_tree(Bricks(vol), *vol.bounds, True).peak_estimate
    assert bricks_need < tree_need
    limit = 0.5 * (bricks_need + tree_need)
    with pytest.raises(Exception, match=r"the abr_tree structure of .* needs about .*memory limit"):
        mi.load_dict({"type": "amr", "data": data, "traversal": "abr", "sampling": "abr", "grid_resolution": 2,
                      "memory_limit": limit})
    monkeypatch.setenv("MI_AMR_MEMORY_LIMIT", "2K")
    assert parse_bytes("2K") == 2048
    with pytest.raises(Exception, match="memory limit of 2.0 KiB"):
        mi.load_dict({"type": "amr", "data": cells, "traversal": "brick", "sampling": "brick",
                      "grid_resolution": 2})
    monkeypatch.delenv("MI_AMR_MEMORY_LIMIT")
    # a damaged file claiming 100 GiB of cells: refused from its size alone
    big = tmp_path / "big.cells"
    with open(big, "wb") as f:
        f.truncate(100 << 30)
    with open(tmp_path / "big.scalars", "wb") as f:
        f.truncate(25 << 30)
    for reader in (read_exabricks, read_exabricks_blocks):       # per-cell and streaming readers
        with pytest.raises(MemoryLimitError, match="big.cells"):
            reader(big)
    # an .npz whose header claims 10^12 values
    npz = tmp_path / "huge.npz"
    import zipfile
    with zipfile.ZipFile(npz, "w") as z:
        for name, shape in (("pos", (10**12, 3)), ("level", (10**12,)), ("value", (10**12,))):
            header = {"descr": "<i4", "fortran_order": False, "shape": shape}
            with z.open(f"{name}.npy", "w") as f:
                np.lib.format.write_array_header_1_0(f, header)
    for reader in (mi_amr.load_cells, read_npz_blocks):
        with pytest.raises(MemoryLimitError, match="huge.npz"):
            reader(npz)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak0 < 1 << 20

