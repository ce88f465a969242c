"""A scene planned from AMR data alone, as ``yt.create_scene`` plans one:
what ``mi-amr render DATA --field NAME`` renders.

`plan_scene` looks at the data once (their statistics:
`mi_amr.data.statistics`): the physical domain (the box the medium fills,
at its true aspect), log10 or linear from where the volume and the mass of
the values lie, a TF preset over the range they span and a density scale
that makes the volume semi-transparent, then checks the predicted picture
(`mi_amr.visibility`) and plans again where it would show nothing or a flat
opaque block (docs/manual/data.md "Default pictures"). `mi_amr.scene_writer`
turns a plan into a scene dictionary or an XML scene.

World space: the domain is centred at the origin, its longest side 1 unit,
and +z is up (simulation codes' convention, and Mitsuba's ``sunsky``: its
horizon is the plane z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .data.blocks import BlockVolume
from .data.cells import AMRCells
from .data.opening import open_data, yt_field
from .data.statistics import (STATS_VERSION, ValueStats, cells_and_weights, fine_histogram, histogram_name,
                              stored_stats, value_stats, volume_and_mass_percentiles, weighted_histograms)
from .data.transform import apply_value_transform
from .data.yt_import import field_key
from .plugins.iso_surfaces import parse_iso_values
from .transfer.function import PRESETS, TransferFunction
from .transfer.layers import Layers, is_layers
from .transfer.spectra import blackbody_luminance
from .visibility import (OPAQUE_OPACITY, PREDICT_RES, LayersSeen, Visibility, camera_rays, layer_weights,
                         layers_opacity, layers_seen, opacity_grid, projected_depth, ray_samples, scale_for_opacity,
                         visibility_of_depths)

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
DEFAULT_TF = "layers"
#: ``--emission blackbody``: Planck's law at the emission field in kelvin
#: (the medium's ``emission_model="blackbody"``), not the TF preset of that
#: name (docs/manual/glowing-gas.md).
BLACKBODY = "blackbody"
#: The extinction TF of glowing gas unless told otherwise: grey (its
#: albedo would tint the glow, which is emitted in proportion to 1 - albedo)
#: and opacity rising with the value.
GLOW_TF = "dust"


@dataclass
class EmissionPlan:
    """The emission of a glowing medium (the ``amr`` medium's ``emission*``
    parameters): TF preset or .json file over ``field`` (None: the
    extinction field), its transform, domain and radiance scale; or, with
    ``model`` ``blackbody``, Planck's law at the field in kelvin (``tf``
    then names it, the range is the field's, for the notes)."""
    tf: str
    field: str | None
    transform: str
    tf_range: tuple[float, float]
    scale: float
    model: str = "tf"


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
    layers: "LayersSeen | None" = None       # a layered TF's layers the picture is predicted to show
    value_range: tuple | None = None         # the range the values' distributions give (`_value_scale`);
                                             # a layered default's ``tf_range`` lies within it
    iso: tuple = ()                          # isosurface values, in the field's own units
    iso_only: bool = False                   # the surfaces alone (the medium's density off)

    def medium_iso(self) -> tuple:
        """The iso values in the medium's value units (log10 of them where
        the plan takes log10 of the field); a `ValueError` for a value a
        log10 medium cannot hold (zero or negative)."""
        if self.transform != "log10":
            return tuple(float(v) for v in self.iso)
        bad = [v for v in self.iso if not v > 0.0]
        if bad:
            raise ValueError(f"iso: the field is drawn in log10 units, so iso values must be positive, got "
                             f"{', '.join(f'{v:g}' for v in bad)} (or plan it linear: --linear / log=False)")
        return tuple(float(np.log10(v)) for v in self.iso)

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
        lo, hi, *hists = weighted_histograms(volume, log)
        for mass, hist in zip((False, True), hists):
            name = histogram_name(log, mass)
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
            vol, mass = volume_and_mass_percentiles(stats, [LOW_PERCENTILE, HIGH_PERCENTILE], True, field)
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
        if vol is None:
            vol, mass = volume_and_mass_percentiles(stats, qs, True, field)
        lo, hi = vol[0], max(vol[1], mass[1])
        note = None
    else:
        vol, mass = volume_and_mass_percentiles(stats, qs, False, field)
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
    if is_layers(tf):
        Layers.parse(tf)                          # its options, checked: a ValueError names the bad one
        return
    if tf not in PRESETS and not Path(tf).is_file():
        import matplotlib
        if tf not in matplotlib.colormaps:
            raise ValueError(f"{flag}: '{tf}' is neither a preset ({', '.join(PRESETS)}), a matplotlib "
                             f"colormap nor a TF .json file")


