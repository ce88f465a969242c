"""Stress tests of bad input (marker ``stress``): fuzzed and truncated
files, wrong parameters and bad updates give clear errors."""

import re

import mitsuba as mi
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import mi_amr
from mi_amr.data.io import read_exabricks, read_npz_blocks

from stress_oracles import constant_cells

pytestmark = pytest.mark.stress


@pytest.mark.parametrize("seed", range(40))
def test04_fuzzed_cells_files_give_clear_errors(tmp_path, seed):
    """Random and truncated bytes, inconsistent sizes, NaN/Inf, absurd levels
    and coordinates: a ValueError naming the file, or valid cells."""
    rng = np.random.default_rng(seed)
    kind = seed % 5
    n = int(rng.integers(1, 50))
    rec = np.zeros((n, 4), "<i4")
    rec[:, 3] = 0
    rec[:, :3] = np.arange(n)[:, None] * np.array([1, 0, 0])
    val = rng.random(n).astype("<f4")
    if kind == 0:
        cells_bytes = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        scal_bytes = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
    else:
        if kind == 1:
            rec[rng.integers(0, n), 3] = int(rng.choice([-5, 31, 2**30]))
        elif kind == 2:
            val[rng.integers(0, n)] = rng.choice([np.nan, np.inf, -np.inf])
        elif kind == 3:
            rec[rng.integers(0, n), :3] = int(rng.choice([2**31 - 1, -2**31]))
        cells_bytes, scal_bytes = rec.tobytes(), val.tobytes()
        if kind == 4:
            cells_bytes = cells_bytes[: int(rng.integers(0, len(cells_bytes)))]
    (tmp_path / "f.cells").write_bytes(cells_bytes)
    (tmp_path / "f.scalars").write_bytes(scal_bytes)
    try:
        c = read_exabricks(tmp_path / "f.cells")
    except ValueError as e:
        assert "f.cells" in str(e) or "f.scalars" in str(e)
        return
    assert np.isfinite(c.value).all() and (c.level >= 0).all()


@pytest.mark.parametrize("params,message", [
    ({"colour": 1.0}, "unknown parameter 'colour'"),
    ({"density_scale": "2"}, "density_scale must be a number"),
    ({"density_scale": float("nan")}, "density_scale must be finite"),
    ({"density_scale": -1.0}, "density_scale must be >= 0"),
    ({"grid_resolution": 2.5}, "grid_resolution must be an integer"),
    ({"grid_resolution": "16"}, "grid_resolution must be an integer"),
    ({"grid_resolution": 0}, "grid_resolution must be >= 1"),
    ({"traversal": "octree"}, "unknown traversal 'octree'"),
    ({"traversal": 3}, "traversal must be a string"),
    ({"sampling": True}, "sampling must be a string"),
    ({"reconstruction": "cubic"}, "unknown reconstruction 'cubic'"),
    ({"majorant": "local"}, "unknown majorant 'local'"),
    ({"brick_size": 0}, "brick_size must be >= 1"),
    ({"kdtree_leaves": 1.5}, "kdtree_leaves must be an integer"),
    ({"max_iterations": 0}, "max_iterations must be >= 1"),
    ({"tf_min": 2.0, "tf_max": 1.0}, "tf_min must be below tf_max"),
    ({"tf_min": "low"}, "tf_min must be a number"),
    ({"transfer_function": 3}, "transfer_function must be a preset name"),
    ({"transfer_function": "no-such-map"}, "no-such-map"),
    ({"to_world": "identity"}, "to_world must be a transform"),
    ({"to_world": "SINGULAR"}, "to_world is singular"),
    ({"overlap": "coarsest"}, "unknown overlap 'coarsest'"),
    ({"memory_limit": -5.0}, "memory_limit must be > 0"),
    ({"data": "cells.npz"}, "'data' must be an mi_amr.AMRCells"),
    ({"sample_emitters": "yes"}, "sample_emitters"),
])
def test15_wrong_scene_parameters_give_clear_errors(llvm, params, message):
    base = {"type": "amr", "data": constant_cells(2)}
    if params.get("to_world") == "SINGULAR":
        params = {"to_world": mi.ScalarTransform4f().scale([1.0, 1.0, 0.0])}
    with pytest.raises(Exception, match=re.escape(message)):
        mi.load_dict({**base, **params})


@pytest.mark.parametrize("params,message", [
    ({"max_depth": "8"}, "max_depth must be an integer"),
    ({"max_depth": -2}, "max_depth must be -1"),
    ({"rr_depth": 0}, "rr_depth must be >= 1"),
    ({"counters": 1}, "counters must be true or false"),
    ({"hide_emitters": "no"}, "hide_emitters"),          # Mitsuba's own check
    ({"samples": 4}, "unknown parameter 'samples'"),
])
def test15b_wrong_integrator_parameters_give_clear_errors(llvm, params, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "amrvolpath", **params})


