"""``mi-amr info DATA [--field F]``: what a data set holds, opened the way
``mi-amr render DATA --field F`` opens it (`mi_amr.data.opening.open_data`:
``.cells``/``.npz``/``.amrb`` files, or anything yt loads). A yt data set
without ``--field`` is described from its headers and index, no value read
(`mi_amr.data.yt_summary`, printed by `format_dataset`).

`describe` gathers levels, cells per level and their physical sizes, the
domain, each field's range with its shares of zeros and negatives (per cell
and volume-weighted) and the memory of an ``amr`` medium with the default
structures (`mi_amr.structures.footprint.medium_bytes`); `format_info` prints it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..autoscene import plan_scene
from ..data.statistics import value_stats
from ..data.opening import is_native, open_data, open_dataset, yt_field
from ..data.io import load_volume
from ..data.metadata import cell_size
from ..data.yt_import import resolve_field
from ..data.yt_summary import summarise
from ..memory import format_bytes
from ..structures.footprint import medium_bytes


def describe(data, field: str | None = None, scalars: str | None = None, plan: bool = False) -> dict:
    """Everything `format_info` prints about ``data`` (a path), as plain
    JSON types. ``field``: the yt field, or for a ``.cells`` file the
    ``NAME-FIELD.scalars`` beside it; ``scalars``: a ``.cells`` file's
    scalars file, named; ``plan``: also the scene ``mi-amr render`` plans
    for them (`mi_amr.autoscene.plan_scene` on the data read once), with
    its predicted picture."""
    path = Path(str(data))
    ds = None
    if scalars is not None:
        if path.suffix != ".cells":
            raise ValueError(f"{path}: --scalars is for .cells files")
        volume = load_volume(path, scalars)
    elif is_native(path):
        volume, _, _ = open_data(path, field)
    else:
        ds = open_dataset(path)
        if field is None:
            return summarise(ds)
        volume, _, _ = open_data(ds, field)
    meta = dict(getattr(volume, "meta", {}) or {})
    lo, hi = volume.bounds
    levels = [int(L) for L in volume.levels]
    counts = _level_counts(volume)
    dx = cell_size(meta)
    total_volume = sum(counts[L] * 8.0 ** L for L in levels)
    main_units = _units(ds, resolve_field(ds, field)) if ds is not None else meta.get("units", "")
    info = {
        "source": str(volume.source), "data": str(path), "field": field, "code": meta.get("code"),
        "cells": int(len(volume)),
        "levels": {L: counts[L] for L in levels},
        "level_table": [{"level": L, "width": 1 << L, "cells": counts[L], "refinement": levels[-1] - L,
                         "volume_share": counts[L] * 8.0 ** L / total_volume,
                         "cell_size": None if dx is None else (dx * (1 << L)).tolist()} for L in levels],
        "bounds": [lo.tolist(), hi.tolist()],
        "extent": (hi - lo).tolist(),
        "domain": _domain(meta, ds),
        "value_range": [float(x) for x in volume.value_range],
        "bytes": int(volume.nbytes),
        "fields": {_main_name(field, meta): dict(_field_stats(volume, None), units=main_units)},
        "medium_bytes": medium_bytes(volume),
    }
    for name in sorted(getattr(volume, "fields", {}) or {}):
        info["fields"][name] = dict(_field_stats(volume, name), units="")
    if ds is not None:
        info["fields_on_disk"] = {_field_name(f): _units(ds, f) for f in ds.field_list}
    if meta.get("value_transform"):
        info["value_transform"] = meta["value_transform"]
    if plan:
        info["plan"] = _plan(volume)
    return info


def _plan(volume) -> dict:
    """The default plan of ``volume`` as plain JSON types (`plan_scene`)."""
    p = plan_scene(volume)
    seen = p.visibility
    return {"transform": p.transform, "tf": p.tf, "tf_range": list(p.tf_range), "density_scale": p.density_scale,
            "optical_depth": p.optical_depth, "peak_depth": p.peak_depth,
            "predicted": None if seen is None else {"shown": seen.shown, "opaque": seen.opaque,
                                                    "footprint_pixels": seen.footprint},
            "notes": list(p.notes[1:])}


def _field_name(f) -> str:
    return ",".join(f) if isinstance(f, tuple) else str(f)


def _main_name(field, meta) -> str:
    return str(field or meta.get("field") or "value")


def _units(ds, field) -> str:
    """The units yt gives ``field`` ('' when it cannot say)."""
    try:
        return str(ds._get_field_info(yt_field(field)).units)
    except Exception:           # yt's field lookup varies by frontend: units are informative only
        return ""


def _level_counts(volume) -> dict:
    """Cells per level (finest = 0): the present cells of each block."""
    if hasattr(volume, "block"):
        b3 = volume.block ** 3
        step = max(1, (1 << 22) // b3)
        present = np.zeros(len(volume.level), np.int64)
        for s in range(0, len(volume.level), step):
            present[s:s + step] = (~np.isnan(volume.values[s * b3:(s + step) * b3].reshape(-1, b3))).sum(axis=1)
        return {int(L): int(present[volume.level == L].sum()) for L in volume.levels}
    return {int(L): int((volume.level == L).sum()) for L in volume.levels}


def _field_stats(volume, name) -> dict:
    """Range and shares of zeros and negatives of one field (None: the
    main values): per cell and weighted by cell volume."""
    s = value_stats(volume, name)
    return {"min": s.min, "max": s.max,
            "positive_min": s.positive_min if s.has_positive else None,
            "positive_max": s.positive_max if s.has_positive else None,
            "zero_cells": s.zero_cells, "negative_cells": s.negative_cells,
            "zero_share_cells": s.zero_cells / s.cells, "negative_share_cells": s.negative_cells / s.cells,
            "zero_share_volume": s.zero_volume / s.volume, "negative_share_volume": s.negative_volume / s.volume}


def _domain(meta, ds) -> dict | None:
    """The physical domain: edges in the data's length unit (and in cm from
    yt), or None when the data carry no domain."""
    if "domain_left_edge" not in meta:
        return None
    out = {"left": [float(x) for x in meta["domain_left_edge"]],
           "right": [float(x) for x in meta["domain_right_edge"]],
           "unit": meta.get("length_unit", ""), "finest_cells": [int(n) for n in meta["domain_cells"]]}
    if ds is not None:
        try:
            out["cm_per_unit"] = float(ds.length_unit.in_cgs().d)
        except Exception:       # a frontend without a length unit
            pass
    return out


def _mib(n) -> str:
    return format_bytes(float(n))


def format_dataset(info: dict) -> str:
    """The text of a yt data set described without a field
    (`mi_amr.data.yt_summary.summarise`): code, domain, levels (yt's
    numbering: 0 the coarsest) and every field with its units."""
    d = info["domain"]
    cm = f" (1 code_length = {d['cm_per_unit']:.6g} cm)" if d.get("cm_per_unit") else ""
    lines = [f"data set     : {info['dataset']}",
             f"code         : {info['code']} (yt's {info['dataset_type']}), {info['dimensionality']}-D, "
             f"{'an octree' if info['index'] == 'octree' else 'grid patches'}",
             f"domain       : {d['left']} .. {d['right']} {d['unit']}{cm}, root "
             f"{' x '.join(str(n) for n in d['root_cells'])} cells, refined by {d['refine_by']:g}",
             f"levels       : {len(info['levels'])} (0 the coarsest, as yt counts; mi-amr's level 0 is the finest)"]
    for row in info["levels"]:
        held = (f"{row['grids']} grids, {row['cells']} cells" if "grids" in row else
                f"{row['octs']} octs, {row['cells']} cells ({row['leaf_cells']} leaves)" if "octs" in row else
                "cells not counted by this reader")
        size = " x ".join(f"{x:.4g}" for x in row["cell_size"])
        lines.append(f"  level {row['level']:2d}: {held}; cells of {size} code_length")
    lines.append(f"fields on disk ({len(info['fields_on_disk'])}; --field NAME or TYPE,NAME):")
    lines += [f"  {k} [{u}]" if u else f"  {k}" for k, u in info["fields_on_disk"].items()]
    by_type = {}
    for k, u in info["fields_derived"].items():
        ftype, name = k.split(",", 1)
        by_type.setdefault(ftype, []).append(f"{name} [{u}]" if u else name)
    lines.append(f"fields yt derives ({len(info['fields_derived'])}):")
    lines += [f"  {ftype}: {', '.join(names)}" for ftype, names in by_type.items()]
    return "\n".join(lines)


def format_info(info: dict) -> str:
    """The text ``mi-amr info`` prints: the summary `AMRCells.summary`
    always printed (source, cells, box, extent, value range, memory, cells
    per level; level 0 the finest, refinement 0 the coarsest), then the
    domain, the fields and the medium's memory; a data set described
    without a field: `format_dataset`."""
    if "fields_derived" in info:
        return format_dataset(info)
    lo, hi = info["bounds"]
    unit = (info["domain"] or {}).get("unit", "")
    lines = [f"source       : {info['source']}",
             f"cells        : {info['cells']}",
             f"bounding box : {lo} .. {hi} (finest-cell units)",
             f"extent       : {info['extent']}",
             f"value range  : [{info['value_range'][0]:.6g}, {info['value_range'][1]:.6g}]",
             f"memory       : {info['bytes'] / 2**20:.2f} MiB (blocks: values, further fields, block headers)",
             "cells per level:"]
    for row in info["level_table"]:
        size = "" if row["cell_size"] is None else \
            " cells of " + " x ".join(f"{x:.4g}" for x in row["cell_size"]) + f" {unit}"
        lines.append(f"  level {row['level']:2d} (width {row['width']:>6d}): {row['cells']}"
                     f" (refinement {row['refinement']}; {100 * row['volume_share']:.3g}% of the volume){size}")
    d = info["domain"]
    if d is None:
        lines.append("domain       : none in the metadata (cells are unit cubes)")
    else:
        cm = f" (1 {d['unit']} = {d['cm_per_unit']:.6g} cm)" if "cm_per_unit" in d else ""
        lines.append(f"domain       : {d['left']} .. {d['right']} {d['unit']}{cm}, "
                     f"{' x '.join(str(n) for n in d['finest_cells'])} finest cells")
    if info.get("value_transform"):
        lines.append(f"values are   : {info['value_transform']} (metadata)")
    lines.append("fields (zeros and negatives: share of the cells / share of the volume):")
    for name, f in info["fields"].items():
        units = f" [{f['units']}]" if f["units"] else ""
        pos = (f", positive {f['positive_min']:.6g} .. {f['positive_max']:.6g}" if f["positive_min"] is not None
               else ", none positive")
        lines.append(f"  {name}{units}: [{f['min']:.6g}, {f['max']:.6g}]{pos}; zeros "
                     f"{100 * f['zero_share_cells']:.3g}% / {100 * f['zero_share_volume']:.3g}%, negatives "
                     f"{100 * f['negative_share_cells']:.3g}% / {100 * f['negative_share_volume']:.3g}%")
    if info.get("fields_on_disk"):
        lines.append("on disk      : " + ", ".join(f"{k} [{u}]" if u else k for k, u in info["fields_on_disk"].items()))
    m = info["medium_bytes"]
    r = m["grid_resolution"]
    lines.append(f"amr medium   : {_mib(m['total'][0])} to {_mib(m['total'][1])} with the default structures "
                 f"({m['reconstruction']}): data {_mib(m['data'])} + point-location hash {_mib(m['hash'])} "
                 f"+ macrocell grid {_mib(m['grid'][0])} ({r[0]} per axis) to {_mib(m['grid'][1])} ({r[1]} per "
                 f"axis), as the cost model chooses (an estimate)"
                 + (f", + the thinning grid's finer majorants {_mib(m['thinning'])} ({m['thinning_resolution']} per "
                    "axis) where the grid is coarser" if m["thinning"] else "")
                 + f"; building the hash peaks at {_mib(m['build_peak'])}")
    if "plan" in info:
        lines.append("the picture mi-amr render plans (docs/manual/data.md, Default pictures):")
        lines += [f"  {note}" for note in info["plan"]["notes"]]
    return "\n".join(lines)
