"""The viewer's wire protocol: every message between the page
(``static/viewer.js``) and the server, as dataclasses; `parse` turns what the
page sends into one of them (or a `ProtocolError` naming what is wrong),
`to_json` turns what the server sends into the JSON the page reads.

Page to server, JSON text of at most `MAX_MESSAGE` bytes, ``{"type": ...,
fields}``; a change message's missing fields keep the view's value:

* ``camera``: `CameraChange` (orbit angles in degrees, distance and target
  in world units; `camera.OrbitCamera`)
* ``tf``: `TFChange` (the TF editor's state, display units; `tf_spec`)
* ``denoise``: `DenoiseChange`
* ``mode``: `ModeChange` (the lighting mode the view refines in)
* ``hybrid``: `HybridChange` (drag frames ray-marched, or in emission_absorption)
* ``iso``: `IsoChange` (the view's isosurfaces: values in the field's own units)
* ``histogram``: `HistogramRequest`; ``snapshot``: `SnapshotRequest`
* ``ack``: `Ack` (the newest frame is on screen)
* the TF editor's requests (`EditorRequest`): ``tf_save`` (`TFSave`, answered
  by a `TFFile`), ``tf_load`` (`TFLoad`), ``field`` (`FieldChange`: another
  field of the same data, for every tab), ``describe`` (`Describe`: a new
  `Hello`)
* annotations, clip plane and slice (`SceneRequest`): ``clip`` (`ClipChange`,
  world units), ``annotate`` (`AnnotateChange`: what the page draws, and
  whether snapshots burn it in), ``annotations`` (`AnnotationsRequest`,
  answered by an `AnnotationsReply`), ``slice`` (`SliceRequest`, answered by
  a `SliceReply`)

Server to page: `Status`, `Hello`, `HistogramReply`, `SnapshotDone`,
`AnnotationsReply`, `SliceReply` and `Error` as JSON text; `Frame` as the header of a binary message (a 4-byte
big-endian header length, the header's JSON, the JPEG image).

The parser checks what a message alone can tell (types, sizes, finite
numbers, fixed ranges); what depends on the view or the scene (a distance
relative to the current one, the scene's colormaps, whether the log10
display exists) is checked where the change is applied, also with a
`ValueError` naming the field.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, fields
from typing import ClassVar

from ..device.isosurface import MAX_ISO_VALUES
from ..plugins.integrator import MODES

#: Largest message accepted from a page (characters of JSON text).
MAX_MESSAGE = 64 * 1024
#: Most control points a TF message may carry.
MAX_POINTS = 256
#: Longest colormap (or field) name a message may carry.
MAX_NAME = 100
#: A TF point's own colour.
_COLOUR = re.compile(r"#[0-9a-fA-F]{6}")


class ProtocolError(ValueError):
    """A page message the server refuses; ``about``: its type, once known
    (the page shows a snapshot's error beside the snapshot button)."""

    def __init__(self, message: str, about: str | None = None):
        super().__init__(message)
        self.about = about


def _optional(**kw):
    """A field left out of the JSON while it is None."""
    return field(default=None, metadata={"omit_none": True}, **kw)


class Message:
    """A protocol message: ``TYPE`` is its ``"type"`` on the wire; ``msg[key]``
    reads a field as the page sees it (``to_json(msg)[key]``)."""
    TYPE: ClassVar[str]

    def __getitem__(self, key):
        return to_json(self)[key]


# ---- Page to server -------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraChange(Message):
    """The orbit camera's new angles (degrees), distance and target (world units)."""
    TYPE: ClassVar[str] = "camera"
    azimuth: float | None = _optional()
    elevation: float | None = _optional()
    distance: float | None = _optional()
    target: tuple[float, float, float] | None = _optional()


@dataclass(frozen=True)
class TFChange(Message):
    """The TF editor's new state: opacity ``points`` (u, alpha) in [0, 1]^2,
    ``colormap`` name, ``log`` (log10 display), display ``range`` (lo, hi),
    ``density`` scale."""
    TYPE: ClassVar[str] = "tf"
    points: tuple[tuple[float, float], ...] | None = _optional()
    colormap: str | None = _optional()
    log: bool | None = _optional()
    range: tuple[float, float] | None = _optional()
    density: float | None = _optional()


@dataclass(frozen=True)
class DenoiseChange(Message):
    """Show denoised images (``on``) or the raw accumulation."""
    TYPE: ClassVar[str] = "denoise"
    on: bool


@dataclass(frozen=True)
class ModeChange(Message):
    """Refine in this lighting mode (``amrvolpath``'s ``mode``, one of
    `MODES`); camera and TF drags render in the fast mode meanwhile."""
    TYPE: ClassVar[str] = "mode"
    mode: str


@dataclass(frozen=True)
class HistogramRequest(Message):
    """Ask for the histogram under the view's TF editor."""
    TYPE: ClassVar[str] = "histogram"


@dataclass(frozen=True)
class SnapshotRequest(Message):
    """Write the view's image and scene as ``name``.* (a plain file stem)."""
    TYPE: ClassVar[str] = "snapshot"
    name: str


@dataclass(frozen=True)
class Ack(Message):
    """The page shows the newest frame: the next may be sent."""
    TYPE: ClassVar[str] = "ack"


@dataclass(frozen=True)
class HybridChange(Message):
    """The hybrid viewer on or off for this view: the passes that answer a
    camera or TF change ray-marched (``ray_march``: noise-free) while ``on``,
    else in ``emission_absorption``; the view refines in its own mode either way."""
    TYPE: ClassVar[str] = "hybrid"
    on: bool


@dataclass(frozen=True)
class IsoChange(Message):
    """The view's isosurfaces (docs/manual/isosurfaces.md): ``values`` in
    the field's own units (what the data hold, before any log10 the medium
    stores; at most `MAX_ISO_VALUES`, () none), ``only``: the surfaces alone
    (the gas off). A missing field keeps the view's."""
    TYPE: ClassVar[str] = "iso"
    values: tuple[float, ...] | None = _optional()
    only: bool | None = _optional()


ViewChange = CameraChange | TFChange | DenoiseChange | ModeChange | HybridChange | IsoChange
PageMessage = CameraChange | TFChange | DenoiseChange | ModeChange | HybridChange | IsoChange | HistogramRequest \
    | SnapshotRequest | Ack


# ---- Server to page -----------------------------------------------------------------------------
@dataclass(frozen=True)
class Status(Message):
    """Loading progress: ``state`` loading, ready or error; ``done`` of
    ``total`` steps (None: unknown) of the step ``desc``."""
    TYPE: ClassVar[str] = "status"
    state: str
    desc: str
    done: int = 0
    total: int | None = None


@dataclass(frozen=True)
class Hello(Message):
    """What a page needs to draw its controls: its view's ``camera``
    (`OrbitCamera`) and ``tf`` (`TFSpec`), the scene's colormaps (and their
    colours, ``{name: ["#rrggbb", ...]}`` over u), the film ``size``
    [width, height] in pixels; ``modes``: the lighting modes the view may
    refine in (None: the scene's integrator has none, ``mode_note`` says
    why), ``mode`` the view's, ``fast_mode`` the one of its drag frames now;
    ``hybrid``: whether its drag frames are ray-marched (None: the scene
    has no ``ray_march``), ``fast_modes`` the drag frames' mode with the
    hybrid ``{"on": ..., "off": ...}``; ``iso``: its isosurfaces
    (`mi_amr.view.isosurfaces.iso_hello`: values and the data's range in
    the field's own units, ``only``, ``max``, ``note`` why there are none)."""
    TYPE: ClassVar[str] = "hello"
    view: int
    camera: object
    tf: object
    colormaps: tuple[str, ...]
    log_available: bool
    denoiser: bool
    denoiser_missing: str | None
    denoise: bool
    size: tuple[int, int]
    max_spp: int
    data: str
    colormap_stops: dict
    out_dir: str | None = _optional()          # where snapshots go (added by the server)
    editor: dict | None = _optional()          # the TF editor's and camera's extras (`ViewEngine.describe`)
    modes: tuple[str, ...] | None = _optional()
    mode: str | None = _optional()
    fast_mode: str | None = _optional()
    mode_note: str | None = _optional()
    hybrid: bool | None = _optional()
    fast_modes: dict | None = _optional()
    iso: dict | None = _optional()


@dataclass(frozen=True)
class HistogramReply(Message):
    """Volume shares in equal bins over the display ``range`` (lo, hi) of
    the ``log`` or linear display; ``density``: see below."""
    TYPE: ClassVar[str] = "histogram"
    counts: tuple[float, ...]
    range: tuple[float, float]
    log: bool
    below: float | None = _optional()          # the share of the volume below the range
    above: float | None = _optional()          # ... and above it
    density: float | None = _optional()        # the density scale, when the server planned it again
                                               # with the range (the log10 toggle): the page takes both


@dataclass(frozen=True)
class Frame(Message):
    """A binary frame's header: the view ``version`` it shows, its samples
    per pixel, ``width`` x ``height`` pixels, render time in ms;
    ``shown_spp``: the samples of the picture when fewer than ``spp`` (a
    denoised image follows the accumulation about each second); ``mode``:
    the lighting mode it was rendered in (None: the scene's integrator has
    none); ``rendered``: the view version whose state it shows (``version``
    is the newest when it was sent: a drag frame may show an older state);
    ``fast``: a drag frame, rendered in the fast mode."""
    TYPE: ClassVar[str] = "frame"
    version: int
    spp: int
    denoised: bool
    preview: bool
    width: int
    height: int
    render_ms: float
    max_spp: int
    shown_spp: int | None = _optional()
    mode: str | None = _optional()
    rendered: int | None = _optional()
    fast: bool | None = _optional()


@dataclass(frozen=True)
class SnapshotDone(Message):
    """The files a snapshot wrote (absolute paths), its samples per pixel,
    and ``notes`` on what else it wrote (the data, once) or chose (a numbered name)."""
    TYPE: ClassVar[str] = "snapshot"
    files: tuple[str, ...]
    spp: int
    notes: tuple[str, ...] | None = _optional()


@dataclass(frozen=True)
class Error(Message):
    """A refused message (nothing changed); ``about``: its type, when known.
    A change that could not render is undone: ``camera`` and ``tf`` are then
    the view's state again (the last one that rendered); a refused ``iso``
    change comes with the view's isosurfaces as they stay (``iso``, as in `Hello`)."""
    TYPE: ClassVar[str] = "error"
    message: str
    about: str | None = _optional()
    camera: object = _optional()
    tf: object = _optional()
    iso: dict | None = _optional()


ServerMessage = Status | Hello | HistogramReply | Frame | SnapshotDone | Error


# ---- The TF editor's requests and replies ------------------------------------------------------
@dataclass(frozen=True)
class TFSave(Message):
    """Ask for the view's TF as a file (`TFFile`)."""
    TYPE: ClassVar[str] = "tf_save"


@dataclass(frozen=True)
class TFLoad(Message):
    """Make a TF JSON file's ``text`` the view's TF (`tf_spec.TFSpec.from_file`)."""
    TYPE: ClassVar[str] = "tf_load"
    text: str


@dataclass(frozen=True)
class FieldChange(Message):
    """Render another field of the same data (yt data sets), for every view."""
    TYPE: ClassVar[str] = "field"
    name: str


@dataclass(frozen=True)
class Describe(Message):
    """Ask for a new `Hello` (after the field changed)."""
    TYPE: ClassVar[str] = "describe"


@dataclass(frozen=True)
class TFFile(Message):
    """The view's TF as the JSON text ``mi-amr render --tf`` reads."""
    TYPE: ClassVar[str] = "tf_file"
    text: str


EditorRequest = TFSave | TFLoad | FieldChange | Describe


# ---- Annotations, clip plane and slice (mi_amr/annotations.py, mi_amr/slicing.py) -----------------
#: Largest slice a page may ask for (pixels along its longer side).
MAX_SLICE = 1024


@dataclass(frozen=True)
class ClipChange(Message):
    """Keep the medium where ``normal . x <= offset`` (world units) in this
    view's pictures; ``normal`` None: no clip plane."""
    TYPE: ClassVar[str] = "clip"
    normal: tuple[float, float, float] | None = _optional()
    offset: float = 0.0


@dataclass(frozen=True)
class AnnotateChange(Message):
    """What the page draws over the picture (``outline``, ``axes``, AMR
    ``levels`` with the refinement levels of ``level_filter`` (None: all),
    ``legend``), and whether a snapshot's PNG gets them (``burn_in``)."""
    TYPE: ClassVar[str] = "annotate"
    outline: bool = False
    axes: bool = False
    levels: bool = False
    legend: bool = False
    level_filter: tuple[int, ...] | None = _optional()
    burn_in: bool = False


@dataclass(frozen=True)
class AnnotationsRequest(Message):
    """Ask for the annotations' geometry (`AnnotationsReply`)."""
    TYPE: ClassVar[str] = "annotations"


@dataclass(frozen=True)
class SliceRequest(Message):
    """Ask for the slice normal to ``axis`` (x, y or z) at world coordinate
    ``position`` along it, ``res`` pixels along its longer side."""
    TYPE: ClassVar[str] = "slice"
    axis: str
    position: float
    res: int = 256


@dataclass(frozen=True)
class AnnotationsReply(Message):
    """World geometry to draw with the view's camera: the domain's 8
    ``corners`` (corner ``x + 2y + 4z``), ``axes`` (name, colour, segment,
    ticks, labels), ``levels`` (per level: ``refinement`` (0 the coarsest),
    ``colour``, ``boxes`` [[lo, hi], ...] world, ``note``), the data's world
    ``box`` (lo, hi) and length ``unit``; ``legend``: the TF's legend as a PNG
    data URL where asked for ("" for the page, which draws its own)."""
    TYPE: ClassVar[str] = "annotations"
    corners: tuple
    axes: tuple
    levels: tuple
    box: tuple
    legend: str = ""
    unit: str = ""


@dataclass(frozen=True)
class SliceReply(Message):
    """A slice: ``png`` (a data URL: the TF's colours, level boundaries
    drawn), ``values`` (base64 float32, row-major from the top row; NaN:
    none) and ``levels`` (base64 int8 refinement levels; -1: none) of
    ``width`` x ``height`` pixels; ``window`` [h0, h1, v0, v1] world
    coordinates along the image axes ``axes`` (names), ``label`` of the
    values (log10 when ``log``)."""
    TYPE: ClassVar[str] = "slice"
    axis: str
    position: float
    width: int
    height: int
    png: str
    values: str
    levels: str
    window: tuple
    axes: tuple
    label: str
    log: bool


SceneRequest = ClipChange | AnnotateChange | AnnotationsRequest | SliceRequest


# ---- JSON ----------------------------------------------------------------------------------------
def _plain(value):
    """``value`` as JSON types (objects with a ``to_json``, tuples, numpy scalars)."""
    if hasattr(value, "to_json"):
        return value.to_json()
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if hasattr(value, "item"):                  # numpy scalars
        return value.item()
    return value


def to_json(msg: Message) -> dict:
    """``msg`` as the JSON object on the wire: ``{"type": ..., fields}``."""
    out = {"type": msg.TYPE}
    for f in fields(msg):
        value = getattr(msg, f.name)
        if value is None and f.metadata.get("omit_none"):
            continue
        out[f.name] = _plain(value)
    return out


def dumps(msg: Message) -> str:
    """``to_json(msg)`` as text."""
    return json.dumps(to_json(msg))


# ---- Parsing -------------------------------------------------------------------------------------
def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _finite(v) -> bool:
    try:
        return _is_number(v) and math.isfinite(float(v))
    except OverflowError:                       # an integer beyond float
        return False


def _number(name, v, lo=-math.inf, hi=math.inf) -> float:
    if not _finite(v) or not lo <= v <= hi:
        raise ValueError(f"{name}: a finite number in [{lo}, {hi}]")
    return float(v)


def _camera(f: dict) -> CameraChange:
    out = {}
    if "azimuth" in f:
        out["azimuth"] = _number("azimuth", f["azimuth"], -1e6, 1e6)
    if "elevation" in f:
        out["elevation"] = _number("elevation", f["elevation"], -90, 90)
    if "distance" in f:
        d = f["distance"]
        if not _finite(d) or not d > 0:
            raise ValueError("distance: a finite number above 0")
        out["distance"] = float(d)
    if "target" in f:
        t = f["target"]
        if not isinstance(t, list) or len(t) != 3 or not all(_is_number(x) for x in t):
            raise ValueError("target: three numbers")
        if not all(_finite(x) and abs(x) <= 1e9 for x in t):
            raise ValueError("target: three finite numbers")
        out["target"] = tuple(float(x) for x in t)
    return CameraChange(**out)


def _tf(f: dict) -> TFChange:
    out = {}
    if "points" in f:
        p = f["points"]
        if not isinstance(p, list) or not 2 <= len(p) <= MAX_POINTS:
            raise ValueError(f"points: a list of 2 to {MAX_POINTS} [u, alpha] pairs")
        if not all(isinstance(q, list) and len(q) in (2, 3) and all(_is_number(x) for x in q[:2]) for q in p):
            raise ValueError("points: a list of [u, alpha] number pairs")
        if not all(len(q) == 2 or (isinstance(q[2], str) and _COLOUR.fullmatch(q[2])) for q in p):
            raise ValueError("points: a point's colour is '#rrggbb'")
        if not all(_finite(x) for q in p for x in q[:2]):
            raise ValueError("points: a list of finite [u, alpha] pairs")
        if not all(0 <= x <= 1 for q in p for x in q[:2]):
            raise ValueError("points: u and alpha must lie in [0, 1]")
        out["points"] = tuple((float(q[0]), float(q[1])) + tuple(c.lower() for c in q[2:]) for q in p)
    if "colormap" in f:
        c = f["colormap"]
        if not isinstance(c, str) or not 1 <= len(c) <= MAX_NAME:
            raise ValueError("colormap: the name of a colormap")
        out["colormap"] = c
    if "log" in f:
        if not isinstance(f["log"], bool):
            raise ValueError("log: true or false")
        out["log"] = f["log"]
    if "range" in f:
        r = f["range"]
        if not isinstance(r, list) or len(r) != 2 or not all(_is_number(x) for x in r):
            raise ValueError("range: [lo, hi], two numbers")
        if not (all(_finite(x) for x in r) and r[0] < r[1]):
            raise ValueError("range: finite, with lo < hi")
        out["range"] = (float(r[0]), float(r[1]))
    if "density" in f:
        d = f["density"]
        if not _finite(d) or not d > 0:
            raise ValueError("density: a positive number")
        out["density"] = float(d)
    return TFChange(**out)


def _text(name, v, most=MAX_MESSAGE) -> str:
    if not isinstance(v, str) or not 1 <= len(v) <= most:
        raise ValueError(f"{name}: text of 1 to {most} characters")
    return v


def _denoise(f: dict) -> DenoiseChange:
    if not isinstance(f.get("on"), bool):
        raise ValueError("denoise: 'on' must be true or false")
    return DenoiseChange(f["on"])


def _hybrid(f: dict) -> HybridChange:
    if not isinstance(f.get("on"), bool):
        raise ValueError("hybrid: 'on' must be true or false")
    return HybridChange(f["on"])


def _iso(f: dict) -> IsoChange:
    out = {}
    if "values" in f:
        v = f["values"]
        if not isinstance(v, list) or len(v) > MAX_ISO_VALUES or not all(_is_number(x) for x in v):
            raise ValueError(f"iso values: a list of at most {MAX_ISO_VALUES} numbers (the field's own units)")
        if not all(_finite(x) for x in v):
            raise ValueError("iso values: finite numbers")
        out["values"] = tuple(float(x) for x in v)
    if "only" in f:
        out["only"] = _bool("iso only", f["only"])
    return IsoChange(**out)


def _mode(f: dict) -> ModeChange:
    if f.get("mode") not in MODES:
        raise ValueError(f"mode: one of {', '.join(MODES)}")
    return ModeChange(f["mode"])


def _snapshot(f: dict) -> SnapshotRequest:
    return SnapshotRequest(safe_name(f.get("name")))


def safe_name(name) -> str:
    """A snapshot name as a plain file stem: letters, digits, ``-``, ``_``,
    ``.`` (not leading), at most 100 characters; anything else (a path, a
    separator, ``..``) is a `ValueError`."""
    if not isinstance(name, str) or not 1 <= len(name) <= 100:
        raise ValueError("snapshot name: 1 to 100 characters")
    if name.startswith(".") or any(not (c.isascii() and (c.isalnum() or c in "-_.")) for c in name):
        raise ValueError(f"snapshot name {name!r}: letters, digits, '-', '_' and '.' only (not leading), "
                         "no folders")
    return name


def _bool(name, v) -> bool:
    if not isinstance(v, bool):
        raise ValueError(f"{name}: true or false")
    return v


def _clip(f: dict) -> ClipChange:
    n = f.get("normal")
    if n is None:
        return ClipChange(None, 0.0)
    if not isinstance(n, list) or len(n) != 3 or not all(_finite(x) and abs(x) <= 1e9 for x in n) \
            or not any(x != 0 for x in n):
        raise ValueError("clip normal: three finite numbers, not all 0 (or null: no clip plane)")
    return ClipChange(tuple(float(x) for x in n), _number("clip offset", f.get("offset", 0.0), -1e9, 1e9))


def _annotate(f: dict) -> AnnotateChange:
    out = {k: _bool(k, f[k]) for k in ("outline", "axes", "levels", "legend", "burn_in") if k in f}
    lf = f.get("level_filter")
    if lf is not None:
        if not isinstance(lf, list) or len(lf) > 64 or not all(isinstance(x, int) and not isinstance(x, bool)
                                                                and 0 <= x < 64 for x in lf):
            raise ValueError("level_filter: a list of refinement levels 0 to 63 (or null: all)")
        out["level_filter"] = tuple(lf)
    return AnnotateChange(**out)


def _slice(f: dict) -> SliceRequest:
    if f.get("axis") not in ("x", "y", "z"):
        raise ValueError("slice axis: x, y or z")
    res = f.get("res", 256)
    if not isinstance(res, int) or isinstance(res, bool) or not 8 <= res <= MAX_SLICE:
        raise ValueError(f"slice res: an integer in [8, {MAX_SLICE}]")
    return SliceRequest(f["axis"], _number("slice position", f.get("position"), -1e9, 1e9), res)


#: Each page message type: its class and the parser of its fields.
_PARSERS = {cls.TYPE: (cls, parse_fields) for cls, parse_fields in (
    (CameraChange, _camera), (TFChange, _tf), (DenoiseChange, _denoise), (ModeChange, _mode),
    (HybridChange, _hybrid), (IsoChange, _iso), (HistogramRequest, lambda f: HistogramRequest()), (SnapshotRequest, _snapshot),
    (Ack, lambda f: Ack()),
    (TFSave, lambda f: TFSave()), (TFLoad, lambda f: TFLoad(_text("text", f.get("text")))),
    (FieldChange, lambda f: FieldChange(_text("name", f.get("name"), MAX_NAME))), (Describe, lambda f: Describe()),
    (ClipChange, _clip), (AnnotateChange, _annotate), (AnnotationsRequest, lambda f: AnnotationsRequest()),
    (SliceRequest, _slice))}


def parse(text) -> PageMessage | EditorRequest:
    """A page's websocket message (``str``; anything else is binary) as a
    typed message; a `ProtocolError` names what is wrong."""
    if not isinstance(text, str):
        raise ProtocolError("messages must be JSON text, not binary")
    if len(text) > MAX_MESSAGE:
        raise ProtocolError(f"message too long ({len(text)} > {MAX_MESSAGE} bytes)")
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise ProtocolError(f"not JSON: {e}") from None
    except RecursionError:
        raise ProtocolError("message: nested too deeply") from None
    except ValueError as e:                      # an integer of more digits than Python converts
        raise ProtocolError(f"message: {str(e).splitlines()[0]}") from None
    return parse_message(obj)


def parse_message(obj) -> PageMessage | EditorRequest:
    """A decoded JSON message (a dict with a ``type``) as a typed message;
    a `ProtocolError` for an unknown type, a field it does not have, or a
    bad value (the field named)."""
    if not isinstance(obj, dict):
        raise ProtocolError("a message is a JSON object with a 'type'")
    kind = obj.get("type")
    if not isinstance(kind, str) or kind not in _PARSERS:
        raise ProtocolError(f"unknown message type {kind!r}")
    cls, parse_fields = _PARSERS[kind]
    known = {f.name for f in fields(cls)}
    extra = sorted(k for k in obj if k != "type" and k not in known)
    if extra:
        raise ProtocolError(f"{kind}: no field(s) {', '.join(map(repr, extra))} "
                            f"(fields: {', '.join(sorted(known)) or 'none'})", kind)
    try:
        return parse_fields({k: v for k, v in obj.items() if k != "type"})
    except ValueError as e:
        raise ProtocolError(str(e), kind) from None
