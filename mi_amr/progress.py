"""Progress bars (tqdm) for loading and building: shown on a terminal once a
step has run for a second, silent otherwise (and in tests)."""

from __future__ import annotations

from tqdm import tqdm


def progress(total=None, desc: str = "", unit: str = "cell"):
    """A tqdm bar over ``total`` units that appears after one second, on
    terminals only, and leaves no line behind."""
    return tqdm(total=total, desc=desc, unit=unit, unit_scale=True, delay=1.0, leave=False,
                disable=None, dynamic_ncols=True)
