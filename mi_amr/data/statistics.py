"""What the values of AMR data are, counted once: extremes and the shares of
zeros and negatives (`ValueStats`), volume- and mass-weighted histograms and
their percentiles, and the viewer's fine histogram; read from an ``.amrb``
file's stored statistics where it has them (`stored_stats`; written by
`mi_amr.autoscene.file_stats`). Weights are cell volumes in finest-cell
volumes (8^level); ``data`` is one data set (`AMRCells`, `BlockVolume`) or
several (a run's outputs)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Bins of the histograms the percentiles are read from (within one bin width).
HISTOGRAM_BINS = 4096
#: Bins of the viewer's fine histogram of the stored values (the medium's:
#: log10 or linear), which its TF editor re-bins (`mi_amr.view.tf_spec.Histogram`).
VIEW_HISTOGRAM_BINS = 1 << 14
#: Bumped whenever `mi_amr.autoscene.file_stats` computes anything
#: differently: files with another version are planned from their values again.
STATS_VERSION = 2


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
    written (`mi_amr.autoscene.file_stats`; `mi_amr.data.amrb` reads it into
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
    return volume_and_mass_percentiles(data, qs, log, field)[1 if mass else 0]


def volume_and_mass_percentiles(data, qs, log: bool = False, field=None) -> tuple[list[float], list[float]]:
    """``(volume-weighted, mass-weighted)`` percentiles ``qs`` of the values
    (see `weighted_percentiles`), both from one pass over them
    (`weighted_histograms`) or from an ``.amrb`` file's stored histograms."""
    st = stored_stats(data, field)
    if st is None:
        lo, hi, *hists = weighted_histograms(data, log, field)
    else:                                          # as `mi_amr.autoscene.file_stats` stored them
        lo, hi = st.get(histogram_name(log, False) + "_span") or (np.inf, -np.inf)
        hists = [st.get(histogram_name(log, mass)) for mass in (False, True)]
    if not np.isfinite(lo):
        raise ValueError("no values to place a transfer function over")
    return tuple(_percentiles(lo, hi, hist, qs) for hist in hists)


def _percentiles(lo, hi, hist, qs) -> list[float]:
    if hi <= lo or hist is None or not np.sum(hist) > 0:
        return [lo for _ in qs]
    edges = np.linspace(lo, hi, HISTOGRAM_BINS + 1)
    cdf = np.cumsum(hist) / hist.sum()
    return [float(edges[min(int(np.searchsorted(cdf, q / 100.0)) + (q > 0), HISTOGRAM_BINS)]) for q in qs]


def histogram_name(log: bool, mass: bool) -> str:
    """The key of a histogram in `mi_amr.autoscene.file_stats`."""
    return f"hist_{'log' if log else 'linear'}{'_mass' if mass else ''}"


def weighted_histograms(data, log: bool, field=None) -> tuple:
    """``(lo, hi, volume counts, mass counts)``: histograms of
    `HISTOGRAM_BINS` equal bins over [lo, hi], the extremes of the values
    (of their log10, values <= 0 left out; from `value_stats`), weighted by
    cell volume and by volume times the value's magnitude, in one pass
    over the values. ``(inf, -inf, None, None)`` without values, ``(lo,
    hi, None, None)`` when all are one value."""
    vs = value_stats(data, field)
    if not vs.cells or (log and not vs.has_positive):
        return np.inf, -np.inf, None, None
    lo, hi = vs.span(log)
    if not hi > lo:
        return lo, hi, None, None
    volume, mass = np.zeros(HISTOGRAM_BINS), np.zeros(HISTOGRAM_BINS)
    scale = HISTOGRAM_BINS / (hi - lo)
    for v, w in cells_and_weights(data, field):
        m = w * np.abs(v)
        if log:
            keep = v > 0
            v, w, m = np.log10(v[keep]), w[keep], m[keep]
        index = np.clip(((v - lo) * scale).astype(np.int64), 0, HISTOGRAM_BINS - 1)
        volume += np.bincount(index, weights=w, minlength=HISTOGRAM_BINS)
        mass += np.bincount(index, weights=m, minlength=HISTOGRAM_BINS)
    return lo, hi, volume, mass


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
    (`mi_amr.autoscene.file_stats`), or None (not stored, another transform, range or bin count)."""
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
