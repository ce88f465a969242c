"""The native ``.amrb`` file, written with what a medium and a plan read
first.

`mi_amr.data.amrb` holds the format and its one writer, `save_amrb`, which
takes what to store beside the blocks as arguments: `save_native` computes
them here, a floor above the structures and the planning, and passes them
(no builder is installed anywhere at import time). They are the macrocell
grids of every reconstruction method (`mi_amr.structures.cost_model.file_grids`:
the cost model's finest candidate each), so that a medium opened from the
file starts rendering after reading it (docs/design.md section 9b), and the
statistics a planned scene reads of the values (`mi_amr.autoscene.file_stats`).
`save_data` is what ``mi_amr.save_cells``, ``mi-amr convert`` and ``mi-amr
render`` call: ``.amrb`` through `save_native`, other files through
`mi_amr.data.io.save_cells`.
"""

from __future__ import annotations

from pathlib import Path

from .autoscene import file_stats
from .data.amrb import save_amrb
from .data.blocks import BlockVolume
from .data.cells import AMRCells
from .data.io import save_cells
from .data.volume import as_volume
from .structures.cost_model import file_grids


def save_native(data: AMRCells | BlockVolume, path) -> Path:
    """Write ``data`` to ``path`` (``.amrb``) with the macrocell grids of
    every reconstruction method and the planning statistics of its values
    (`mi_amr.data.amrb.save_amrb`); returns the path."""
    volume = as_volume(data)
    return save_amrb(volume, path, grids=file_grids(volume), stats=file_stats(volume))


def save_data(data: AMRCells | BlockVolume, path) -> Path:
    """Write ``data`` by the file's suffix: ``.amrb`` as `save_native`,
    ``.cells`` (+ ``.scalars``) and ``.npz`` as `mi_amr.data.io.save_cells`;
    returns the path (of the ``.cells`` file for a pair)."""
    return save_native(data, path) if Path(path).suffix == ".amrb" else save_cells(data, path)
