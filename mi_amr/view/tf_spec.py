"""What the viewer's transfer-function editor edits, and the table it gives.

The editor works in *display* units: the values themselves (linear) or their
log10, over a value range ``[lo, hi]`` of those units; opacity control
points ``(u, alpha)`` lie in the normalised display value ``u = (d - lo) /
(hi - lo)``, colour comes from a matplotlib colormap over ``u``, or from the
points' own colours (``(u, alpha, "#rrggbb")``, `point_colours`). The medium
holds its values in *stored* units (``value_transform`` none or log10, fixed
at load: docs/design.md section 11). `TFSpec.table` samples the display-space
TF at the entries of a table that is uniform in stored units, so both
display modes work over one loaded medium: switching them changes the table,
not the data. `TFSpec.file_json` writes the editor's TF as the JSON that
``mi-amr render --tf`` reads (in display units), with the editor's state
beside it; `TFSpec.from_file` reads that, or any TF JSON, back.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..data.statistics import VIEW_HISTOGRAM_BINS, fine_histogram, stored_fine_histogram
from ..transfer.function import TransferFunction
from ..transfer.layers import Layers, is_layers
from .protocol import TFChange, parse_message

#: Entries of the tables the editor makes (fine enough for a linear display
#: over log-stored values spanning several decades).
TABLE_SIZE = 1024
#: Colormaps offered in the editor ("scene": the medium's own colours).
COLORMAPS = ("plasma", "viridis", "magma", "inferno", "cividis", "turbo", "coolwarm", "gray")


def hex_rgb(colours) -> np.ndarray:
    """``"#rrggbb"`` strings -> (n, 3) floats in [0, 1]."""
    return np.array([[int(c[i:i + 2], 16) for i in (1, 3, 5)] for c in colours], np.float64).reshape(-1, 3) / 255.0


def rgb_hex(rgb) -> list[str]:
    """(n, 3) floats in [0, 1] -> ``"#rrggbb"`` strings."""
    q = np.rint(255 * np.clip(np.asarray(rgb, np.float64).reshape(-1, 3), 0, 1)).astype(int)
    return ["#%02x%02x%02x" % tuple(c) for c in q]


def spiky_points() -> list[tuple[float, float]]:
    """The ``spiky`` preset's opacity as control points (three tents)."""
    pts = [(0.0, 0.0)]
    for c, a in ((0.25, 0.55), (0.5, 0.8), (0.8, 1.0)):
        pts += [(c - 0.025, 0.0), (c, a), (c + 0.025, 0.0)]
    return pts + [(1.0, 0.0)]


def layer_points(layers: Layers | str = "layers") -> list:
    """A layered TF (`mi_amr.transfer.layers.Layers`, or its name) as the
    editor's points: per layer a peak at its centre, its shoulders one
    standard deviation off (the profile's value there: `Layers.profiles`)
    and its feet at zero 2.5 deviations off (the last layer holds its peak up to u = 1),
    each point in its layer's colour; what the editor's "add layers"
    builds over the range shown (tf_editor.js ``layerPoints``)."""
    layers = Layers.parse(layers) if isinstance(layers, str) else layers
    sigma = layers.width / layers.n
    foot = min(2.5 * sigma, 0.5 / layers.n - 1e-4)
    shoulder = min(sigma, 0.8 * foot)
    pts = [(0.0, 0.0)]
    for k, (c, a, colour) in enumerate(zip(layers.centres(), layers.opacities(), rgb_hex(layers.colours()))):
        last = k == layers.n - 1
        below, above = layers.profiles([c - shoulder, c + shoulder])[:, k]
        side = [(c - foot, 0.0), (c - shoulder, a * below), (c, a)]
        side += [(1.0, a)] if last else [(c + shoulder, a * above), (c + foot, 0.0)]
        pts += [(float(u), float(v), colour) for u, v in side]
    if pts[-1][0] < 1.0:
        pts.append((1.0, 0.0))
    return pts


def preset_points(name: str) -> tuple[str, list]:
    """``(colormap, points)`` of a TF the plan names: a layered one's
    (`layer_points`), else `PRESET_POINTS`' (``spiky``'s for others)."""
    if is_layers(name):
        layers = Layers.parse(name)
        return layers.colormap if layers.colormap in COLORMAPS else "viridis", layer_points(layers)
    return PRESET_POINTS.get(name, PRESET_POINTS["spiky"])


