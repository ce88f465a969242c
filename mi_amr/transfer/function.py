"""RGBA transfer functions (TF) and majorants of value ranges.

A TF is an (N, 4) table over a value domain ``[lo, hi]``. Entry ``i`` sits at
the normalised value ``u = i / (N - 1)``, with ``u = (v - lo) / (hi - lo)``
clamped to [0, 1]; between entries the table is interpolated linearly. The
alpha channel is an opacity in [0, 1] that the medium scales by
``density_scale`` into an extinction in inverse world units; rgb is the
single-scattering albedo.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from .layers import Layers, is_layers


class TransferFunction(mi.Object):
    """An RGBA lookup table over a scalar value domain.

    Subclasses ``mitsuba.Object`` so that it can be the ``transfer_function``
    entry of a ``mi.load_dict`` scene dictionary.

    Parameters
    ----------
    rgba : array (N, 4), N >= 2
        Colour (albedo) and opacity per entry, each in [0, 1].
    domain : (lo, hi)
        Values mapped to the first and the last entry; ``lo < hi``.
    """

    def __init__(self, rgba, domain):
        super().__init__()
        rgba = np.asarray(rgba, dtype=np.float64)
        if rgba.ndim != 2 or rgba.shape[1] != 4 or rgba.shape[0] < 2:
            raise ValueError(f"transfer function table must have shape (N>=2, 4), got {rgba.shape}")
        if not np.all(np.isfinite(rgba)):
            raise ValueError("transfer function table contains NaN or Inf")
        if rgba.min() < 0 or rgba.max() > 1:
            raise ValueError("transfer function entries must lie in [0, 1], got "
                             f"[{rgba.min():.4g}, {rgba.max():.4g}]")
        lo, hi = (float(d) for d in domain)
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"transfer function domain must be finite with lo < hi, got {domain}")
        with np.errstate(over="ignore", divide="ignore"):
            lo32, hi32 = np.float32(lo), np.float32(hi)
            inv32 = np.float32(1.0) / (hi32 - lo32) if hi32 > lo32 else np.float32(np.inf)
        if not (np.isfinite(lo32) and np.isfinite(hi32) and np.isfinite(inv32)):
            raise ValueError(f"transfer function domain {domain} cannot be used in float32 "
                             "(bounds out of range, or too narrow to tell apart)")
        self.rgba = rgba.astype(np.float32)
        self.domain = (lo, hi)

    def __reduce__(self):
        return (TransferFunction, (self.rgba, self.domain))

    def __len__(self):
        return self.rgba.shape[0]

    def __repr__(self):
        return (f"TransferFunction[{len(self)} entries, domain {self.domain}, "
                f"max alpha {self.rgba[:, 3].max():.3g}]")

    # ---- Evaluation (numpy; the Dr.Jit version lives in the medium) ------
    def normalize(self, v) -> np.ndarray:
        """Normalised position ``u`` in [0, 1] of values ``v``."""
        lo, hi = self.domain
        return np.clip((np.asarray(v, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0)

    def __call__(self, v) -> np.ndarray:
        """RGBA at values ``v`` (any shape) -> shape ``v.shape + (4,)``."""
        x = self.normalize(v) * (len(self) - 1)
        i = np.minimum(np.floor(x).astype(np.int64), len(self) - 2)
        f = (x - i)[..., None]
        return ((1 - f) * self.rgba[i] + f * self.rgba[i + 1]).astype(np.float32)

    def range_entries(self, vmin, vmax) -> tuple[np.ndarray, np.ndarray]:
        """Table entries ``lo..hi`` (inclusive) covering value ranges
        ``[vmin, vmax]`` under linear interpolation (docs/design.md section 4)."""
        n1 = len(self) - 1
        lo = np.minimum(np.floor(self.normalize(vmin) * n1).astype(np.int64), n1)
        hi = np.minimum(np.ceil(self.normalize(vmax) * n1).astype(np.int64), n1)
        return lo, np.maximum(hi, lo)

    def max_alpha(self, vmin, vmax) -> np.ndarray:
        """Maximum opacity over value ranges (numpy, brute force, for tests)."""
        lo, hi = self.range_entries(np.atleast_1d(vmin), np.atleast_1d(vmax))
        a = self.rgba[:, 3]
        return np.array([a[l:h + 1].max() for l, h in zip(lo, hi)], dtype=np.float32)

    def sparse_table(self, op=np.maximum) -> np.ndarray:
        """Range-maximum sparse table of alpha, shape (K, N), K = floor(log2 N) + 1:
        row k holds ``max(alpha[i : i + 2**k])`` (clamped at the end); with
        ``op=np.minimum`` the range-minimum table."""
        a = self.rgba[:, 3].astype(np.float32)
        rows = [a]
        k = 1
        while (1 << k) <= len(a):
            prev = rows[-1]
            half = 1 << (k - 1)
            shifted = np.concatenate([prev[half:], np.full(half, prev[-1])])
            shifted[len(a) - half:] = prev[len(a) - half:]
            rows.append(op(prev, shifted))
            k += 1
        return np.stack(rows)

    # ---- Construction ----------------------------------------------------
    @classmethod
    def from_colormap(cls, cmap="viridis", opacity=((0.0, 0.0), (1.0, 1.0)),
                      domain=(0.0, 1.0), n: int = 256) -> "TransferFunction":
        """A TF from a matplotlib colormap (name or object) and opacity control
        points ``[(u, alpha), ...]`` in normalised value, linearly interpolated."""
        import matplotlib
        cm = matplotlib.colormaps[cmap] if isinstance(cmap, str) else cmap
        u = np.linspace(0, 1, n)
        rgba = np.array(cm(u), dtype=np.float64)
        pts = np.asarray(opacity, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError("opacity control points must be a sequence of (u, alpha) pairs")
        order = np.argsort(pts[:, 0], kind="stable")
        rgba[:, 3] = np.interp(u, pts[order, 0], pts[order, 1])
        return cls(rgba, domain)

    @classmethod
    def preset(cls, name: str, domain=(0.0, 1.0), n: int = 256) -> "TransferFunction":
        """Named presets.

        * ``spiky``: narrow, high-opacity peaks (iso-surface-like).
        * ``foggy``: low, broad opacity (translucent).
        * ``ramp``: opacity linear in value (alpha = u), viridis colour.
        * ``constant``: opacity 1 everywhere, white.
        * ``dust``: grey, mostly absorbing (albedo 0.25), opacity ``u^3``
          (the dense gas absorbs, the thin gas lets the glow behind it
          through): the extinction of glowing gas, which then keeps the
          emission's colours.
        * ``blackbody``: for emission (the ``amr`` medium's ``emission``):
          matplotlib's ``inferno`` (black through red and orange to pale
          yellow, as a heated body), intensity ``alpha = u^2``.
        * ``layers`` (or ``layers:n=8,width=0.2,colormap=plasma,low=0.02``):
          narrow Gaussian layers coloured from a colormap, opacity rising
          with the value (`mi_amr.transfer.layers.Layers`, yt's
          ``add_layers``); the plan's default for data.
        """
        if is_layers(name):
            return cls(Layers.parse(name).rgba(n), domain)
        if name == "spiky":
            peaks = [(0.25, 0.55), (0.5, 0.8), (0.8, 1.0)]
            u = np.linspace(0, 1, n)
            alpha = np.zeros(n)
            for c, a in peaks:
                alpha = np.maximum(alpha, a * np.clip(1 - np.abs(u - c) / 0.025, 0, 1))
            tf = cls.from_colormap("plasma", list(zip(u, alpha)), domain, n)
        elif name == "foggy":
            tf = cls.from_colormap("viridis", [(0.0, 0.0), (0.15, 0.02), (0.5, 0.08),
                                               (1.0, 0.15)], domain, n)
        elif name == "ramp":
            tf = cls.from_colormap("viridis", [(0.0, 0.0), (1.0, 1.0)], domain, n)
        elif name == "constant":
            tf = cls(np.ones((n, 4)), domain)
        elif name == "dust":
            u = np.linspace(0, 1, n)
            tf = cls(np.column_stack([np.full((n, 3), 0.25), u ** 3]), domain)
        elif name == "blackbody":
            u = np.linspace(0, 1, n)
            tf = cls.from_colormap("inferno", list(zip(u, u * u)), domain, n)
        else:
            raise ValueError(f"unknown transfer function preset {name!r} "
                             f"(choose from {', '.join(PRESETS)} (layers:n=N,width=W,colormap=NAME,low=A), "
                             "a matplotlib colormap name, or a .json file)")
        return tf

    # ---- Files -------------------------------------------------------------
    def to_json(self, path=None) -> str:
        """``{"domain": [lo, hi], "rgba": [[r, g, b, a], ...]}``; written to
        ``path`` when given."""
        text = json.dumps({"domain": list(self.domain),
                           "rgba": [[round(float(x), 7) for x in row] for row in self.rgba]})
        if path is not None:
            Path(path).write_text(text)
        return text

    @classmethod
    def from_json(cls, path) -> "TransferFunction":
        """Our format ``{"domain": [lo, hi], "rgba": [[r, g, b, a], ...]}``, or a
        ParaView preset file (recognised by its ``RGBPoints``), over the
        domain the file stores (`load` rescales it)."""
        return cls.read_json(path).tf

    @classmethod
    def read_json(cls, path, name: str | None = None) -> "TFFile":
        """A TF ``.json`` file with what it says about its range (`TFFile`):
        ours (a table, or layers: ``{"layers": {"n": 8, ...}}`` with an
        optional ``"domain"``), or a ParaView preset (``name`` picks one
        from a list)."""
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: cannot read transfer function JSON ({e})") from e
        if isinstance(d, list) or (isinstance(d, dict) and "RGBPoints" in d):
            preset = _paraview_preset(d, path, name)
            return TFFile(cls._from_paraview_preset(preset, path), True, _keep_range(preset, path))
        if isinstance(d, dict) and "layers" in d:
            try:
                layers = Layers.from_dict(d["layers"])
                tf = cls(layers.rgba(256), d.get("domain", (0.0, 1.0)))
            except (ValueError, TypeError) as e:
                raise ValueError(f"{path}: {e}") from e
            return TFFile(tf, False, _keep_range(d, path), layers, "domain" in d)
        if not isinstance(d, dict) or "domain" not in d or "rgba" not in d:
            raise ValueError(f"{path}: expected an object with 'domain' and 'rgba' (or 'layers')")
        try:
            return TFFile(cls(d["rgba"], d["domain"]), False, _keep_range(d, path))
        except (ValueError, TypeError) as e:
            raise ValueError(f"{path}: {e}") from e

    def rescaled(self, domain) -> "TransferFunction":
        """The same table over ``domain`` (its entries stretched linearly
        from this domain onto the new one, as ParaView rescales a preset)."""
        return TransferFunction(self.rgba, domain)

    @classmethod
    def from_paraview(cls, path, name: str | None = None, n: int = 256) -> "TransferFunction":
        """A ParaView colour-map / opacity preset (JSON exported from
        ParaView's preset manager: a list of presets, or one preset object).

        ``RGBPoints`` is a flat list of ``x, r, g, b`` quadruples and
        ``Points`` (optional) of ``x, opacity, midpoint, sharpness``; the value
        domain is the range of the x positions. Colours are interpolated
        linearly in RGB and opacity piecewise linearly (ParaView's default
        midpoint 0.5 / sharpness 0); without ``Points`` the opacity ramps
        from 0 to 1 over the domain. ``name`` picks a preset from a list.
        The TF keeps the preset's own domain; `load` rescales it to the
        data's range as ParaView does.
        """
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: cannot read ParaView preset ({e})") from e
        return cls._from_paraview_preset(_paraview_preset(d, path, name), path, n)

    @classmethod
    def _from_paraview_preset(cls, preset: dict, path, n: int = 256) -> "TransferFunction":
        """The table of one ParaView preset object (`from_paraview`)."""
        rgb = np.asarray(preset["RGBPoints"], dtype=np.float64)
        if rgb.size < 8 or rgb.size % 4 or not np.all(np.isfinite(rgb)):
            raise ValueError(f"{path}: 'RGBPoints' must hold finite x, r, g, b quadruples (>= 2)")
        rgb = rgb.reshape(-1, 4)
        xs = [rgb[:, 0]]
        pts = None
        if preset.get("Points"):
            pts = np.asarray(preset["Points"], dtype=np.float64)
            if pts.size % 4 or not np.all(np.isfinite(pts)):
                raise ValueError(f"{path}: 'Points' must hold x, opacity, midpoint, sharpness quadruples")
            pts = pts.reshape(-1, 4)
            xs.append(pts[:, 0])
        lo = float(min(x.min() for x in xs))
        hi = float(max(x.max() for x in xs))
        if not hi > lo:
            raise ValueError(f"{path}: the preset's points span an empty value range")
        v = np.linspace(lo, hi, n)
        o = np.argsort(rgb[:, 0], kind="stable")
        table = np.empty((n, 4))
        for c in range(3):
            table[:, c] = np.interp(v, rgb[o, 0], rgb[o, c + 1])
        if pts is not None:
            o = np.argsort(pts[:, 0], kind="stable")
            table[:, 3] = np.interp(v, pts[o, 0], pts[o, 1])
        else:
            table[:, 3] = (v - lo) / (hi - lo)
        return cls(np.clip(table, 0.0, 1.0), (lo, hi))

    @classmethod
    def load(cls, spec, domain=None, *, data_range=None, keep_range: bool = False) -> "TransferFunction":
        """A TF from a preset name, a matplotlib colormap name (opacity ramp
        0 -> 1), a ``.json`` path (ours or a ParaView preset) or a
        TransferFunction (returned as it is).

        ``domain``: the value range asked for (a medium's ``tf_min`` /
        ``tf_max``, a plan's range), value units; ``data_range``: the data's
        own range, the default where no ``domain`` is asked for. Presets
        and colormaps span ``domain``, else ``data_range``, else [0, 1]. A
        ``.json`` file's table is rescaled as ParaView applies a preset:
        stretched onto ``domain``; with no ``domain``, a ParaView preset
        onto ``data_range`` (ParaView's rescale to the data range) while
        our own format keeps the domain it stores (written in value units,
        for these data). A file keeps its own range always when it says
        ``"keep_range": true`` or the caller gives ``keep_range``
        (ParaView's "Use preset range"); docs/manual/transfer-functions.md.
        """
        if isinstance(spec, TransferFunction):
            return spec
        spec = str(spec)
        if spec.endswith(".json"):
            f = cls.read_json(spec)
            if f.layers is not None:          # layers span the range asked for, else the file's, else the data's
                keep = (keep_range or f.keep_range or domain is None) and f.has_domain
                target = f.tf.domain if keep else domain if domain is not None else data_range
                return f.tf if target is None else f.tf.rescaled(target)
            target = domain if domain is not None else (data_range if f.paraview else None)
            return f.tf if target is None or keep_range or f.keep_range else f.tf.rescaled(target)
        domain = domain if domain is not None else (data_range if data_range is not None else (0.0, 1.0))
        if spec not in PRESETS:
            import matplotlib
            if spec in matplotlib.colormaps:
                # a matplotlib colormap by name, with opacity rising linearly
                return cls.from_colormap(spec, [(0.0, 0.0), (1.0, 1.0)], domain)
        return cls.preset(spec, domain)


PRESETS = ("layers", "spiky", "foggy", "ramp", "constant", "dust", "blackbody")


@dataclass(frozen=True)
class TFFile:
    """A TF ``.json`` file as read: the table over the domain it stores,
    whether it is a ParaView preset (rescaled to the data's range unless
    told otherwise) and whether it asks to keep its own range
    (``"keep_range": true``); for a file of layers, their parameters and
    whether it stores a domain (else the table spans [0, 1])."""
    tf: TransferFunction
    paraview: bool
    keep_range: bool
    layers: Layers | None = None
    has_domain: bool = True


def _paraview_preset(d, path, name: str | None) -> dict:
    """The preset object of a ParaView preset file's JSON ``d`` (a list of
    presets or one; ``name`` picks one by its ``Name``)."""
    presets = d if isinstance(d, list) else [d]
    if name is not None:
        presets = [p for p in presets if isinstance(p, dict) and p.get("Name") == name]
        if not presets:
            raise ValueError(f"{path}: no preset named {name!r}")
    preset = presets[0] if presets else None
    if not isinstance(preset, dict) or "RGBPoints" not in preset:
        raise ValueError(f"{path}: not a ParaView preset (no 'RGBPoints')")
    return preset


def _keep_range(d: dict, path) -> bool:
    """A TF file's ``"keep_range"`` (default false): keep the range it stores."""
    keep = d.get("keep_range", False)
    if not isinstance(keep, bool):
        raise ValueError(f"{path}: 'keep_range' must be true or false, got {keep!r}")
    return keep


def range_majorants_host(tf, vmin, vmax, density_scale: float) -> np.ndarray:
    """``density_scale * max alpha`` over the TF entries covering each value
    range (numpy; 0 for empty ranges). Same rule as the Dr.Jit kernel."""
    finite = vmin <= vmax
    lo, hi = tf.range_entries(np.where(finite, vmin, 0.0), np.where(finite, vmax, 0.0))
    st = tf.sparse_table()
    k = np.floor(np.log2(hi - lo + 1)).astype(np.int64)
    m = np.maximum(st[k, lo], st[k, hi + 1 - (np.int64(1) << k)])
    return np.where(finite, density_scale * m, 0.0)