def plan_scene(data, field=None, *, tf: str | None = None, log: bool | None = None, value_range=None,
               density_scale: float | None = None, emission: str | None = None,
               emission_field: str | None = None, emission_log: bool | None = None, emission_range=None,
               emission_scale: float | None = None, stats=None, iso=None, iso_only: bool = False) -> ScenePlan:
    """Look at the data once and plan a scene (see the module docstring).

    ``log``: None chooses log10 when at least `MIN_POSITIVE_SHARE` of the
    volume holds positive values and they span at least `LOG_DECADES`
    decades, from the volume-weighted 1st percentile to the mass-weighted
    (volume times value) 99.9th;
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
    ``emission``: an emission TF (a preset, colormap or .json file), or
    ``blackbody`` (`BLACKBODY`: Planck's law at the field in kelvin, no TF
    and no log10), makes the gas glow, from ``emission_field`` (a further
    field, e.g. ``temperature``; None: the extinction field), with its own
    ``emission_log``/``emission_range`` chosen by the same rule and a
    radiance scale (``emission_scale``, default: one that makes the mean
    glow of the absorbing gas 1); the scene then has no other light.
    ``stats``: the data sets whose values choose the scales and ranges
    (default: ``data``): all outputs of a time series, so that one TF
    range serves every frame. ``iso``: isosurface values in the field's
    own units (at most 4; docs/manual/isosurfaces.md), ``iso_only``: the
    surfaces alone."""
    iso = parse_iso_values(iso, "iso")
    if iso_only and not iso:
        raise ValueError("iso_only: needs iso values (--iso V ...)")
    fields = (emission_field,) if emission is not None and emission_field else ()
    volume, extent, what = open_data(data, field, fields)
    stats = volume if stats is None else stats
    notes = [f"data: {what}"]
    range_given = value_range is not None
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
        if emission != BLACKBODY:
            _check_tf_name(emission, "--emission")
        key = None
        if emission_field:
            key = field_key(yt_field(emission_field))
            if key not in volume.fields:
                have = ", ".join(repr(n) for n in sorted(volume.fields)) or "none besides the main one"
                raise ValueError(f"{what}: no field {key!r} for the emission (further fields: {have})")
        if emission == BLACKBODY and key is None and log:
            raise ValueError(f"{what}: --emission blackbody reads the emission field in kelvin, and the extinction "
                             f"field is drawn in log10 units: name the temperature with --emission-field, or pass "
                             f"--linear")
        e_log, e_range, more, _ = _value_scale(stats, key, False if emission == BLACKBODY else emission_log,
                                               emission_range, f"{key or 'extinction'} values", source=what)
        notes += more
        if key is None and log:               # the extinction field is log10 already in the medium
            e_log = False
        model = "blackbody" if emission == BLACKBODY else "tf"
        if emission_scale is None:
            mean = (_mean_blackbody_glow(stats, key, tf, value_range, log) if model == "blackbody"
                    else _mean_glow(stats, key, emission, e_range, e_log, tf, value_range, log))
            emission_scale = 1.0 / max(mean, 1e-12)
        glow = EmissionPlan(emission, key, "log10" if e_log else "none", e_range, float(emission_scale), model)
        notes.append(f"emission '{emission}' over {key or 'the extinction field'} in [{e_range[0]:.4g}, "
                     f"{e_range[1]:.4g}]{' (log10 units)' if e_log else ''}, emission_scale {emission_scale:.3g}")
    radius = 0.5 * float(np.linalg.norm(world))
    direction = np.array([1.5, 1.0, 0.35]) / np.linalg.norm([1.5, 1.0, 0.35])    # just above the horizon
    origin = direction * radius / np.sin(np.radians(FOV / 2)) * 1.1
    plan = ScenePlan(volume, transform, tf, value_range, float(density_scale), world, origin, notes=notes,
                     emission=glow, optical_depth=float(depth), peak_depth=float(peak_depth),
                     value_range=value_range, iso=iso, iso_only=bool(iso_only))
    if iso:
        plan.medium_iso()                    # a value log10 units cannot hold: refused before any rendering
        notes.append(f"isosurfaces at {', '.join(f'{v:.4g}' for v in iso)}{' (alone)' if iso_only else ''}")
    alpha_grid = None
    if is_layers(tf):
        planned, alpha_grid = _planned_layers(plan, stats, vs, tf_given, scale_given, range_given)
        scale_given |= planned
    return _checked(plan, stats, vs, tf_given, scale_given, alpha_grid)


