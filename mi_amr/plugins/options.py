"""The ``amr`` medium's properties, parsed once into a typed record.

Parsing validates every value (unknown names, wrong types, out-of-range
numbers give a `ParameterError` naming the parameter); the medium only
stores the result (docs/design.md section 6).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..data.blocks import BlockVolume
from ..data.cells import AMRCells
from ..data.io import load_volume
from ..data.metadata import physical_box
from ..data.opening import field_scalars, is_native, open_data, volume_checksum
from ..data.reconstruction import METHODS
from ..data.transform import VALUE_TRANSFORMS, apply_value_transform, positive_floor
from ..data.volume import as_volume
from ..memory import default_memory_limit
from ..params import ParameterError, check_known, get_bool, get_float, get_int, get_string
from ..building import SAMPLINGS, StructureOptions, TRAVERSALS
from ..structures.cache import HOST_CACHE
from ..transfer.classification import EMISSION_MODELS, MAX_DENSITY_SCALE, check_emission_scale
from ..transfer.function import TransferFunction
from .iso_surfaces import parse_iso_values

MAJORANTS = ("ray", "global")
OVERLAPS = ("error", "finest")
#: Bound on the iterations of one tracking loop (reported by the counters).
MAX_TRACKING_ITERATIONS = 1 << 20
#: Largest condition number of to_world's linear part (float32 precision).
MAX_CONDITION = 1e7
#: The parameters ``amr`` accepts, besides a nested phase function (the
#: docs/manual/medium.md's table and the plugin docstring's are tested against this set:
#: tests/test_docs.py).
KNOWN = {"filename", "field", "data_checksum", "scalars", "data", "transfer_function", "tf_min", "tf_max", "tf_keep_range",
         "density_scale", "reconstruction", "majorant", "grid_resolution", "grid_refinement", "thinning_resolution",
         "overlap", "to_world", "sample_emitters", "traversal", "sampling", "brick_size",
         "kdtree_leaves", "max_iterations", "memory_limit", "value_masks", "value_transform",
         "emission", "emission_field", "emission_scale", "emission_min", "emission_max", "emission_transform",
         "emission_model",
         "clip_normal", "clip_offset", "iso", "iso_only"}


@dataclass(frozen=True)
class Emission:
    """What makes a medium glow: the emission TF over its (transformed)
    emission field, the field's name (None: the extinction field, as the
    extinction TF sees it, after ``value_transform``), the transform of its values and the radiance
    scale (docs/design.md section 12). ``model``: ``tf``, or ``blackbody``
    (Planck's law at the field in kelvin; ``tf`` is then None)."""
    tf: "TransferFunction | None"
    field: str | None
    transform: str
    scale: float
    model: str = "tf"


@dataclass(frozen=True)
class MediumOptions:
    """Everything the ``amr`` medium needs, validated. ``density_scale`` in
    inverse world units; ``to_world`` maps the local unit cube to the world.
    ``volume``: the data as blocks; ``cells``: the `AMRCells` they were made
    from when the scene gave cells (else None)."""
    volume: BlockVolume
    cells: "AMRCells | None"
    tf: TransferFunction
    density_scale: float
    majorant: str
    max_iterations: int
    to_world: "mi.ScalarTransform4f"
    structures: StructureOptions
    emission: "Emission | None" = None
    clip: "tuple | None" = None            # (normal (3,), offset): keep world points with normal . x <= offset
    iso: tuple = ()                        # iso values, value units (after value_transform)
    iso_bsdfs: tuple = ()                  # the nested BSDFs, by slot
    iso_only: bool = False                 # surfaces only: the medium's own density off

    @property
    def world_scale(self) -> float:
        """Geometric mean scale of ``to_world`` (local unit length in world units)."""
        m = np.array(self.to_world.matrix, dtype=np.float64)[:3, :3]
        return float(np.cbrt(abs(np.linalg.det(m)))) or 1.0


def parse_medium_options(props: mi.Properties) -> MediumOptions:
    """Validate the ``amr`` plugin's properties and load its data."""
    check_known(props, "amr", KNOWN, allow=lambda k, v: isinstance(v, (mi.PhaseFunction, mi.BSDF)))
    reconstruction = get_string(props, "amr", "reconstruction", "tent", METHODS)
    transform = get_string(props, "amr", "value_transform", "none", VALUE_TRANSFORMS)
    data = _load_data(props, reconstruction)
    # once, at load; the TF domain is in transformed units (a file's volume is
    # this medium's own, so it is transformed in place)
    data, _ = apply_value_transform(data, transform, inplace="filename" in props.keys())
    volume, cells = medium_volume(data, reconstruction)
    emission = _emission(props, volume)
    structures = StructureOptions(
        reconstruction=reconstruction,
        traversal=get_string(props, "amr", "traversal", "grid", TRAVERSALS),
        sampling=get_string(props, "amr", "sampling", "hash", SAMPLINGS),
        grid_resolution=get_int(props, "amr", "grid_resolution", None, minimum=1),
        grid_refinement=_refinement(props),
        thinning_resolution=get_int(props, "amr", "thinning_resolution", None, minimum=0, maximum=1024),
        brick_size=get_int(props, "amr", "brick_size", 8, minimum=1, maximum=1024),
        kdtree_leaves=get_int(props, "amr", "kdtree_leaves", 4096, minimum=1),
        value_masks=get_bool(props, "amr", "value_masks", True),
        memory_limit=get_float(props, "amr", "memory_limit", default_memory_limit(), positive=True))
    return MediumOptions(
        volume=volume,
        cells=cells,
        tf=_transfer_function(props, volume),
        density_scale=get_float(props, "amr", "density_scale", 1.0, minimum=0.0, maximum=MAX_DENSITY_SCALE),
        majorant=get_string(props, "amr", "majorant", "ray", MAJORANTS),
        max_iterations=get_int(props, "amr", "max_iterations", MAX_TRACKING_ITERATIONS,
                               minimum=1, maximum=2**31),
        to_world=_to_world(props, volume),
        structures=structures,
        emission=emission,
        clip=_clip(props),
        **_iso(props))


def _iso(props) -> dict:
    """``iso`` (numbers, in the values' units after ``value_transform``),
    the nested BSDFs (in order: the first for the first value, ...) and
    ``iso_only``."""
    values = parse_iso_values(props["iso"] if "iso" in props.keys() else None)
    bsdfs = tuple(props[k] for k in props.keys() if isinstance(props[k], mi.BSDF))
    if len(bsdfs) > max(len(values), 0) and bsdfs:
        raise ParameterError(f"amr: {len(bsdfs)} nested BSDFs for {len(values)} iso values (one BSDF per "
                             f"iso value, in order)")
    only = get_bool(props, "amr", "iso_only", False)
    if only and not values:
        raise ParameterError("amr: iso_only needs iso values (iso_only shows the surfaces alone)")
    return dict(iso=values, iso_bsdfs=bsdfs, iso_only=only)


def _clip(props) -> "tuple | None":
    """``clip_normal`` (a world-space vector) and ``clip_offset`` (world
    units): the medium is kept where ``normal . x <= offset`` (None: all)."""
    if "clip_normal" not in props.keys():
        if "clip_offset" in props.keys():
            raise ParameterError("amr: clip_offset needs clip_normal (the clip plane's normal)")
        return None
    try:
        normal = np.array([float(x) for x in props["clip_normal"]], dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError(f"amr: clip_normal must be a vector of 3 numbers, got {props['clip_normal']!r}") from None
    if normal.shape != (3,) or not np.isfinite(normal).all() or not np.any(normal):
        raise ParameterError(f"amr: clip_normal must be a nonzero finite vector of 3 numbers, got {normal.tolist()}")
    return normal, get_float(props, "amr", "clip_offset", 0.0)


def as_transform4f(t) -> "mi.ScalarTransform4f":
    """Any Mitsuba scalar transform (float or double) as ScalarTransform4f."""
    if t is None:
        return mi.ScalarTransform4f()
    if isinstance(t, mi.ScalarTransform4f):
        return t
    m = np.array(getattr(t, "matrix", t), dtype=np.float64)
    # the inverse in float64: a float32 inversion under- or overflows for
    # scales far from 1 (1e-20: the determinant is 1e-60)
    inv_t = np.linalg.inv(m).T
    return mi.ScalarTransform4f(mi.ScalarMatrix4f(m.astype(np.float32)), mi.ScalarMatrix4f(inv_t.astype(np.float32)))


def _refinement(props) -> int | None:
    """``grid_refinement``: 1 (a uniform grid) or a power of two up to 64."""
    f = get_int(props, "amr", "grid_refinement", None, minimum=1, maximum=64)
    if f is not None and f & (f - 1):
        raise ParameterError(f"amr: grid_refinement must be 1 or a power of two (2, 4, ..., 64), got {f}")
    return f


def medium_volume(data: AMRCells | BlockVolume, method: str) -> tuple[BlockVolume, "AMRCells | None"]:
    """``(volume, cells)``: the data as blocks, resolved once here; the blocks
    of an `AMRCells` are made once per cells object (their block size
    weighed for the first medium's reconstruction: media on the same cells
    share the blocks and their device copy), and ``cells`` is that object
    (None for a `BlockVolume`)."""
    if isinstance(data, AMRCells):
        return HOST_CACHE.get(data, "volume", lambda: as_volume(data, method)), data
    return data, None


def _load_data(props, method: str) -> AMRCells | BlockVolume:
    overlap = get_string(props, "amr", "overlap", "error", OVERLAPS)
    has_file, has_data = "filename" in props.keys(), "data" in props.keys()
    if has_file == has_data:
        raise ValueError("amr: give exactly one of 'filename' (a .cells, .npz or .amrb file) "
                         "or 'data' (an AMRCells object)")
    for name in ("field", "data_checksum"):
        if has_data and name in props.keys():
            raise ParameterError(f"amr: '{name}' is for a 'filename' of data yt loads, not for 'data' "
                                 "(the cells carry their values)")
    if has_data:
        if "scalars" in props.keys():
            raise ParameterError("amr: 'scalars' names the scalars file of a 'filename', not of 'data' "
                                 "(the cells carry their values)")
        data = props["data"]
        if not isinstance(data, (AMRCells, BlockVolume)):
            raise ParameterError(f"amr: 'data' must be an mi_amr.AMRCells or BlockVolume, "
                                 f"got {type(data).__name__}")
        return data
    resolver = mi.file_resolver()
    path = Path(str(resolver.resolve(get_string(props, "amr", "filename", None))))
    field = get_string(props, "amr", "field", None)
    checksum = get_string(props, "amr", "data_checksum", None)
    if not is_native(path):                  # anything yt loads (docs/manual/medium.md)
        if field is None:
            raise ParameterError(f"amr: filename {path} is not a .cells, .npz or .amrb file: name the 'field' "
                                 "yt reads from it")
        emission_field = get_string(props, "amr", "emission_field", None)
        volume, _, _ = open_data(path, field, (emission_field,) if emission_field else ())
        volume = as_volume(volume)
        if checksum is not None and volume_checksum(volume) != checksum:
            raise ParameterError(f"amr: the data of {path} field {field} are not those this scene was written "
                                 f"for (data_checksum {checksum}, now {volume_checksum(volume)})")
        return volume
    if checksum is not None:
        raise ParameterError(f"amr: data_checksum is for data yt loads, not for {path.suffix} files")
    scalars = get_string(props, "amr", "scalars", None)
    if field is not None:
        if scalars is not None or field_scalars(path, field) is None:
            raise ParameterError(f"amr: field {field!r} of {path.name}: a .cells file's field is its "
                                 f"{path.stem}-{field}.scalars (not there, or 'scalars' given too)")
        scalars = str(field_scalars(path, field))
    if scalars is not None:
        scalars = str(resolver.resolve(scalars))
    return load_volume(path, scalars, overlap=overlap, method=method)


def _transfer_function(props, cells: BlockVolume) -> TransferFunction:
    """The extinction TF: a preset over ``tf_min``/``tf_max`` (default: the
    data's range), or a ``.json`` file rescaled as ParaView applies a
    preset (`TransferFunction.load`; ``tf_keep_range`` keeps the file's)."""
    tf = props.get("transfer_function", "foggy")
    vlo, vhi = cells.value_range
    if vhi <= vlo:                 # constant data: centre the value in the TF domain
        pad = max(0.5, 1e-3 * abs(vlo))
        vlo, vhi = vlo - pad, vhi + pad
    domain = (get_float(props, "amr", "tf_min", vlo), get_float(props, "amr", "tf_max", vhi))
    if domain[1] <= domain[0]:
        raise ParameterError(f"amr: tf_min must be below tf_max, got {domain[0]} and {domain[1]}")
    keep = get_bool(props, "amr", "tf_keep_range", False)
    if isinstance(tf, TransferFunction):
        return tf
    if isinstance(tf, str):
        return _load_tf(tf, "transfer_function", domain, (vlo, vhi), _asked(props, "tf_min", "tf_max"), keep)
    raise ParameterError(f"amr: transfer_function must be a preset name, a .json path "
                         f"or a TransferFunction, got {type(tf).__name__}")


def _asked(props, *names) -> bool:
    """Whether the scene gives any of the range parameters ``names``."""
    return any(n in props.keys() for n in names)


def _load_tf(spec: str, name: str, domain, data_range, asked: bool, keep: bool = False) -> TransferFunction:
    """The TF ``spec`` (preset, colormap or ``.json`` path, found through
    Mitsuba's file resolver: relative to the scene file) over ``domain``,
    a range the scene asked for (``asked``) or the data's ``data_range``
    (`TransferFunction.load`); its errors as one line naming ``name``."""
    if spec.endswith(".json"):
        spec = str(mi.file_resolver().resolve(spec))
    try:
        return TransferFunction.load(spec, domain if asked else None, data_range=data_range, keep_range=keep)
    except ValueError as e:
        raise ParameterError(f"amr: {name}: {e}") from e


def _emission(props, data) -> Emission | None:
    """The ``emission*`` parameters, checked against the data (None without
    ``emission``): the field exists, the emission TF's domain defaults to
    the (transformed) field's range."""
    given = [k for k in props.keys() if k.startswith("emission")]
    model = get_string(props, "amr", "emission_model", "tf", EMISSION_MODELS)
    if model == "blackbody":
        return _blackbody(props, data, given)
    if "emission" not in props.keys():
        if given:
            raise ParameterError(f"amr: {', '.join(sorted(given))} given without 'emission' (the emission TF)")
        return None
    field = get_string(props, "amr", "emission_field", None)
    transform = get_string(props, "amr", "emission_transform", "none", VALUE_TRANSFORMS)
    values = _field_values(data, field)
    lo, hi = data.field_range(field)
    if transform == "log10":
        floor = positive_floor(values, f"{data.source} field {field or 'value'}")
        lo, hi = float(np.log10(max(lo, floor))), float(np.log10(max(hi, floor)))
    if hi <= lo:
        pad = max(0.5, 1e-3 * abs(lo))
        lo, hi = lo - pad, hi + pad
    domain = (get_float(props, "amr", "emission_min", lo), get_float(props, "amr", "emission_max", hi))
    if domain[1] <= domain[0]:
        raise ParameterError(f"amr: emission_min must be below emission_max, got {domain[0]} and {domain[1]}")
    spec = props["emission"]
    if not isinstance(spec, (str, TransferFunction)):
        raise ParameterError(f"amr: emission must be a preset name, a colormap name, a .json path or a "
                             f"TransferFunction, got {type(spec).__name__}")
    tf = spec if isinstance(spec, TransferFunction) else \
        _load_tf(spec, "emission", domain, (lo, hi), _asked(props, "emission_min", "emission_max"))
    scale = check_emission_scale(get_float(props, "amr", "emission_scale", 1.0))
    return Emission(tf=tf, field=field, transform=transform, scale=scale)


def _blackbody(props, data, given) -> Emission:
    """``emission_model='blackbody'``: the medium glows by Planck's law at
    its emission field read as kelvin (`mi_amr.transfer.spectra`); an
    emission TF, its domain and a transform of the field are refused."""
    extra = sorted(set(given) & {"emission", "emission_min", "emission_max"})
    if extra:
        raise ParameterError(f"amr: emission_model='blackbody' takes no emission TF ({', '.join(extra)}): the "
                             f"emission field is read as kelvin through Planck's law")
    if get_string(props, "amr", "emission_transform", "none", VALUE_TRANSFORMS) != "none":
        raise ParameterError("amr: emission_model='blackbody' reads the emission field in kelvin; "
                             "emission_transform must be 'none'")
    field = get_string(props, "amr", "emission_field", None)
    if field is None and get_string(props, "amr", "value_transform", "none", VALUE_TRANSFORMS) != "none":
        raise ParameterError("amr: emission_model='blackbody' on the extinction field needs its values in kelvin "
                             "(value_transform 'none'), or an emission_field in kelvin")
    _field_values(data, field)
    scale = check_emission_scale(get_float(props, "amr", "emission_scale", 1.0))
    return Emission(tf=None, field=field, transform="none", scale=scale, model="blackbody")


def _field_values(data, field: str | None) -> np.ndarray:
    """The values of ``field`` of the data (None: the main field), or a
    `ParameterError` naming the fields there are."""
    if field is None:
        return data.values
    if field not in data.fields:
        have = ", ".join(repr(n) for n in sorted(data.fields)) or "none besides the main one"
        raise ParameterError(f"amr: emission_field {field!r} is not a field of {data.source} (fields: {have})")
    return data.fields[field]


def _to_world(props, data=None) -> "mi.ScalarTransform4f":
    """``to_world`` as a finite, invertible ScalarTransform4f. Without one,
    data that carry a physical domain (`mi_amr.data.metadata`) are placed
    on it, anisotropic cells included; other data fill the unit cube."""
    if "to_world" not in props.keys():
        box = physical_box(data) if data is not None else None
        if box is None:
            return mi.ScalarTransform4f()
        return as_transform4f(mi.ScalarTransform4d().translate(box[0].tolist()).scale(box[1].tolist()))
    t = props["to_world"]
    if not hasattr(t, "matrix"):
        raise ParameterError(f"amr: to_world must be a transform, got {t!r} ({type(t).__name__})")
    m = np.array(t.matrix, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise ParameterError("amr: to_world has non-finite entries")
    a = m[:3, :3]
    cond = np.linalg.cond(a)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise ParameterError(f"amr: to_world is singular or too ill-conditioned for float32 "
                             f"(condition number {cond:.3g} > {MAX_CONDITION:.0e})")
    return as_transform4f(t)
