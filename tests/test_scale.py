"""Ten million cells (marker ``slow``): a block-structured file streams into
the compact form, every value reconstructed at random points equals the
field the generator sampled, and the medium keeps about 4 bytes per cell.
Speed is measured by ``python -m mi_amr.bench --scale``, not here."""

import mitsuba as mi
import numpy as np
import pytest

from mi_amr.data.datasets import _field, block_leaves, write_block_dataset

pytestmark = pytest.mark.slow


def test01_ten_million_block_structured_cells(llvm, tmp_path):
    n, levels = 10_000_000, 5
    path = write_block_dataset(tmp_path / "big.cells", n, levels)
    med = mi.load_dict({"type": "amr", "filename": str(path), "reconstruction": "nearest",
                        "transfer_function": "spiky", "density_scale": 10.0})
    vol = med.volume
    assert len(vol) == path.stat().st_size // 16 and len(vol) > 0.9 * n
    assert vol.block >= 8 and vol.nbytes / len(vol) < 4.1
    assert med.resident_bytes / len(vol) < 5.0
    assert med._given_cells is None          # no per-cell records were made

    # Oracle: the leaf block holding each point, the cell inside it, and the
    # generator's field at that cell's centre.
    lo_b, level_b, nxb, n_fine, seed = block_leaves(n, levels)
    f, _ = _field("cloud", seed)
    w_b = (np.int64(1) << level_b.astype(np.int64))
    rng = np.random.default_rng(0)
    lo, hi = vol.bounds
    x = lo + rng.random((20000, 3)) * (hi - lo)
    inside = np.all((x[:, None] >= lo_b[None]) & (x[:, None] < lo_b[None] + (nxb * w_b)[None, :, None]), axis=2)
    assert np.all(inside.sum(axis=1) == 1)               # the blocks tile the domain
    k = np.argmax(inside, axis=1)
    cell = lo_b[k] + np.floor((x - lo_b[k]) / w_b[k, None]) * w_b[k, None]
    expected = f((cell + 0.5 * w_b[k, None]) / n_fine).astype(np.float32)

    u = ((x - lo) / (hi - lo)).astype(np.float32)
    value, found = med.structures.sampler().eval(mi.Vector3f(u.T.copy()))
    assert found.numpy().all()
    # float32 local coordinates place points within 2^-24 of the domain:
    # points that close to a cell face may land in the neighbour
    near_face = np.any(np.abs((x - cell) / w_b[k, None] - np.round((x - cell) / w_b[k, None])) * w_b[k, None]
                       < 1e-6 * (hi - lo), axis=1)
    ok = value.numpy() == expected
    assert np.all(ok | near_face) and ok.mean() > 0.999