#: The first layer's opacities (relative to the last's, 1) the plan tries for
#: the default layered TF ...
LAYER_LOWS = np.logspace(-3.5, 0.0, 8)
#: ... and the density scales, times the one that gives `TARGET_DEPTH` at
#: the layers' mean opacity.
LAYER_SCALES = np.exp2(np.arange(-6.0, 6.01, 1.0))
#: A plan whose layers tint less than this share of the footprint shows
#: none of them.
MIN_TINTED = 0.2
#: Pixels per side and steps of the rays the search predicts layers with.
LAYER_SEARCH_RES, LAYER_SEARCH_STEPS = 32, 64


#: The default layered TF spans the values that the picture's pixels reach
#: at most along their rays, from this quantile of the pixels to that one
#: (within the planned range): each layer then shows over a comparable
#: share of the picture.
PIXEL_QUANTILES = (0.05, 0.95)


def _pixel_range(plan: ScenePlan, log: bool):
    """``(lo, hi)`` (transformed units) of the largest values along the
    check's camera rays through the voxel grid of the values' means
    (`opacity_grid` of the values), at the `PIXEL_QUANTILES` of the
    footprint's pixels, within the planned range; None when they do not
    span a range."""
    lo, hi = plan.tf_range

    def value_and_presence(v):
        x = np.maximum(_log_or_floor(v), lo) if log else v
        return np.stack([x, np.ones_like(x)], axis=1)
    grid = opacity_grid(plan.data, value_and_presence)
    values = np.where(grid[..., 1] > 0, grid[..., 0] / np.where(grid[..., 1] > 0, grid[..., 1], 1.0), -np.inf)
    rays = camera_rays(plan.origin, plan.target, plan.up, plan.fov, PREDICT_RES)
    samples, _, hits = ray_samples(values, plan.extent, *rays)
    top = samples.max(axis=1) if len(samples) else np.zeros(0)
    top = top[np.isfinite(top)]
    if not len(top):
        return None
    q = np.quantile(top, PIXEL_QUANTILES)
    lo, hi = max(lo, float(q[0])), min(hi, float(q[1]))
    return (lo, hi) if hi > lo else None