def test15c_bad_updates_are_refused_and_undone(llvm):
    """density_scale of NaN or 1e38 (whose float32 reciprocal flushes to 0
    and would make the medium clear) and NaN TF entries through
    mi.traverse: a clear error, and the medium keeps rendering its last
    valid state."""
    from conftest import volume_scene
    with pytest.raises(Exception, match=r"density_scale must be <= 1e\+30"):
        mi.load_dict({"type": "amr", "data": constant_cells(2), "density_scale": 1e38})
    scene = mi.load_dict(volume_scene({"type": "amr", "data": constant_cells(2), "transfer_function": "ramp",
                                       "density_scale": 3.0}, res=8, integrator="amrvolpath"))
    before = np.array(mi.render(scene, spp=4, seed=0))
    params = mi.traverse(scene)
    k_scale = [k for k in params.keys() if k.endswith("density_scale")][0]
    k_rgba = [k for k in params.keys() if k.endswith("tf_rgba")][0]
    for key, bad in ((k_scale, float("nan")), (k_scale, 1e38), (k_rgba, mi.Float([np.nan] * 8))):
        params[key] = bad
        with pytest.raises(ValueError, match="density_scale|NaN"):
            params.update()
        after = np.array(mi.render(scene, spp=4, seed=0))
        np.testing.assert_array_equal(after, before)


FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _check_loaded_or_clear_error(load, names):
    """``load()`` returns valid cells or raises ValueError/MemoryError naming a file."""
    try:
        c = load()
    except (ValueError, MemoryError) as e:
        assert any(n in str(e) for n in names), str(e)
        return None
    assert len(c) > 0 and np.isfinite(c.value).all() and (c.level >= 0).all()
    assert (c.pos % c.width[:, None] == 0).all()
    return c


@FUZZ
@given(cells_bytes=st.binary(max_size=400), scalars_bytes=st.binary(max_size=200))
def test17_fuzz_random_bytes(tmp_path_factory, cells_bytes, scalars_bytes):
    d = tmp_path_factory.mktemp("fuzz")
    (d / "f.cells").write_bytes(cells_bytes)
    (d / "f.scalars").write_bytes(scalars_bytes)
    _check_loaded_or_clear_error(lambda: read_exabricks(d / "f.cells"), ["f.cells", "f.scalars"])


records = st.lists(st.tuples(st.integers(-2**31, 2**31 - 1), st.integers(-2**31, 2**31 - 1),
                             st.integers(-2**31, 2**31 - 1), st.integers(-40, 40)),
                   min_size=0, max_size=30)


small_records = st.lists(st.tuples(st.integers(0, 7), st.integers(0, 7), st.integers(0, 7),
                                   st.integers(0, 3)), min_size=1, max_size=30)


values = st.floats(allow_nan=True, allow_infinity=True, width=32)


@FUZZ
@given(rec=st.one_of(records, small_records), vals=st.lists(values, max_size=35),
       cut=st.integers(0, 20), overlap=st.sampled_from(["error", "finest"]))
def test17b_fuzz_structured_records(tmp_path_factory, rec, vals, cut, overlap):
    """Well-formed records with absurd levels and coordinates, NaN/Inf values,
    inconsistent counts and truncation: valid cells (which then render-ready
    structures accept) or a clear error."""
    d = tmp_path_factory.mktemp("fuzz")
    cells_bytes = np.asarray(rec, dtype="<i4").reshape(-1, 4).tobytes()
    (d / "f.cells").write_bytes(cells_bytes[: max(0, len(cells_bytes) - cut)])
    (d / "f.scalars").write_bytes(np.asarray(vals, dtype="<f4").tobytes())
    c = _check_loaded_or_clear_error(lambda: read_exabricks(d / "f.cells", overlap=overlap),
                                     ["f.cells", "f.scalars"])
    if c is not None:
        from mi_amr.data.blocks import BlockVolume
        v = BlockVolume.from_cells(c)                 # point location accepts every valid data set
        value, found = v.lookup(int(c.level[0]), (c.pos[:1] - v.origin) >> int(c.level[0]))
        assert found.all() and value[0] == c.value[0]
        lo, hi = c.bounds
        assert (hi - lo).max() < 2**31


@FUZZ
@given(pos=st.lists(st.tuples(st.integers(-100, 100), st.integers(-100, 100), st.integers(-100, 100)),
                    max_size=20),
       level=st.lists(st.integers(-3, 40), max_size=20), value=st.lists(values, max_size=20),
       pos_dtype=st.sampled_from(["<i4", "<i8", "<f4"]), junk=st.binary(max_size=64))
def test17c_fuzz_npz(tmp_path_factory, pos, level, value, pos_dtype, junk):
    d = tmp_path_factory.mktemp("fuzz")
    p = d / "f.npz"
    np.savez(p, pos=np.asarray(pos, dtype=pos_dtype).reshape(-1, 3), level=np.asarray(level, dtype="<i4"),
             value=np.asarray(value, dtype="<f4"))
    if junk:                                      # damage the archive
        data = bytearray(p.read_bytes())
        at = len(junk) * 7 % max(len(data), 1)
        data[at:at + len(junk)] = junk
        p.write_bytes(bytes(data))
    cells = _check_loaded_or_clear_error(lambda: mi_amr.load_cells(p), ["f.npz"])
    # the streaming reader accepts exactly the same archives, with the same cells
    try:
        vol = read_npz_blocks(p)
    except (ValueError, MemoryError) as e:
        assert cells is None and "f.npz" in str(e), str(e)
        return
    assert cells is not None and len(vol) == len(cells)
    got = vol.to_cells()
    key = lambda c: sorted(zip(map(tuple, c.pos.tolist()), c.level.tolist(), c.value.tolist()))  # noqa: E731
    assert key(got) == key(cells)

