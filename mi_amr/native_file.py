"""The native ``.amrb`` file, written with what a medium would build first.

`mi_amr.data.amrb` holds the format and its one writer, `save_amrb`
(``save_cells(X.amrb)``, ``mi-amr convert`` and `save_native` all go
through it); the macrocell grids it stores are built a floor above the data
(`mi_amr.structures.cost_model.file_grids`: the cost model's finest
candidate for every reconstruction method), and this module hands that
builder to it when the package is imported, so that a medium opened from
the file starts rendering after reading it (docs/design.md section 9b).
"""

from __future__ import annotations

from pathlib import Path

from .data.amrb import save_amrb, use_grid_builder
from .data.blocks import BlockVolume
from .data.cells import AMRCells
from .structures.cost_model import file_grids

use_grid_builder(file_grids)


def save_native(data: AMRCells | BlockVolume, path) -> Path:
    """Write ``data`` to ``path`` (``.amrb``) with the macrocell grids of
    every reconstruction method (`mi_amr.data.amrb.save_amrb`); returns the path."""
    return save_amrb(data, path)
