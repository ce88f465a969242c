"""The native ``.amrb`` file, written with what a medium would build first.

`mi_amr.data.amrb` stores blocks and, optionally, macrocell grids; the grids
are built here (`mi_amr.structures.cost_model.file_grids`: the cost model's
finest candidate for every reconstruction method), so that a medium opened
from the file starts rendering after reading it (docs/design.md section 9b).
"""

from __future__ import annotations

from pathlib import Path

from .data.amrb import write_amrb
from .data.blocks import BlockVolume
from .data.cells import AMRCells
from .structures.cost_model import file_grids


def save_native(data: AMRCells | BlockVolume, path) -> Path:
    """Write ``data`` to ``path`` (``.amrb``) with the macrocell grids of
    every reconstruction method; returns the path."""
    volume = data if isinstance(data, BlockVolume) else BlockVolume.from_cells(data)
    return write_amrb(volume, path, grids=file_grids(volume))
