#!/usr/bin/env python
"""Load rate of octree AMR through yt: an octree of about ``--leaves`` leaf
cells built with ``yt.load_octree`` (``octree`` of tests/amr_formats.py: complete to
depth 7, a share of the depth-7 cells refined once more), then
`mi_amr.data.yt_import.from_yt_blocks` on it, timed in two parts:

* yt's part: what yt does for mi-amr inside the load (the leaves' centres
  and widths, ``fcoords``/``fwidth``, once; the field, on the two passes that
  read values), plus building yt's index before it (reported apart);
* mi-amr's part: the rest (rounding to finest units and the checks,
  `octree_cells`; the block build, `BlockVolume.from_chunks`).

    DRJIT_LIBLLVM_PATH="$(tools/find-llvm19)" .venv/bin/python tools/bench_yt_octree.py [--leaves 1e7]

Wall seconds on a shared machine: run it twice, read the better.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--leaves", type=float, default=1e7, help="leaf cells, about (default 1e7)")
    args = p.parse_args(argv)
    import yt
    from yt.data_objects.data_containers import YTDataContainer
    from yt.data_objects.selection_objects.data_selection_objects import YTSelectionContainer

    import mi_amr.data.yt_import as yi
    from amr_formats import octree
    yt.set_log_level(50)
    depth = 7
    share = min(1.0, max(0.0, (args.leaves / 8 ** depth - 1) / 7))      # each refined cell: 7 more leaves
    rng = np.random.default_rng(0)
    t = time.perf_counter()
    mask, _, level = octree(depth + 1, lambda c, d: np.full(len(c), d < depth) | (rng.random(len(c)) < share))
    value = 1.0 + np.arange(len(level), dtype=np.float64)
    ds = yt.load_octree(octree_mask=mask, data={("gas", "density"): value[:, None]}, num_zones=1,
                        partial_coverage=0)
    built = time.perf_counter() - t
    t = time.perf_counter()
    ds.index
    index = time.perf_counter() - t

    spent = {"yt": 0.0, "octree_cells": 0.0}

    def timed(fn, key):
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[key] += time.perf_counter() - t0
        return wrapper
    for name in ("fcoords", "fwidth"):
        setattr(YTSelectionContainer, name, property(timed(getattr(YTSelectionContainer, name).fget, "yt")))
    YTDataContainer.__getitem__ = timed(YTDataContainer.__getitem__, "yt")
    yi.octree_cells = timed(yi.octree_cells, "octree_cells")
    t = time.perf_counter()
    vol = yi.from_yt_blocks(ds, ("gas", "density"))
    total = time.perf_counter() - t
    n = vol.n_cells
    assert n == len(level)
    ours = total - spent["yt"]
    print(f"{n} leaves (octree and yt.load_octree built in {built:.1f} s; yt's index {index:.1f} s)")
    print(f"from_yt_blocks: {total:.2f} s, {n / total / 1e6:.2f} M leaves/s")
    print(f"  yt's part    : {spent['yt']:.2f} s, {n / spent['yt'] / 1e6:.2f} M leaves/s (fcoords, fwidth, field)")
    print(f"  mi-amr's part: {ours:.2f} s, {n / ours / 1e6:.2f} M leaves/s (of which octree_cells "
          f"{spent['octree_cells']:.2f} s, blocks {ours - spent['octree_cells']:.2f} s)")
    print(f"  {vol}")


if __name__ == "__main__":
    main()
