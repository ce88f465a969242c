"""Layered transfer functions: a few narrow Gaussian layers of opacity over
the value range, each in one colour of a colormap, opacity rising with the
value (yt's ``ColorTransferFunction.add_layers``;
docs/manual/transfer-functions.md "Layers").

A layered TF is a few parameters, not a table written by hand (`Layers`).
It is named by a string wherever a TF is named (Python, ``mi-amr render
--tf``, an XML scene's ``transfer_function``):
``layers`` (the defaults) or ``layers:n=8,width=0.2,colormap=plasma,low=0.02``,
or by a ``.json`` file ``{"layers": {"n": 8, ...}}`` (optionally with a
``"domain"``). All positions are in the normalised value ``u`` in [0, 1]
of the TF's domain (`mi_amr.transfer.function`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from functools import lru_cache

import numpy as np

#: The spec string's name.
NAME = "layers"
#: A layer's profile reaches 0 this many standard deviations off its centre.
CUT = 2.5


@dataclass(frozen=True)
class Layers:
    """``n`` Gaussian layers centred at ``u_k = (k + 1/2) / n``, standard
    deviation ``width / n`` (``width``: a share of the distance between two
    layers), colour ``colormap(k / (n - 1))`` (a matplotlib colormap, a
    perceptually uniform one by default), opacity ``low ** (1 - k / (n -
    1))``: from ``low`` at the first (thinnest) layer to 1 at the last,
    which holds its opacity above its centre (values above the range, the
    densest structure, stay seen in the last colour); 0 between layers and
    at the range's bottom (`profiles`)."""
    n: int = 7
    width: float = 0.18
    colormap: str = "viridis"
    low: float = 0.02

    def __post_init__(self):
        import matplotlib
        if not (isinstance(self.n, (int, np.integer)) and 1 <= self.n <= 64):
            raise ValueError(f"layers: n must be an integer from 1 to 64, got {self.n!r}")
        if not (np.isfinite(self.width) and 0.01 <= self.width <= 2.0):
            raise ValueError(f"layers: width must lie in [0.01, 2] (a share of the distance between layers), "
                             f"got {self.width!r}")
        if not (np.isfinite(self.low) and 0.0 < self.low <= 1.0):
            raise ValueError(f"layers: low (the first layer's opacity) must lie in (0, 1], got {self.low!r}")
        if self.colormap not in matplotlib.colormaps:
            raise ValueError(f"layers: colormap {self.colormap!r} is not a matplotlib colormap")

    # ---- Names -------------------------------------------------------------
    @classmethod
    def parse(cls, spec: str) -> "Layers":
        """``layers`` or ``layers:key=value,...`` (keys n, width, colormap,
        low); a `ValueError` names what is wrong."""
        name, _, rest = str(spec).partition(":")
        if name != NAME:
            raise ValueError(f"not a layered TF: {spec!r}")
        kw = {}
        known = {f.name: f.type for f in fields(cls)}
        for item in filter(None, (s.strip() for s in rest.split(","))):
            key, eq, value = item.partition("=")
            key = key.strip()
            if not eq or key not in known:
                raise ValueError(f"layers: expected key=value with keys {', '.join(known)}, got {item!r}")
            kw[key] = value.strip()
        return cls.from_dict(kw)

    @classmethod
    def from_dict(cls, d: dict) -> "Layers":
        """From ``{"n": 8, "width": 0.2, "colormap": "plasma", "low": 0.02}``
        (any subset; numbers or their strings)."""
        if not isinstance(d, dict):
            raise ValueError(f"layers: expected an object of options, got {type(d).__name__}")
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"layers: unknown option(s) {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(f.name for f in fields(cls))})")
        kw = {}
        try:
            if "n" in d:
                n = float(d["n"])
                if n != int(n):
                    raise ValueError
                kw["n"] = int(n)
            for key in ("width", "low"):
                if key in d:
                    kw[key] = float(d[key])
        except (TypeError, ValueError):
            raise ValueError(f"layers: n, width and low are numbers (n an integer), got {d!r}") from None
        if "colormap" in d:
            kw["colormap"] = str(d["colormap"])
        return cls(**kw)

    def spec(self) -> str:
        """The string that names these layers (`parse` reads it back)."""
        default = Layers()
        kw = [f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in asdict(self).items()
              if v != getattr(default, k)]
        return NAME + (":" + ",".join(kw) if kw else "")

    # ---- The layers ----------------------------------------------------------
    def centres(self) -> np.ndarray:
        """(n,) layer centres in normalised value u."""
        return (np.arange(self.n) + 0.5) / self.n

    def opacities(self) -> np.ndarray:
        """(n,) peak opacity of each layer, rising geometrically to 1."""
        t = np.arange(self.n) / max(self.n - 1, 1)
        return self.low ** (1.0 - t) if self.n > 1 else np.ones(1)

    def colours(self) -> np.ndarray:
        """(n, 3) sRGB colour of each layer (the colormap over the layers)."""
        import matplotlib
        t = np.arange(self.n) / max(self.n - 1, 1)
        return np.asarray(matplotlib.colormaps[self.colormap](t), np.float64)[:, :3]

    def profiles(self, u) -> np.ndarray:
        """``(len(u), n)``: each layer's profile at normalised values ``u``
        (clamped to [0, 1], as the table is), peak 1: a Gaussian lowered
        to end at 0 `CUT` standard deviations off its centre, the first one
        at u = 0 at the latest (values at or below the range's bottom,
        empty space, stay transparent)."""
        u = np.clip(np.asarray(u, np.float64).reshape(-1), 0.0, 1.0)
        sigma = self.width / self.n
        c = self.centres()
        d = u[:, None] - c[None, :]
        d[:, -1] = np.minimum(d[:, -1], 0.0)          # the last layer holds its opacity above its centre
        cut = np.full(d.shape, CUT * sigma)           # each side ends at CUT deviations ...
        cut[:, 0] = np.where(d[:, 0] < 0, min(CUT * sigma, c[0]), cut[:, 0])    # ... the first at u = 0 below
        g, g_cut = np.exp(-0.5 * (d / sigma) ** 2), np.exp(-0.5 * (cut / sigma) ** 2)
        return np.clip((g - g_cut) / (1.0 - g_cut), 0.0, 1.0)

    def profiles_fast(self, u) -> np.ndarray:
        """`profiles` looked up in a table of `PROFILE_TABLE` entries over
        [0, 1] (nearest entry): for millions of values at once."""
        table = _profile_table(self)
        i = np.rint(np.clip(np.asarray(u, np.float64).reshape(-1), 0.0, 1.0) * (len(table) - 1)).astype(np.int64)
        return table[i]

    def layer_opacity(self, u) -> np.ndarray:
        """``(len(u), n)``: each layer's opacity at normalised values ``u``
        (the TF's alpha is their maximum)."""
        return self.profiles(u) * self.opacities()[None, :]

    def with_low(self, low: float) -> "Layers":
        """The same layers with the first one's opacity ``low``."""
        return replace(self, low=float(low))

    def rgba(self, entries: int = 256) -> np.ndarray:
        """``(entries, 4)`` table over u in [0, 1]: alpha the largest layer's
        opacity, colour the layers' colours weighted by their Gaussians
        (each layer's own colour across it)."""
        u = np.linspace(0.0, 1.0, entries)
        g = self.profiles(u)
        a = g * self.opacities()[None, :]
        w = g / np.maximum(g.sum(axis=1, keepdims=True), 1e-300)
        out = np.empty((entries, 4))
        out[:, :3] = w @ self.colours()
        out[:, 3] = a.max(axis=1)
        return np.clip(out, 0.0, 1.0)


#: Entries of the table `Layers.profiles_fast` looks profiles up in.
PROFILE_TABLE = 4096


@lru_cache(maxsize=16)
def _profile_table(layers: Layers) -> np.ndarray:
    return layers.profiles(np.linspace(0.0, 1.0, PROFILE_TABLE))


def is_layers(spec) -> bool:
    """Whether ``spec`` names a layered TF (``layers`` or ``layers:...``)."""
    return isinstance(spec, str) and (spec == NAME or spec.startswith(NAME + ":"))
