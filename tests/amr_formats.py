"""Small simulation outputs written by the tests themselves, in the codes'
own on-disk formats, so that the readers yt uses for real data are exercised
without downloading anything.

`write_amrex_plotfile`: an AMReX/BoxLib plotfile directory (``Header``,
``Level_L/Cell_H`` and ``Level_L/Cell_D_00000``), as AMReX's
``WriteMultiLevelPlotfile`` lays it out (format "HyperCLaw-V1.1", one FAB file
per level, little-endian doubles, x fastest).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_amrex_plotfile(path, levels, prob_lo, prob_hi, field="density"):
    """Write a plotfile. ``levels``: per level, a list of ``(lo, data)``
    boxes, ``lo`` the box's first cell index (i, j, k) at that level and
    ``data`` its values indexed ``[i, j, k]``; level 0 must cover the domain
    and each finer level refines by 2."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    prob_lo, prob_hi = np.asarray(prob_lo, float), np.asarray(prob_hi, float)
    hi0 = np.max([np.asarray(lo) + np.asarray(d.shape) for lo, d in levels[0]], axis=0) - 1
    finest = len(levels) - 1
    dims = [(hi0 + 1) * 2 ** L for L in range(finest + 1)]
    dx = [(prob_hi - prob_lo) / d for d in dims]

    def box(lo, hi):
        return f"(({lo[0]},{lo[1]},{lo[2]}) ({hi[0]},{hi[1]},{hi[2]}) (0,0,0))"
    lines = ["HyperCLaw-V1.1", "1", field, "3", "0.0", str(finest),
             " ".join(f"{x:.17g}" for x in prob_lo), " ".join(f"{x:.17g}" for x in prob_hi),
             " ".join("2" for _ in range(finest)),
             " ".join(box((0, 0, 0), d - 1) for d in dims),
             " ".join("0" for _ in range(finest + 1))]
    lines += [" ".join(f"{x:.17g}" for x in d) for d in dx]
    lines += ["0", "0"]
    for L, boxes in enumerate(levels):
        lines += [f"{L} {len(boxes)} 0.0", "0"]
        for lo, data in boxes:
            lo = np.asarray(lo)
            for a in range(3):
                lines.append(f"{prob_lo[a] + lo[a] * dx[L][a]:.17g} "
                             f"{prob_lo[a] + (lo[a] + data.shape[a]) * dx[L][a]:.17g}")
        lines.append(f"Level_{L}/Cell")
        _write_level(path / f"Level_{L}", boxes, box)
    (path / "Header").write_text("\n".join(lines) + "\n")
    return path


def _write_level(level_dir, boxes, box):
    level_dir.mkdir(exist_ok=True)
    offsets = []
    with open(level_dir / "Cell_D_00000", "wb") as f:
        for lo, data in boxes:
            lo = np.asarray(lo)
            hi = lo + np.asarray(data.shape) - 1
            offsets.append(f.tell())
            f.write(f"FAB ((8, (64 11 52 0 1 12 0 1023)),(8, (8 7 6 5 4 3 2 1))){box(lo, hi)} 1\n"
                    .encode("ascii"))
            f.write(np.asarray(data, "<f8").ravel(order="F").tobytes())
    head = ["1", "0", "1", "0", f"({len(boxes)} 0"]
    head += [box(np.asarray(lo), np.asarray(lo) + np.asarray(d.shape) - 1) for lo, d in boxes]
    head += [")", str(len(boxes))]
    head += [f"FabOnDisk: Cell_D_00000 {o}" for o in offsets]
    (level_dir / "Cell_H").write_text("\n".join(head) + "\n")
