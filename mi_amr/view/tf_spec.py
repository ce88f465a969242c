"""What the viewer's transfer-function editor edits, and the table it gives.

The editor works in *display* units: the values themselves (linear) or their
log10, over a value range ``[lo, hi]`` of those units; opacity control
points ``(u, alpha)`` lie in the normalised display value ``u = (d - lo) /
(hi - lo)``, colour comes from a matplotlib colormap over ``u``. The medium
holds its values in *stored* units (``value_transform`` none or log10, fixed
at load: docs/design.md section 11). `TFSpec.table` samples the display-space
TF at the entries of a table that is uniform in stored units, so both
display modes work over one loaded medium: switching them changes the table,
not the data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..transfer.function import TransferFunction
from .protocol import TFChange, parse_message

#: Entries of the tables the editor makes (fine enough for a linear display
#: over log-stored values spanning several decades).
TABLE_SIZE = 1024
#: Colormaps offered in the editor ("scene": the medium's own colours).
COLORMAPS = ("plasma", "viridis", "magma", "inferno", "cividis", "turbo", "coolwarm", "gray")


def spiky_points() -> list[tuple[float, float]]:
    """The ``spiky`` preset's opacity as control points (three tents)."""
    pts = [(0.0, 0.0)]
    for c, a in ((0.25, 0.55), (0.5, 0.8), (0.8, 1.0)):
        pts += [(c - 0.025, 0.0), (c, a), (c + 0.025, 0.0)]
    return pts + [(1.0, 0.0)]


PRESET_POINTS = {
    "spiky": ("plasma", spiky_points()),
    "foggy": ("viridis", [(0.0, 0.0), (0.15, 0.02), (0.5, 0.08), (1.0, 0.15)]),
    "ramp": ("viridis", [(0.0, 0.0), (1.0, 1.0)]),
}


@dataclass
class TFSpec:
    """The editor's state (display units; see the module docstring)."""
    points: list = field(default_factory=spiky_points)
    colormap: str = "plasma"
    log: bool = False
    range: tuple = (0.0, 1.0)
    density: float = 1.0

    def to_json(self) -> dict:
        return {"points": [list(map(float, p)) for p in self.points], "colormap": self.colormap,
                "log": bool(self.log), "range": [float(self.range[0]), float(self.range[1])],
                "density": float(self.density)}

    @classmethod
    def from_message(cls, msg, current: "TFSpec", log_available: bool,
                     colormaps=COLORMAPS) -> "TFSpec":
        """A validated spec from an editor message (a `protocol.TFChange` or
        its JSON fields; missing ones keep ``current``'s); a `ValueError`
        names the first bad field."""
        if not isinstance(msg, TFChange):
            msg = parse_message(dict(msg, type="tf"))
        return current.changed(msg, log_available, colormaps)

    def changed(self, change: TFChange, log_available: bool, colormaps=COLORMAPS) -> "TFSpec":
        """This spec with ``change`` applied (its fields already checked by
        the protocol), checked against the scene: ``colormaps`` offered,
        whether the log10 display is (``log_available``: log-stored values);
        points sorted by u. A `ValueError` names the field."""
        pts = change.points if change.points is not None else self.points
        cmap = change.colormap if change.colormap is not None else self.colormap
        if cmap not in colormaps:
            raise ValueError(f"colormap: one of {', '.join(colormaps)}")
        log = change.log if change.log is not None else self.log
        if log and not log_available:
            raise ValueError("log: these data hold values <= 0 over much of the volume; "
                             "the log10 display is not available")
        lo, hi = (float(x) for x in (change.range if change.range is not None else self.range))
        if not log and log_available and hi <= 0:
            raise ValueError("range: hi must be above 0 (the data are positive)")
        density = change.density if change.density is not None else self.density
        order = sorted(range(len(pts)), key=lambda i: pts[i][0])      # stable
        return TFSpec([(float(pts[i][0]), float(pts[i][1])) for i in order], cmap, log, (lo, hi), float(density))

    def table(self, stored_log: bool, scene_rgb: np.ndarray | None = None) -> TransferFunction:
        """The medium's TF: `TABLE_SIZE` entries uniform in stored units over
        this spec's range; ``scene_rgb`` (N, 3): the colours of the
        "scene" colormap (the medium's own, over u)."""
        import matplotlib
        lo, hi = self.range
        if stored_log and not self.log:
            # linear display over log10-stored values: entries uniform in log10
            s_lo = np.log10(max(lo, hi * 1e-12)) if lo <= 0 else np.log10(lo)
            s_hi = np.log10(hi)
            x = np.linspace(s_lo, s_hi, TABLE_SIZE)
            u = (10.0 ** x - lo) / (hi - lo)
            domain = (s_lo, s_hi)
        else:
            # same units (a log display needs log-stored values: from_message checks)
            u = np.linspace(0.0, 1.0, TABLE_SIZE)
            domain = (lo, hi)
        u = np.clip(u, 0.0, 1.0)
        pts = np.asarray(self.points, dtype=np.float64)
        rgba = np.empty((TABLE_SIZE, 4))
        if self.colormap == "scene" and scene_rgb is not None:
            grid = np.linspace(0, 1, len(scene_rgb))
            for c in range(3):
                rgba[:, c] = np.interp(u, grid, scene_rgb[:, c])
        else:
            rgba[:, :3] = matplotlib.colormaps[self.colormap](u)[:, :3]
        rgba[:, 3] = np.interp(u, pts[:, 0], pts[:, 1])
        return TransferFunction(np.clip(rgba, 0.0, 1.0), domain)