#: The editor's presets: a colormap and opacity points (the first four
#: are `TransferFunction.preset`'s, what the autoscene plan names).
PRESET_POINTS = {
    "layers": ("viridis", layer_points()),
    "spiky": ("plasma", spiky_points()),
    "foggy": ("viridis", [(0.0, 0.0), (0.15, 0.02), (0.5, 0.08), (1.0, 0.15)]),
    "ramp": ("viridis", [(0.0, 0.0), (1.0, 1.0)]),
    "ramp down": ("magma", [(0.0, 1.0), (1.0, 0.0)]),
    "tent": ("coolwarm", [(0.0, 0.0), (0.5, 0.8), (1.0, 0.0)]),
    "step": ("inferno", [(0.0, 0.0), (0.5, 0.0), (0.52, 0.7), (1.0, 0.7)]),
    "gray ramp": ("gray", [(0.0, 0.0), (1.0, 0.6)]),
}
#: Opacity samples the editor takes from a loaded table of more entries.
LOADED_POINTS = 65


def point_colours(points, u, base) -> np.ndarray:
    """(len(u), 3) colours over ``u``: between two neighbouring points of
    which at least one has its own colour, the two points' colours blended
    linearly (a point without one takes ``base`` at its u); elsewhere
    ``base(u)`` (the colormap)."""
    u = np.asarray(u, np.float64)
    out = base(u)
    own = [i for i, p in enumerate(points) if len(p) > 2]
    if not own or len(points) < 2:
        return out
    pu = np.array([p[0] for p in points], np.float64)
    col = base(pu)
    col[own] = hex_rgb([points[i][2] for i in own])
    has = np.zeros(len(points), bool)
    has[own] = True
    i = np.clip(np.searchsorted(pu, u, side="right") - 1, 0, len(pu) - 2)
    width = pu[i + 1] - pu[i]
    t = np.clip(np.divide(u - pu[i], width, out=np.zeros_like(u), where=width > 0), 0.0, 1.0)
    blend = col[i] + t[:, None] * (col[i + 1] - col[i])
    return np.where((has[i] | has[i + 1])[:, None], blend, out)


