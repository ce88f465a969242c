"""Resolution at the boundary (as OpenVKL's ``commit()``; docs/design.md
section 6c): data and reconstruction methods enter the package through
`as_volume` and `as_method`, once, where a user hands them in (the medium's
options, the short-cuts of `mi_amr`, the command line's loaders, the
benchmarks). Inside, functions take a `BlockVolume` and a `Reconstruction`
object only."""

from __future__ import annotations

from ..reconstruction import Reconstruction, reconstruction_method
from .blocks import BlockVolume
from .cells import AMRCells

__all__ = ["as_method", "as_volume"]


def as_method(method: str | Reconstruction) -> Reconstruction:
    """The method object of a name in `mi_amr.reconstruction.METHODS` (or
    the object itself); `ValueError` for an unknown name."""
    return reconstruction_method(method)


def as_volume(data: AMRCells | BlockVolume, method: str | Reconstruction = "tent") -> BlockVolume:
    """``data`` as blocks: a `BlockVolume` as it is, the blocks of an
    `AMRCells` (their block size weighed for ``method``, the reconstruction
    they will serve); `TypeError` for anything else."""
    if isinstance(data, BlockVolume):
        return data
    if isinstance(data, AMRCells):
        return BlockVolume.from_cells(data, method=as_method(method))
    raise TypeError(f"expected an mi_amr.AMRCells or BlockVolume, got {type(data).__name__}")