#: Bins of the fine histogram that every editor histogram is re-binned from.
FINE_BINS = 1 << 14


def colormap_stops(names, scene_rgb=None, n: int = 9) -> dict:
    """``{name: ["#rrggbb", ...]}``: ``n`` colours of each colormap over u in
    [0, 1], what the editor's colour strip shows ("scene": the medium's own)."""
    import matplotlib
    u = np.linspace(0, 1, n)
    out = {}
    for name in names:
        if name == "scene":
            if scene_rgb is None:
                continue
            grid = np.linspace(0, 1, len(scene_rgb))
            rgb = np.stack([np.interp(u, grid, scene_rgb[:, c]) for c in range(3)], axis=1)
        else:
            rgb = matplotlib.colormaps[name](u)[:, :3]
        out[name] = ["#%02x%02x%02x" % tuple(int(round(255 * float(x))) for x in np.clip(c, 0, 1)) for c in rgb]
    return out


class Histogram:
    """The volume-weighted distribution of the stored values, computed once
    (`FINE_BINS` bins over their range), re-binned for any display range
    and mode in microseconds: the cumulative distribution interpolated at
    the display bins' edges (mapped to stored units)."""

    def __init__(self, volume):
        from ..autoscene import cells_and_weights
        lo, hi = volume.value_range
        if not hi > lo:
            lo, hi = lo - 0.5, hi + 0.5
        counts, total = np.zeros(FINE_BINS), 0.0
        for v, w in cells_and_weights(volume):
            counts += np.histogram(v, bins=FINE_BINS, range=(lo, hi), weights=w)[0]
            total += float(w.sum())
        self.edges = np.linspace(lo, hi, FINE_BINS + 1)
        self.cdf = np.concatenate([[0.0], np.cumsum(counts)]) / (total or 1.0)

    def shares(self, spec: TFSpec, stored_log: bool, bins: int = 128) -> list[float]:
        """Share of the volume in each of ``bins`` display bins over ``spec.range``."""
        edges = np.linspace(spec.range[0], spec.range[1], bins + 1)
        if stored_log and not spec.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                edges = np.where(edges > 0, np.log10(np.maximum(edges, 1e-300)), -np.inf)
        cdf = np.interp(edges, self.edges, self.cdf, left=0.0, right=1.0)
        return np.maximum(np.diff(cdf), 0.0).tolist()