@dataclass
class TFSpec:
    """The editor's state (display units; see the module docstring)."""
    points: list = field(default_factory=spiky_points)
    colormap: str = "plasma"
    log: bool = False
    range: tuple = (0.0, 1.0)
    density: float = 1.0

    def to_json(self) -> dict:
        return {"points": [[float(p[0]), float(p[1]), *p[2:]] for p in self.points], "colormap": self.colormap,
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
        return TFSpec([(float(pts[i][0]), float(pts[i][1]), *pts[i][2:]) for i in order], cmap, log, (lo, hi),
                      float(density))

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
        pts = np.array([p[:2] for p in self.points], dtype=np.float64)
        rgba = np.empty((TABLE_SIZE, 4))
        if self.colormap == "scene" and scene_rgb is not None:
            grid = np.linspace(0, 1, len(scene_rgb))

            def base(x):
                return np.stack([np.interp(x, grid, scene_rgb[:, c]) for c in range(3)], axis=1)
        else:
            def base(x):
                return matplotlib.colormaps[self.colormap](x)[:, :3]
        rgba[:, :3] = point_colours(self.points, u, base)
        rgba[:, 3] = np.interp(u, pts[:, 0], pts[:, 1])
        return TransferFunction(np.clip(rgba, 0.0, 1.0), domain)

    def file_json(self, scene_rgb: np.ndarray | None = None) -> str:
        """This TF as the JSON ``mi-amr render --tf`` reads: `TABLE_SIZE`
        entries uniform in the display units (``"log10"``: whether those are
        log10, then render with ``--log``) over the range, and the editor's
        state (``"editor"``) that `from_file` restores exactly."""
        tf = self.table(stored_log=self.log, scene_rgb=scene_rgb)
        d = json.loads(tf.to_json())
        d.update(log10=bool(self.log), editor=self.to_json())
        return json.dumps(d)

    def from_file(self, text: str, log_available: bool, colormaps=COLORMAPS) -> "TFSpec":
        """The spec of a TF JSON file's ``text``: a file `file_json` wrote
        (its editor state), or any table ``mi-amr render --tf`` reads (ours
        or a ParaView preset, which takes this spec's range as ParaView
        applies a preset unless it says ``"keep_range": true``; a domain in
        this spec's display units, or log10 where it says so; up to
        `LOADED_POINTS` points with their table colours). A `ValueError`
        says what is wrong."""
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"TF file: not JSON ({e})") from None
        if isinstance(d, dict) and isinstance(d.get("editor"), dict):
            return self.changed(parse_message(dict(d["editor"], type="tf")), log_available, colormaps)
        keep = True                                          # our own tables keep their domain
        if isinstance(d, list) or (isinstance(d, dict) and "RGBPoints" in d):
            with tempfile.TemporaryDirectory() as tmp:       # ParaView presets are read from a file
                path = Path(tmp) / "preset.json"
                path.write_text(text)
                try:
                    read = TransferFunction.read_json(path)
                except ValueError as e:
                    raise ValueError(f"TF file: {str(e).replace(str(path) + ': ', '')}") from None
                tf, keep = read.tf, read.keep_range          # a preset takes the range shown, as ParaView
                                                             # applies one, unless it keeps its own
        elif isinstance(d, dict) and "domain" in d and "rgba" in d:
            try:
                tf = TransferFunction(d["rgba"], d["domain"])
            except (ValueError, TypeError) as e:
                raise ValueError(f"TF file: {e}") from None
        else:
            raise ValueError("TF file: expected an object with 'domain' and 'rgba' (or a ParaView preset)")
        log = d.get("log10", self.log) if isinstance(d, dict) else self.log
        if not isinstance(log, bool):
            raise ValueError("TF file: 'log10' must be true or false")
        n = min(len(tf), LOADED_POINTS)
        u = np.linspace(0.0, 1.0, n)
        grid = np.linspace(0.0, 1.0, len(tf))
        rgba = np.stack([np.interp(u, grid, tf.rgba[:, c]) for c in range(4)], axis=1)
        points = [[float(a), float(b), h] for a, b, h in zip(u, rgba[:, 3], rgb_hex(rgba[:, :3]))]
        value_range = tf.domain if keep else self.range
        change = parse_message({"type": "tf", "points": points, "log": log, "range": list(map(float, value_range))})
        return self.changed(change, log_available, colormaps)


#: Bins of the fine histogram that every editor histogram is re-binned from.
FINE_BINS = VIEW_HISTOGRAM_BINS


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

    def __init__(self, volume, data=None):
        """``volume``: the medium's; ``data``: the data it was made from,
        whose ``.amrb`` file may hold this histogram already
        (`mi_amr.data.statistics.stored_fine_histogram`): then nothing is counted."""
        stored = None if data is None else stored_fine_histogram(data, volume, FINE_BINS)
        self.edges, self.cdf = stored if stored is not None else fine_histogram(volume, FINE_BINS)

    def _cdf(self, edges, spec: TFSpec, stored_log: bool) -> np.ndarray:
        """The share of the volume below each display value of ``edges``."""
        edges = np.asarray(edges, np.float64)
        if stored_log and not spec.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                edges = np.where(edges > 0, np.log10(np.maximum(edges, 1e-300)), -np.inf)
        return np.interp(edges, self.edges, self.cdf, left=0.0, right=1.0)

    def shares(self, spec: TFSpec, stored_log: bool, bins: int = 128) -> list[float]:
        """Share of the volume in each of ``bins`` display bins over ``spec.range``."""
        cdf = self._cdf(np.linspace(spec.range[0], spec.range[1], bins + 1), spec, stored_log)
        return np.maximum(np.diff(cdf), 0.0).tolist()

    def outside(self, spec: TFSpec, stored_log: bool) -> tuple[float, float]:
        """``(below, above)``: the shares of the volume below and above ``spec.range``."""
        lo, hi = self._cdf(spec.range, spec, stored_log)
        return float(lo), float(max(1.0 - hi, 0.0))
