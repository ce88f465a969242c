"""A scene made from AMR data alone, as ``yt.create_scene`` makes one: what
``mi-amr render DATA --field NAME`` renders.

`plan_scene` looks at the data once: the physical domain (the box the
medium fills, at its true aspect), the volume-weighted distribution of the
values (linear or log10 chosen from its dynamic range), a TF preset placed
over its percentiles and a density scale that makes the volume
semi-transparent. `scene_for` turns the plan into a dictionary for
``mi.load_dict``; `write_scene_xml` into an XML scene that references the
data file, to edit and re-render.

World space: the domain is centred at the origin, its longest side 1 unit,
and +z is up (simulation codes' convention, and Mitsuba's ``sunsky``: its
horizon is the plane z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from pathlib import Path
from types import SimpleNamespace
from xml.sax.saxutils import quoteattr

import mitsuba as mi
import numpy as np

from .data.blocks import BlockVolume
from .data.cells import AMRCells
from .data.opening import open_data, yt_field
from .data.transform import apply_value_transform
from .data.yt_import import field_key
from .transfer.function import PRESETS, TransferFunction
from .visibility import (OPAQUE_OPACITY, PREDICT_RES, Visibility, camera_rays, opacity_grid, projected_depth,
                         scale_for_opacity, visibility_of_depths)

#: Percentiles (of the volume and of the mass) that bound the TF domain.
LOW_PERCENTILE, HIGH_PERCENTILE = 1.0, 99.9
#: log10 is chosen when the volume's 1st and the mass's 99.9th percentiles
#: of the positive values are at least this many decades apart ...
LOG_DECADES = 2.0
#: ... and at least this share of the volume holds positive values (the rest
#: is floored: `mi_amr.data.transform`).
MIN_POSITIVE_SHARE = 0.9
#: A linear TF range leaves zeros out when they fill at least this share of
#: the volume (empty space, covered cells): they take the TF's bottom.
FLOOR_SHARE = 0.01
#: Optical depth of the mean extinction across the domain's longest side.
TARGET_DEPTH = 1.5
#: Largest optical depth across the domain's longest side at the TF's highest
#: opacity over the data's values: the planned density scale is at most
#: ``MAX_DEPTH / that opacity``. It bounds the global majorant, so the cost of
#: a render (null collisions per unit length), where a tiny mean opacity
#: would otherwise ask for a huge scale (the bundled data plan 20-480).
MAX_DEPTH = 500.0
FOV = 35.0
#: Opacity peaks at a few values, like the layered Gaussians of yt's volume
#: renderings: shells of structure rather than a fog over the whole domain.
DEFAULT_TF = "spiky"
#: The extinction TF of glowing gas unless told otherwise: grey (its
#: albedo would tint the glow, which is emitted in proportion to 1 - albedo)
#: and opacity rising with the value.
GLOW_TF = "dust"
#: Towards the sun: 50 degrees above the horizon, behind the camera's right.
SUN_DIRECTION = [0.5, 0.6, 0.9]
HISTOGRAM_BINS = 4096
#: Bins of the viewer's fine histogram of the stored values (the medium's:
#: log10 or linear), which its TF editor re-bins (`mi_amr.view.tf_spec.Histogram`).
VIEW_HISTOGRAM_BINS = 1 << 14


@dataclass
class EmissionPlan:
    """The emission of a glowing medium (the ``amr`` medium's ``emission*``
    parameters): TF preset or .json file over ``field`` (None: the
    extinction field), its transform, domain and radiance scale."""
    tf: str
    field: str | None
    transform: str
    tf_range: tuple[float, float]
    scale: float


@dataclass
class ScenePlan:
    """Everything `scene_for` and `write_scene_xml` need (world units)."""
    data: AMRCells | BlockVolume
    transform: str                    # value_transform: "none" or "log10"
    tf: str                           # a preset name or a TF .json path
    tf_range: tuple[float, float]     # in transformed units
    density_scale: float              # inverse world units
    extent: np.ndarray                # domain size, world units (longest side 1)
    origin: np.ndarray                # camera position
    fov: float = FOV
    notes: list = dc_field(default_factory=list)
    target: tuple = (0.0, 0.0, 0.0)   # the point the camera looks at
    up: tuple = (0.0, 0.0, 1.0)       # the camera's up direction
    emission: "EmissionPlan | None" = None   # a glowing medium: no sun, sky or floor
    optical_depth: float | None = None       # of the mean opacity across the longest side (planned scale)
    peak_depth: float | None = None          # at the TF's highest opacity over the values, same length
    visibility: "Visibility | None" = None   # the planned picture as predicted (`mi_amr.visibility`)

    @property
    def lit(self) -> bool:
        """Whether the scene has the sun, sky and floor (not for glowing gas,
        which is its own light, on black, as emission-absorption renderers
        show it)."""
        return self.emission is None

    def floor_height(self) -> float:
        """The ground plane, just below the domain (z up)."""
        return float(-0.5 * self.extent[2] - 0.001)

    def to_world_matrix(self) -> np.ndarray:
        """Unit cube -> the domain box centred at the origin."""
        m = np.diag([*self.extent, 1.0])
        m[:3, 3] = -0.5 * self.extent
        return m


def cells_and_weights(data, field=None):
    """Chunks of ``(values float64, volume weights)`` of the present cells
    (weights in finest-cell volumes: 8^level); ``field``: a further field
    of the data (None: the main values). ``data`` may be a list (or any
    iterable) of data sets: the chunks of all of them."""
    if hasattr(data, "weighted_values"):          # one data set (`AMRCells` or `BlockVolume`)
        yield from data.weighted_values(field)
        return
    for d in data:
        yield from cells_and_weights(d, field)


@dataclass
class ValueStats:
    """What the values of a field are, counted per cell and weighted by cell
    volume (in finest-cell volumes, 8^level): extremes, and how many are 0 or
    negative (those have no log10)."""
    cells: int = 0
    volume: float = 0.0
    zero_cells: int = 0
    zero_volume: float = 0.0
    negative_cells: int = 0
    negative_volume: float = 0.0
    min: float = np.inf
    max: float = -np.inf
    positive_min: float = np.inf      # smallest value above 0 (inf: none)
    positive_max: float = -np.inf

    @property
    def positive_volume_share(self) -> float:
        """Share of the volume whose values are above 0."""
        return 1.0 - (self.zero_volume + self.negative_volume) / self.volume if self.volume else 0.0

    @property
    def has_positive(self) -> bool:
        return bool(np.isfinite(self.positive_min))

    def span(self, log: bool) -> tuple[float, float]:
        """``(lo, hi)`` of the values, or of the log10 of the positive ones."""
        if log:
            return float(np.log10(self.positive_min)), float(np.log10(self.positive_max))
        return float(self.min), float(self.max)

    def shares(self, what: str = "values") -> str | None:
        """A note naming the shares of zeros and negatives (None: all positive)."""
        if not self.zero_cells and not self.negative_cells:
            return None
        parts = [f"{100 * v / self.volume:.3g}% of the volume ({100 * n / self.cells:.3g}% of the cells) {name}"
                 for v, n, name in ((self.zero_volume, self.zero_cells, "is 0"),
                                    (self.negative_volume, self.negative_cells, "is negative")) if n]
        return f"{what}: {' and '.join(parts)}"


def stored_stats(data, field=None) -> dict | None:
    """What an ``.amrb`` file stored of ``data``'s main values when it was
    written (`file_stats`; `mi_amr.data.amrb` reads it into
    ``BlockVolume.stored_stats``), or None: other data, a further field, an
    older file, or values changed since (their range or count differs)."""
    st = getattr(data, "stored_stats", None)
    if field is not None or not st or st.get("version") != STATS_VERSION:
        return None
    if st.get("n_cells") != int(data.n_cells) or st.get("value_range") != [float(x) for x in data.value_range]:
        return None
    return st


def value_stats(data, field=None) -> ValueStats:
    """`ValueStats` of ``field`` (None: the main values) of one data set or
    several (see `cells_and_weights`), in one pass (none for an ``.amrb``
    file's stored ones: `stored_stats`)."""
    st = stored_stats(data, field)
    if st is not None:
        return ValueStats(**{k: (np.inf if v == "inf" else -np.inf if v == "-inf" else v)
                             for k, v in st["value_stats"].items()})
    s = ValueStats()
    for v, w in cells_and_weights(data, field):
        if not v.size:
            continue
        zero, neg = v == 0, v < 0
        s.cells += v.size
        s.volume += float(w.sum())
        s.zero_cells += int(zero.sum())
        s.zero_volume += float(w[zero].sum())
        s.negative_cells += int(neg.sum())
        s.negative_volume += float(w[neg].sum())
        s.min, s.max = min(s.min, float(v.min())), max(s.max, float(v.max()))
        pos = v[v > 0]
        if pos.size:
            s.positive_min = min(s.positive_min, float(pos.min()))
            s.positive_max = max(s.positive_max, float(pos.max()))
    return s


def positive_share(data, field=None) -> float:
    """Share of the volume whose values are above 0."""
    return value_stats(data, field).positive_volume_share


def weighted_percentiles(data, qs, log: bool = False, field=None, mass: bool = False) -> list[float]:
    """Volume-weighted percentiles ``qs`` (0-100) of the values (of their
    log10 with ``log``, values <= 0 left out), from a histogram of
    `HISTOGRAM_BINS` bins: within one bin width. ``mass``: weighted by
    volume times the value's magnitude instead (where the mass of a density
    lies). ``data``: one data set or several (a time series: one histogram
    over all of them)."""
    st = stored_stats(data, field)
    if st is None:
        lo, hi, hist = _weighted_histogram(data, log, field, mass)
    else:                                          # as `file_stats` stored them
        name = _histogram_name(log, mass)
        lo, hi = st.get(name + "_span") or (np.inf, -np.inf)
        hist = st.get(name)
    if not np.isfinite(lo):
        raise ValueError("no values to place a transfer function over")
    if hi <= lo or hist is None or not np.sum(hist) > 0:
        return [lo for _ in qs]
    edges = np.linspace(lo, hi, HISTOGRAM_BINS + 1)
    cdf = np.cumsum(hist) / hist.sum()
    return [float(edges[min(int(np.searchsorted(cdf, q / 100.0)) + (q > 0), HISTOGRAM_BINS)]) for q in qs]


def _histogram_name(log: bool, mass: bool) -> str:
    """The key of a histogram in `file_stats`."""
    return f"hist_{'log' if log else 'linear'}{'_mass' if mass else ''}"


def _weighted_histogram(data, log: bool, field=None, mass: bool = False) -> tuple:
    """``(lo, hi, counts)``: the volume-weighted histogram of
    `HISTOGRAM_BINS` bins over [lo, hi], the extremes of the values (of
    their log10, values <= 0 left out); ``mass``: weighted by volume times
    the value's magnitude. ``(inf, -inf, None)`` without values, ``(lo, hi,
    None)`` when all are one value."""
    lo, hi = (np.inf, -np.inf)
    for v, _ in cells_and_weights(data, field):
        if log:
            v = v[v > 0]
            if not v.size:
                continue
            v = np.log10(v)
        if v.size:
            lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
    if not np.isfinite(lo) or hi <= lo:
        return lo, hi, None
    edges = np.linspace(lo, hi, HISTOGRAM_BINS + 1)
    hist = np.zeros(HISTOGRAM_BINS)
    for v, w in cells_and_weights(data, field):
        if mass:
            w = w * np.abs(v)
        if log:
            keep = v > 0
            v, w = np.log10(v[keep]), w[keep]
        hist += np.histogram(v, bins=edges, weights=w)[0]
    return lo, hi, hist


def fine_histogram(volume, bins: int = VIEW_HISTOGRAM_BINS) -> tuple:
    """``(edges, cdf)``: the volume-weighted cumulative distribution of
    ``volume``'s values at the edges of ``bins`` bins over its value range
    (widened by 0.5 either side when it is one value): what the viewer's TF
    editor re-bins (`mi_amr.view.tf_spec.Histogram`)."""
    lo, hi = volume.value_range
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    counts, total = np.zeros(bins), 0.0
    for v, w in cells_and_weights(volume):
        counts += np.histogram(v, bins=bins, range=(lo, hi), weights=w)[0]
        total += float(w.sum())
    return np.linspace(lo, hi, bins + 1), np.concatenate([[0.0], np.cumsum(counts)]) / (total or 1.0)


def stored_fine_histogram(data, medium_volume, bins: int = VIEW_HISTOGRAM_BINS) -> tuple | None:
    """``(edges, cdf)`` of `fine_histogram` of ``medium_volume`` (the medium's
    values: ``data``'s, or their log10) as ``data``'s ``.amrb`` file stored it
    (`file_stats`), or None (not stored, another transform, range or bin count)."""
    st = stored_stats(data)
    transform = medium_volume.meta.get("value_transform", "none") if medium_volume is not data else "none"
    entry = None if st is None else st.get(f"view_{transform}")
    if entry is None or st.get(f"view_{transform}_span") != [float(x) for x in medium_volume.value_range] \
            or len(entry) != bins + 1 or int(medium_volume.n_cells) != st["n_cells"]:
        return None
    lo, hi = medium_volume.value_range
    if not hi > lo:
        lo, hi = lo - 0.5, hi + 0.5
    return np.linspace(lo, hi, bins + 1), np.asarray(entry, np.float64)


#: Bumped whenever `file_stats` computes anything differently: files with
#: another version are planned from their values again.
STATS_VERSION = 2


def file_stats(volume: BlockVolume) -> dict:
    """What `plan_scene` and the viewer read from the values, computed when
    an ``.amrb`` file is written (`mi_amr.data.amrb.save_amrb` stores it,
    read back as ``BlockVolume.stored_stats``; docs/performance/view.md
    "The first picture"): `value_stats`, the histograms of
    `weighted_percentiles` (linear and log10), the mean opacity of the
    default plan's TF (`_mean_alpha`, for `DEFAULT_TF` over the range
    `plan_scene` chooses) and the viewer's fine histograms of the values
    as its medium holds them (linear, and log10 when the viewer would store
    them so). Numbers are JSON values, arrays float64 arrays; each is what
    the same function computes from the values, so a plan from the file is
    the plan from the values."""
    vs = value_stats(volume)
    out = {"version": STATS_VERSION, "n_cells": int(volume.n_cells),
           "value_range": [float(x) for x in volume.value_range],
           "value_stats": {k: (("inf" if v > 0 else "-inf") if isinstance(v, float) and np.isinf(v) else v)
                           for k, v in vs.__dict__.items()}}
    if not vs.cells:
        return out
    for log in (False, True):
        for mass in (False, True):
            name = _histogram_name(log, mass)
            lo, hi, hist = _weighted_histogram(volume, log, mass=mass)
            out[name + "_span"] = [float(lo), float(hi)] if np.isfinite(lo) else None
            if hist is not None:
                out[name] = hist
    try:     # the choice of scale and range from the histograms just made (not counted again)
        log, value_range, _, _ = _value_scale(SimpleNamespace(stored_stats=out, n_cells=volume.n_cells,
                                                              value_range=volume.value_range), None, None, None)
        out["mean_alpha"] = [{"tf": DEFAULT_TF, "range": list(value_range), "log": log,
                              "value": _mean_alpha(volume, DEFAULT_TF, value_range, log)}]
    except ValueError:
        pass
    out["view_none"], out["view_none_span"] = fine_histogram(volume)[1], [float(x) for x in volume.value_range]
    planned_log = out.get("mean_alpha", [{}])[0].get("log")
    if vs.has_positive and volume.meta.get("value_transform") != "log10" and \
            (planned_log or vs.positive_volume_share >= MIN_POSITIVE_SHARE):     # as `mi_amr.view.scene` decides
        logged, _ = apply_value_transform(volume, "log10")
        out["view_log10"], out["view_log10_span"] = fine_histogram(logged)[1], [float(x) for x in logged.value_range]
    return out



def _value_scale(stats, field, log, value_range, what="values", source="the data"):
    """``(log, (lo, hi), notes, ValueStats)``: log10 or linear values and the
    TF domain for ``field`` of ``stats`` (one data set or several), by the
    rule of `plan_scene` (docs/manual/data.md "Default pictures").

    log10 is chosen when at least `MIN_POSITIVE_SHARE` of the volume holds
    positive values and the volume's and the mass's distributions together
    span at least `LOG_DECADES` decades: from the volume's 1st percentile
    to the mass's 99.9th (the mass: volume times value, where a density
    keeps its matter). The TF range covers where the volume lies (its
    1st-99.9th percentiles) and where the mass lies (the same percentiles
    of the mass); with log10 zeros and negatives take the TF's bottom (the
    medium raises them to the smallest positive value, at or below the
    range). A value that fills at least `FLOOR_SHARE` of the volume below
    all others (zeros: empty space, an embedded boundary's covered cells) is
    left out of a linear range and takes the TF's bottom. A range is never
    widened beyond the data's distributions; only one value gets a range
    centred on it."""
    vs = value_stats(stats, field)
    notes = []
    if not vs.cells:
        raise ValueError(f"{source}: no values to place a transfer function over")
    share_note = vs.shares(what)
    vol = mass = None                 # log10 percentiles of the volume and of the mass
    if log is None:
        share = vs.positive_volume_share
        if vs.has_positive:
            vol = weighted_percentiles(stats, [LOW_PERCENTILE, HIGH_PERCENTILE], log=True, field=field)
            mass = weighted_percentiles(stats, [LOW_PERCENTILE, HIGH_PERCENTILE], log=True, field=field, mass=True)
        decades = max(vol[1], mass[1]) - min(vol[0], mass[0]) if vol else 0.0
        log = bool(share >= MIN_POSITIVE_SHARE and decades >= LOG_DECADES)
        if log:
            notes.append(f"log10 chosen for the {what}: the volume lies from 10^{vol[0]:.3g} "
                         f"and the mass up to 10^{max(vol[1], mass[1]):.3g} ({decades:.2g} decades; "
                         f"log10 from {LOG_DECADES:g})")
        elif share < MIN_POSITIVE_SHARE:
            notes.append(f"linear {what}: only {100 * share:.3g}% of the volume holds positive ones "
                         f"(log10 needs {100 * MIN_POSITIVE_SHARE:.0f}%; --log to force it)")
        else:
            notes.append(f"linear {what}: the volume and the mass lie within {decades:.2g} decades "
                         f"(log10 from {LOG_DECADES:g}; --log to force it)")
    if log and not vs.has_positive:
        raise ValueError(f"{source}: log10 of the {what} needs positive values, but none is above 0 "
                         f"(min {vs.min:.6g}, max {vs.max:.6g}); use --linear")
    if share_note:
        notes.append(share_note + ("; the log10 range is of the positive ones, zeros and negatives take the "
                                   f"TF's bottom (raised to the smallest positive value, {vs.positive_min:.4g})"
                                   if log else ""))
    if value_range is None:
        value_range, note = _planned_range(stats, field, vs, log, vol, mass, what)
        if note:
            notes.append(note)
    value_range = (float(value_range[0]), float(value_range[1]))
    if not value_range[1] > value_range[0]:
        raise ValueError(f"the TF range must have LO < HI, got {value_range}")
    return bool(log), value_range, notes, vs


def _planned_range(stats, field, vs: ValueStats, log: bool, vol=None, mass=None, what="values"):
    """``((lo, hi), note or None)``: the TF range of `_value_scale` in the
    chosen space (``vol``, ``mass``: the log10 percentiles when known)."""
    qs = [LOW_PERCENTILE, HIGH_PERCENTILE]
    if log:
        vol = vol or weighted_percentiles(stats, qs, log=True, field=field)
        mass = mass or weighted_percentiles(stats, qs, log=True, field=field, mass=True)
        lo, hi = vol[0], max(vol[1], mass[1])
        note = None
    else:
        vol = weighted_percentiles(stats, qs, field=field)
        mass = weighted_percentiles(stats, qs, field=field, mass=True)
        floor = vs.min == 0 and vs.zero_volume >= FLOOR_SHARE * vs.volume
        if floor:                                 # zeros fill a share of the volume: the TF's bottom
            lo, hi = (mass[0], mass[1]) if mass[1] > mass[0] else (0.0, mass[1])
            note = (f"{what}: {100 * vs.zero_volume / vs.volume:.3g}% of the volume is 0 (empty space or "
                    f"covered cells): left out of the TF range, they take its bottom")
        else:
            lo, hi = min(vol[0], mass[0]), max(vol[1], mass[1])
            note = None
    if hi > lo:
        return (float(lo), float(hi)), note
    pad = max(0.5, 1e-3 * abs(lo))              # one value: centre it
    return (lo - pad, lo + pad), (f"the {what} are one value, {lo:.6g}{' (log10 units)' if log else ''}: "
                                  f"the TF range is centred on it")


def _check_tf_name(tf, flag):
    if tf not in PRESETS and not Path(tf).is_file():
        import matplotlib
        if tf not in matplotlib.colormaps:
            raise ValueError(f"{flag}: '{tf}' is neither a preset ({', '.join(PRESETS)}), a matplotlib "
                             f"colormap nor a TF .json file")


def plan_scene(data, field=None, *, tf: str | None = None, log: bool | None = None, value_range=None,
               density_scale: float | None = None, emission: str | None = None,
               emission_field: str | None = None, emission_log: bool | None = None, emission_range=None,
               emission_scale: float | None = None, stats=None) -> ScenePlan:
    """Look at the data once and plan a scene (see the module docstring).

    ``log``: None chooses log10 when at least 90% of the volume holds
    positive values and their 1st and 99.9th volume-weighted percentiles
    are more than 1000x apart;
    ``value_range``: the TF domain (in transformed units), else those
    volume's and the mass's percentiles (`_value_scale`); ``tf``: a preset
    name or a TF .json file (None: `DEFAULT_TF`, which the check below may
    change); ``density_scale`` (inverse world units, the longest side
    1): else `TARGET_DEPTH` over the mean opacity, at most `MAX_DEPTH` over
    the TF's highest opacity over the values (`_planned_density_scale`).
    Then the plan is checked as a user would look at it: the picture is
    predicted (`mi_amr.visibility`) and, when nearly
    nothing of the data shows or the footprint is a flat opaque block, the
    TF (if not given) and the density scale (if not given) are planned
    again, each change with a note (`_checked`).
    ``emission``: an emission TF (preset such as ``blackbody``, colormap
    or .json file) makes the gas glow, from ``emission_field`` (a further
    field, e.g. ``temperature``; None: the extinction field), with its own
    ``emission_log``/``emission_range`` chosen by the same rule and a
    radiance scale (``emission_scale``, default: one that makes the mean
    glow of the absorbing gas 1); the scene then has no other light.
    ``stats``: the data sets whose values choose the scales and ranges
    (default: ``data``): all outputs of a time series, so that one TF
    range serves every frame."""
    fields = (emission_field,) if emission is not None and emission_field else ()
    volume, extent, what = open_data(data, field, fields)
    stats = volume if stats is None else stats
    notes = [f"data: {what}"]
    log, value_range, more, vs = _value_scale(stats, None, log, value_range, source=what)
    notes += more
    transform = "log10" if log else "none"
    tf_given, scale_given = tf is not None, density_scale is not None
    tf = DEFAULT_TF if tf is None else tf
    _check_tf_name(tf, "--tf")
    world = extent / extent.max()
    mean = _mean_alpha(stats, tf, value_range, log)
    peak = _peak_alpha(tf, value_range, log, vs)
    depth_note = ""
    if density_scale is None:
        density_scale, depth_note = _planned_density_scale(mean, peak)
    depth, peak_depth = density_scale * mean, density_scale * peak
    notes.append(f"TF '{tf}' over [{value_range[0]:.4g}, {value_range[1]:.4g}]"
                 f"{' (log10 units)' if log else ''}, density_scale {density_scale:.3g}: optical depth "
                 f"{depth:.3g} across the longest side at the mean opacity {mean:.3g}, {peak_depth:.3g} at the "
                 f"TF's highest opacity over the values ({peak:.3g}){depth_note}")
    glow = None
    if emission is not None:
        _check_tf_name(emission, "--emission")
        key = None
        if emission_field:
            key = field_key(yt_field(emission_field))
            if key not in volume.fields:
                have = ", ".join(repr(n) for n in sorted(volume.fields)) or "none besides the main one"
                raise ValueError(f"{what}: no field {key!r} for the emission (further fields: {have})")
        e_log, e_range, more, _ = _value_scale(stats, key, emission_log, emission_range,
                                               f"{key or 'extinction'} values", source=what)
        notes += more
        if key is None and log:               # the extinction field is log10 already in the medium
            e_log = False
        if emission_scale is None:
            emission_scale = 1.0 / max(_mean_glow(stats, key, emission, e_range, e_log, tf, value_range, log), 1e-12)
        glow = EmissionPlan(emission, key, "log10" if e_log else "none", e_range, float(emission_scale))
        notes.append(f"emission '{emission}' over {key or 'the extinction field'} in [{e_range[0]:.4g}, "
                     f"{e_range[1]:.4g}]{' (log10 units)' if e_log else ''}, emission_scale {emission_scale:.3g}")
    radius = 0.5 * float(np.linalg.norm(world))
    direction = np.array([1.5, 1.0, 0.35]) / np.linalg.norm([1.5, 1.0, 0.35])    # just above the horizon
    origin = direction * radius / np.sin(np.radians(FOV / 2)) * 1.1
    plan = ScenePlan(volume, transform, tf, value_range, float(density_scale), world, origin, notes=notes,
                     emission=glow, optical_depth=float(depth), peak_depth=float(peak_depth))
    return _checked(plan, stats, vs, tf_given, scale_given)


#: The plan's check: a predicted picture showing the data in less than this
#: share of the domain's footprint is planned again ...
MIN_SHOWN = 0.02
#: ... and so is one opaque in at least this share of the pixels that show
#: the data (a flat opaque block: nothing inside can be seen).
MAX_OPAQUE = 0.9
#: A re-planned density makes this share of the footprint's pixels that see
#: any medium reach `mi_amr.visibility.OPAQUE_OPACITY` (too opaque) or half
#: opacity (too faint).
REPLAN_SHARE = 0.5
#: TF used when the planned one is transparent at every value the data hold.
FALLBACK_TF = "ramp"


def _checked(plan: ScenePlan, stats, vs: ValueStats, tf_given: bool, scale_given: bool) -> ScenePlan:
    """``plan`` after its check (docs/manual/data.md "Default pictures"):
    predict the picture (`mi_amr.visibility`); when it shows the data in
    under `MIN_SHOWN` of the footprint, take `FALLBACK_TF` if the TF is
    transparent at every value the data hold (and was not given), then
    raise the density scale (if not given) within the `MAX_DEPTH` bound;
    when at least `MAX_OPAQUE` of what shows is opaque, lower it. Each
    change is a note; the last prediction is ``plan.visibility``."""
    log = plan.transform == "log10"
    rays = camera_rays(plan.origin, plan.target, plan.up, plan.fov, PREDICT_RES)

    def depths(tf):
        fn = TransferFunction.load(tf, plan.tf_range)
        grid = opacity_grid(plan.data, lambda v: fn(_log_or_floor(v) if log else v)[:, 3])
        return projected_depth(grid, plan.extent, *rays)
    tau, hits = depths(plan.tf)
    seen = visibility_of_depths(tau, hits, plan.density_scale)
    if seen.shown < MIN_SHOWN and not tau.any() and not tf_given:
        tau_b, hits_b = depths(FALLBACK_TF)
        if tau_b.any():
            mean = _mean_alpha(stats, FALLBACK_TF, plan.tf_range, log)
            peak = _peak_alpha(FALLBACK_TF, plan.tf_range, log, vs)
            scale = plan.density_scale if scale_given else _planned_density_scale(mean, peak)[0]
            plan.notes.append(f"check: TF '{plan.tf}' is transparent at every value the data hold (nothing would "
                              f"show): TF '{FALLBACK_TF}' instead, density_scale {scale:.3g}")
            plan.tf, plan.density_scale, tau, hits = FALLBACK_TF, float(scale), tau_b, hits_b
            plan.optical_depth, plan.peak_depth = scale * mean, scale * peak
            seen = visibility_of_depths(tau, hits, plan.density_scale)
    if not scale_given and tau.any():
        bound = MAX_DEPTH / plan.peak_depth * plan.density_scale if plan.peak_depth else np.inf
        new = None
        if seen.shown < MIN_SHOWN:
            new = max(plan.density_scale, min(scale_for_opacity(tau, hits, REPLAN_SHARE, 0.5), bound))
            why = f"shows the data in {100 * seen.shown:.2g}% of the footprint"
        elif seen.opaque >= MAX_OPAQUE * seen.shown:
            new = min(plan.density_scale, scale_for_opacity(tau, hits, REPLAN_SHARE, OPAQUE_OPACITY))
            why = (f"is opaque in {100 * seen.opaque:.3g}% of the footprint, nearly all it shows "
                   f"({100 * seen.shown:.3g}%): a flat block")
        if new is not None and new > 0 and abs(np.log(new / plan.density_scale)) > 0.05:
            after = visibility_of_depths(tau, hits, new)
            plan.notes.append(f"check: the picture {why} at density_scale {plan.density_scale:.3g}: "
                              f"{new:.3g} instead{' (the bound)' if new == bound else ''}")
            ratio = new / plan.density_scale
            plan.density_scale, plan.optical_depth, plan.peak_depth = \
                float(new), plan.optical_depth * ratio, plan.peak_depth * ratio
            seen = after
    plan.visibility = seen
    plan.notes.append(f"predicted picture: {seen}")
    return plan


def planned_display(data, stored, log: bool, table) -> tuple[tuple[float, float], float]:
    """``((lo, hi), density_scale)`` that `plan_scene` chooses for ``data``
    shown in ``log`` (log10) or linear units with a TF of the caller's
    (``table(range) -> TransferFunction`` over the medium's stored values
    ``stored``, a `BlockVolume`): the viewer's log10 toggle re-plans both,
    so that a linear plan's density never carries over to a log10 display
    (or back). The range is in the display's units."""
    _, value_range, _, _ = _value_scale(data, None, log, None)
    fn = table(value_range)
    total = weight = 0.0
    for v, w in cells_and_weights(stored):
        total += float((fn(v)[:, 3] * w).sum())
        weight += float(w.sum())
    lo, hi = stored.value_range
    peak = float(fn.max_alpha(lo, hi)[0])
    return value_range, _planned_density_scale(total / weight if weight else 0.0, peak)[0]


def _planned_density_scale(mean, peak) -> tuple[float, str]:
    """``(density_scale, note)``: `TARGET_DEPTH` across the longest side (1
    world unit) at the ``mean`` opacity, but at most `MAX_DEPTH` at the
    ``peak`` opacity (the global majorant's bound), with a note when that
    cap applies."""
    scale = TARGET_DEPTH / max(mean, 1e-6)
    if peak > 0 and scale * peak > MAX_DEPTH:
        return MAX_DEPTH / peak, (f"; capped (the mean opacity asked for {scale:.3g}, optical depth {scale * peak:.3g} "
                                  f"at the highest opacity, over the bound {MAX_DEPTH:g}: a render's cost)")
    return scale, f" (bound {MAX_DEPTH:g})"


def _peak_alpha(tf, value_range, log, vs: ValueStats) -> float:
    """The TF's highest opacity over the values the data can take (between
    their extremes, interpolation included; with log10, zeros and negatives
    at the TF's bottom): density_scale times it is the global majorant."""
    fn = TransferFunction.load(tf, value_range)
    lo, hi = vs.span(log)
    if log and (vs.zero_cells or vs.negative_cells):
        lo = min(lo, value_range[0])
    return float(fn.max_alpha(lo, hi)[0])


def _log_or_floor(v):
    """log10 of values, -inf for those <= 0 (they take the TF's low end)."""
    return np.log10(np.where(v > 0, v, 1.0)) - np.where(v > 0, 0.0, np.inf)


def _mean_glow(stats, key, emission, e_range, e_log, tf, value_range, log) -> float:
    """Mean brightness ``alpha * max(rgb)`` of the emission TF over the
    cells, weighted by their volume and extinction opacity (the gas that
    absorbs is the gas that glows)."""
    em = TransferFunction.load(emission, e_range)
    fn = TransferFunction.load(tf, value_range)
    total = weight = 0.0
    for (v, w), (g, _) in zip(cells_and_weights(stats), cells_and_weights(stats, key)):
        a = fn(_log_or_floor(v) if log else v)[:, 3] * w
        if key is None and log:
            g = _log_or_floor(g)
        e = em(_log_or_floor(g) if e_log else g)
        total += float((e[:, 3] * e[:, :3].max(axis=1) * a).sum())
        weight += float(a.sum())
    return total / weight if weight else 0.0


def _mean_alpha(volume, tf, value_range, log) -> float:
    """Volume-weighted mean TF opacity of the cells (an ``.amrb`` file's
    stored one for the TF, range and scale it was stored for: `file_stats`)."""
    st = stored_stats(volume)
    for m in () if st is None else st.get("mean_alpha", ()):
        if (m["tf"], m["range"], m["log"]) == (tf, [float(x) for x in value_range], bool(log)):
            return float(m["value"])
    fn = TransferFunction.load(tf, value_range)
    total = weight = 0.0
    for v, w in cells_and_weights(volume):
        if log:      # values <= 0 take the floor, below the range: the TF's low end
            v = _log_or_floor(v)
        total += float((fn(v)[:, 3] * w).sum())
        weight += float(w.sum())
    return total / weight if weight else 0.0


def scene_for(data, field=None, *, res: int = 400, spp: int = 64, integrator: str = "amrvolpath",
              mode: str | None = None, **options) -> dict:
    """A scene dictionary for ``mi.load_dict`` that shows ``data`` (see
    `open_data`) with no scene written by hand; ``options`` go to
    `plan_scene` (``tf``, ``log``, ``value_range``, ``density_scale``);
    ``mode``: the ``amrvolpath`` lighting mode (None: its default)."""
    plan = data if isinstance(data, ScenePlan) else plan_scene(data, field, **options)
    T = mi.ScalarTransform4f

    def matrix(m):       # the numbers `write_scene_xml` writes, so that both render the same image
        return T(mi.ScalarMatrix4f(_as_written(m).reshape(4, 4).astype(np.float32)))
    T4d = getattr(mi, "ScalarTransform4d", T)            # the XML's look-at is computed in double precision
    camera = T4d().look_at(*(_as_written(v).tolist() for v in (plan.origin, plan.target, plan.up)))
    medium = {"type": "amr", "data": plan.data, "transfer_function": plan.tf,
              "tf_min": plan.tf_range[0], "tf_max": plan.tf_range[1], "value_transform": plan.transform,
              "density_scale": plan.density_scale, "to_world": matrix(plan.to_world_matrix())}
    medium.update(emission_parameters(plan))
    scene = {
        "type": "scene",
        "integrator": dict({"type": integrator, "max_depth": 64}, **({} if mode is None else {"mode": mode})),
        "sensor": {"type": "perspective", "fov": plan.fov,
                   "to_world": T(mi.ScalarMatrix4f(np.array(camera.matrix, dtype=np.float64).astype(np.float32))),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "volume": {"type": "cube", "to_world": matrix(_cube_matrix(plan)),
                   "bsdf": {"type": "null"}, "interior": medium},
    }
    if plan.lit:
        scene["sky"] = {"type": "sunsky", "sun_direction": SUN_DIRECTION, "turbidity": 3.0,
                        "sun_scale": 2.5, "sky_scale": 6.0}
        scene["floor"] = {"type": "rectangle",
                          "to_world": T().translate([0, 0, float(f"{plan.floor_height():.6g}")]) @ T().scale(1000),
                          "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.45}}}
    return scene


def _as_written(values) -> np.ndarray:
    """``values`` as `write_scene_xml` writes them (9 significant digits)."""
    return np.array([float(f"{float(x):.9g}") for x in np.ravel(values)])


def _cube_matrix(plan: ScenePlan) -> np.ndarray:
    """``to_world`` of the cube that bounds the medium (Mitsuba's cube
    spans -1..1)."""
    return plan.to_world_matrix() @ np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 0.5, 0.5], [0, 0, 0, 1.0]])


