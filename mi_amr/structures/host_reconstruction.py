"""Reconstruction on the host: vectorised numpy over a `BlockVolume`.

Used to resample dense reference grids. ``x`` in finest-level cell units;
each method's own numpy evaluation (`Reconstruction.host_eval`, methods in
`mi_amr.reconstruction`; docs/design.md section 3).
"""

from __future__ import annotations

import numpy as np

from ..data.blocks import BlockVolume
from ..reconstruction import Reconstruction


class HostReconstruction:
    """Vectorised numpy reconstruction through the blocks of the data."""

    def __init__(self, volume: BlockVolume):
        self.volume = volume

    def __call__(self, x, method: Reconstruction):
        """``(value, found)`` at points ``x`` (M, 3), absolute finest units."""
        x = np.asarray(x, dtype=np.float64) - self.volume.origin
        return method.host_eval(self.volume, x)
