"""mi-amr: path tracing of adaptive-mesh-refinement volume data in Mitsuba 3.

Importing this package registers the ``amr`` medium for the active Mitsuba
variant and for every variant selected later. Its Python front door
(`scene`, `show`, `render_jobs`, `scene_for`) needs no variant set first: it
renders in the one set, else in the one ``mi-amr render`` chooses
(`mi_amr.rendering.use_variant`).
"""

from __future__ import annotations

from ._llvm import ensure_llvm_path

ensure_llvm_path()

import mitsuba as mi  # noqa: E402

from .scene_writer import scene_for as _scene_for  # noqa: E402
from .data import datasets  # noqa: E402,F401
from .data.cells import AMRCells  # noqa: E402
from .data.convert import dense_to_amr  # noqa: E402
from .autoscene import plan_scene  # noqa: E402
from .data.opening import open_data  # noqa: E402
from .data_scene import DataScene, scene, show  # noqa: E402
from .rendering import RenderJob, render_jobs, use_variant  # noqa: E402
from .data.io import load_cells, read_exabricks, read_npz, write_exabricks, write_npz  # noqa: E402
from .native_file import save_data as save_cells  # noqa: E402  (.amrb with its grids and statistics)
from .data.yt_import import from_yt as _from_yt, world_transform as _world_transform  # noqa: E402
from .core.jit_struct import refresh  # noqa: E402
from .plugins.integrator import integrator_class  # noqa: E402
from .plugins.prb_integrator import prb_integrator_class  # noqa: E402
from .plugins.medium import AMRMedium, amr_media, medium_class, require_jit_rgb_variant, scene_media  # noqa: E402
from .transfer.function import TransferFunction  # noqa: E402

__version__ = "0.1.0"
__all__ = ["AMRCells", "TransferFunction", "dense_to_amr", "load_cells", "save_cells",
           "read_exabricks", "write_exabricks", "read_npz", "write_npz", "register",
           "set_transfer_function", "amr_media", "from_yt", "world_transform", "scene_for", "scene", "show", "DataScene",
           "open_data", "plan_scene", "RenderJob", "render_jobs"]


def register(variant: str | None = None):
    """Register the mi-amr plugins for the active variant (called on import
    and on every variant change). The plugin classes are made for the
    variant that is active when a scene instantiates them."""
    if mi.variant() is None:
        return
    refresh()

    def make_medium(props):
        require_jit_rgb_variant("the 'amr' medium")
        return medium_class()(props)

    def make_integrator(props):
        require_jit_rgb_variant("the 'amrvolpath' integrator")
        return integrator_class()(props)

    def make_prb_integrator(props):
        require_jit_rgb_variant("the 'amrprbvolpath' integrator")
        return prb_integrator_class()(props)

    mi.register_medium("amr", make_medium)
    mi.register_integrator("amrvolpath", make_integrator)
    mi.register_integrator("amrprbvolpath", make_prb_integrator)


def _on_variant_change(old, new):
    if new is not None:
        register()


mi.detail.add_variant_callback(_on_variant_change)
register()


def from_yt(ds, field, **kw):
    """Leaf cells of a yt grid or octree data set (see `mi_amr.data.yt_import.from_yt`)."""
    return _from_yt(ds, field, **kw)


def world_transform(ds):
    """``to_world`` for a yt dataset's domain (see `mi_amr.data.yt_import`)."""
    return _world_transform(ds)


def scene_for(data, field=None, variant: str | None = None, **options) -> dict:
    """A scene dictionary for ``mi.load_dict`` made from AMR data alone:
    camera framing the domain at its true aspect, sun and sky, a TF over
    the values' distribution (see `mi_amr.scene_writer.scene_for`), in
    ``variant``, else the one set, else the one ``mi-amr render`` chooses
    (`use_variant`)."""
    use_variant(variant)
    return _scene_for(data, field, **options)


def set_transfer_function(scene_or_medium, tf=None, density_scale=None):
    """Change the transfer function (new table, domain or size) and/or the
    density scale of every `amr` medium of a scene, or of one medium. Only
    the majorants are recomputed; no structure is rebuilt (except the
    pre-classified kd-tree) and no kernel is recompiled. Returns the media."""
    media = amr_media(scene_or_medium)
    if not media:
        raise ValueError("set_transfer_function: no amr medium found")
    for m in media:
        new_tf = m.tf if tf is None else TransferFunction.load(tf, m.tf.domain)
        m.set_transfer_function(new_tf, density_scale)
    return media