def emission_parameters(plan: ScenePlan) -> dict:
    """The ``amr`` medium's ``emission*`` parameters of a plan ({} for gas
    that does not glow)."""
    e = plan.emission
    if e is None:
        return {}
    out = {"emission": e.tf, "emission_transform": e.transform, "emission_min": e.tf_range[0],
           "emission_max": e.tf_range[1], "emission_scale": e.scale}
    if e.field is not None:
        out["emission_field"] = e.field
    return out


def _tf_reference(tf: str) -> str:
    """How a scene file names a TF: a preset or colormap by its name, a TF
    file by its absolute path (the scene renders from any folder)."""
    return str(Path(tf).resolve()) if tf not in PRESETS and Path(tf).is_file() else str(tf)


def write_scene_xml(plan: ScenePlan, data_file, path, res: int = 400, spp: int = 64,
                    mode: str | None = None) -> Path:
    """Write ``plan`` as an XML scene that loads ``data_file`` (``res`` and
    ``spp`` are its defaults, ``-D res=...`` overrides them; ``mode``: the
    ``amrvolpath`` lighting mode, written unless None)."""
    path = Path(path)
    mode_line = "" if mode is None else f"\n        <string name=\"mode\" value={quoteattr(str(mode))}/>"
    m = plan.to_world_matrix()
    matrix = " ".join(f"{x:.9g}" for x in m.ravel())
    cube_matrix = " ".join(f"{x:.9g}" for x in _cube_matrix(plan).ravel())
    o, t, u = (", ".join(f"{float(x):.9g}" for x in v) for v in (plan.origin, plan.target, plan.up))
    # an XML comment may not hold "--" (the notes name flags such as --log)
    notes = "\n         ".join(n.replace("--", "- -") for n in plan.notes)
    glow_params = {k: _tf_reference(v) if k == "emission" else v for k, v in emission_parameters(plan).items()}
    glow = "".join(f"\n        <{'float' if isinstance(v, float) else 'string'} name=\"{k}\" value="
                   f"{quoteattr(format(v, '.9g') if isinstance(v, float) else str(v))}/>"
                   for k, v in glow_params.items())
    lights = "" if not plan.lit else f"""
    <emitter type="sunsky">
        <vector name="sun_direction" value="{', '.join(str(x) for x in SUN_DIRECTION)}"/>
        <float name="turbidity" value="3"/>
        <float name="sun_scale" value="2.5"/>
        <float name="sky_scale" value="6"/>
    </emitter>

    <shape type="rectangle">  <!-- the ground, just below the domain -->
        <transform name="to_world">
            <scale value="1000"/>
            <translate z="{plan.floor_height():.6g}"/>
        </transform>
        <bsdf type="diffuse">
            <rgb name="reflectance" value="0.45"/>
        </bsdf>
    </shape>
"""
    text = f"""<scene version="3.0.0">
    <!-- made by mi-amr from the data alone; edit and re-render with
         mi-amr render {path.name} -o OUT.exr
         {notes} -->
    <default name="spp" value="{spp}"/>
    <default name="res" value="{res}"/>

    <integrator type="amrvolpath">
        <integer name="max_depth" value="64"/>{mode_line}
    </integrator>

    <sensor type="perspective">
        <float name="fov" value="{plan.fov}"/>
        <transform name="to_world">
            <lookat origin="{o}" target="{t}" up="{u}"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="$res"/>
            <integer name="height" value="$res"/>
            <rfilter type="box"/>
        </film>
    </sensor>
{lights}
    <medium type="amr" id="volume">
        <string name="filename" value={quoteattr(str(data_file))}/>
        <string name="transfer_function" value={quoteattr(_tf_reference(plan.tf))}/>
        <float name="tf_min" value="{plan.tf_range[0]:.9g}"/>
        <float name="tf_max" value="{plan.tf_range[1]:.9g}"/>
        <string name="value_transform" value="{plan.transform}"/>
        <float name="density_scale" value="{plan.density_scale:.9g}"/>{glow}
        <transform name="to_world">
            <matrix value="{matrix}"/>
        </transform>
    </medium>

    <shape type="cube">
        <transform name="to_world">
            <matrix value="{cube_matrix}"/>
        </transform>
        <bsdf type="null"/>
        <ref name="interior" id="volume"/>
    </shape>
</scene>
"""
    path.write_text(text)
    return path