def _planned_layers(plan: ScenePlan, stats, vs: ValueStats, tf_given: bool, scale_given: bool,
                    range_given: bool = False) -> tuple:
    """Plan a layered TF so that light crosses the outer layers to the inner
    ones: the layers' unit-peak profiles are averaged into the check's
    voxel grid (`opacity_grid`, one channel a layer) and the camera's rays
    march through it (`ray_samples`); for each first-layer opacity of
    `LAYER_LOWS` (unless the TF was given) and density scale of
    `LAYER_SCALES` (unless given, within the `MAX_DEPTH` bound) the share
    of each pixel's light that each layer gives is predicted
    (`layer_weights`), and the plan takes the pair that shows the most
    layers (`layers_seen`), the most evenly (never a flat opaque block).
    Notes say which layers the picture is predicted to show. Where at most
    one layer would be seen (the values do not spread over the range: a
    field of zeros and ones) a default TF becomes `FALLBACK_TF` over the
    values' range. Returns whether it set the density scale, and the TF's
    opacity over the check's voxel grid (None if not made)."""
    log = plan.transform == "log10"
    layers = Layers.parse(plan.tf)
    if not range_given:
        shown = _pixel_range(plan, log)
        if shown is not None and shown != plan.tf_range:
            plan.notes.append(f"layers: over [{shown[0]:.4g}, {shown[1]:.4g}]{' (log10 units)' if log else ''}, "
                              f"the largest values along the rays of {100 * PIXEL_QUANTILES[0]:g}-"
                              f"{100 * PIXEL_QUANTILES[1]:g}% of the picture's pixels (values above take the "
                              f"last layer's colour)")
            plan.tf_range = shown
    lo, hi = plan.tf_range

    def u(v):
        return ((_log_or_floor(v) if log else v) - lo) / (hi - lo)
    grid = opacity_grid(plan.data, lambda v: layers.profiles_fast(u(v)))
    search = camera_rays(plan.origin, plan.target, plan.up, plan.fov, LAYER_SEARCH_RES)
    samples, dt, hits = ray_samples(grid.astype(np.float32), plan.extent, *search, LAYER_SEARCH_STEPS)
    if not hits.any():
        return False, None
    dt = dt.astype(np.float32)
    lows = [layers.low] if tf_given else LAYER_LOWS
    best = None
    for low in lows:
        opac = layers.with_low(low).opacities()
        alpha = grid @ opac
        base = TARGET_DEPTH / max(float(alpha[alpha > 0].mean()) if (alpha > 0).any() else 0.0, 1e-6)
        scales = [plan.density_scale] if scale_given else np.minimum(base * LAYER_SCALES, MAX_DEPTH / opac.max())
        for scale in np.unique(scales):
            weights = layer_weights(samples, dt, opac, scale)
            seen, block = layers_seen(weights, int(hits.sum())), layers_opacity(weights)
            p = seen.shares[list(seen.seen)]
            even = float(np.exp(-(p / p.sum() * np.log(p / p.sum())).sum())) if len(p) else 0.0
            flat = block.opaque >= MAX_OPAQUE * block.shown        # a flat opaque block: the check's rule
            score = (not flat, len(seen.seen) if seen.tinted >= MIN_TINTED else 0, seen.tinted, even)
            if best is None or score > best[0]:
                best = (score, low, float(scale))
    (_, count, *_), low, scale = best
    if count < 2 and not tf_given:              # the values do not spread over layers (a field of two values)
        if not range_given:
            plan.tf_range = plan.value_range
        mean = _mean_alpha(stats, FALLBACK_TF, plan.tf_range, log)
        peak = _peak_alpha(FALLBACK_TF, plan.tf_range, log, vs)
        new = plan.density_scale if scale_given else _planned_density_scale(mean, peak)[0]
        plan.notes.append(f"layers: at most {count} of {layers.n} layers would be seen (the values do not spread "
                          f"over the range): TF '{FALLBACK_TF}' instead, density_scale {new:.3g}")
        plan.tf, plan.density_scale = FALLBACK_TF, float(new)
        plan.optical_depth, plan.peak_depth = new * mean, new * peak
        return False, None
    chosen = layers if tf_given else layers.with_low(low)
    if not tf_given:
        plan.tf = chosen.spec()
    ratio = scale / plan.density_scale
    plan.density_scale = scale
    mean = float((grid @ chosen.opacities()).mean())          # the voxels' mean: the cells' volume-weighted one
    plan.optical_depth, plan.peak_depth = scale * mean, scale * _peak_alpha(plan.tf, plan.tf_range, log, vs)
    rays = camera_rays(plan.origin, plan.target, plan.up, plan.fov, PREDICT_RES)
    samples, dt, hits = ray_samples(grid, plan.extent, *rays)
    plan.layers = layers_seen(layer_weights(samples, dt, chosen.opacities(), scale), int(hits.sum()))
    plan.notes.append(f"layers: TF '{plan.tf}' (first layer's opacity {chosen.low:.3g} of the last's), "
                      f"density_scale {scale:.3g}{'' if scale_given else f' ({ratio:.3g}x the mean-opacity one)'}: "
                      f"optical depth {plan.optical_depth:.3g} at the mean opacity; predicted {plan.layers}")
    return not scale_given, (grid * chosen.opacities()).max(axis=-1)


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


def _checked(plan: ScenePlan, stats, vs: ValueStats, tf_given: bool, scale_given: bool,
             alpha_grid=None) -> ScenePlan:
    """``plan`` after its check (docs/manual/data.md "Default pictures"):
    predict the picture (`mi_amr.visibility`); when it shows the data in
    under `MIN_SHOWN` of the footprint, take `FALLBACK_TF` if the TF is
    transparent at every value the data hold (and was not given), then
    raise the density scale (if not given) within the `MAX_DEPTH` bound;
    when at least `MAX_OPAQUE` of what shows is opaque, lower it. Each
    change is a note; the last prediction is ``plan.visibility``.
    ``alpha_grid``: the TF's opacity over the voxel grid, when the plan
    made it already (`_planned_layers`)."""
    log = plan.transform == "log10"
    rays = camera_rays(plan.origin, plan.target, plan.up, plan.fov, PREDICT_RES)

    def depths(tf):
        if alpha_grid is not None and tf == plan.tf:      # the layers' grid, made already
            return projected_depth(alpha_grid, plan.extent, *rays)
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


def _mean_blackbody_glow(stats, key, tf, value_range, log) -> float:
    """Mean luminance of the normalised blackbody (`mi_amr.transfer.spectra`)
    at the cells' temperatures (kelvin), weighted as `_mean_glow` weighs."""
    fn = TransferFunction.load(tf, value_range)
    total = weight = 0.0
    for (v, w), (g, _) in zip(cells_and_weights(stats), cells_and_weights(stats, key)):
        a = fn(_log_or_floor(v) if log else v)[:, 3] * w
        y = blackbody_luminance(g)
        total += float((y * a).sum())
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
