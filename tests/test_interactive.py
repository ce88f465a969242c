"""Transfer-function changes: majorants recomputed, nothing rebuilt or recompiled."""

import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr

from conftest import random_amr, volume_scene


def _key(params, suffix):
    keys = [k for k in params.keys() if k.endswith(suffix)]
    assert len(keys) == 1, keys
    return keys[0]


def test01_traverse_exposes_tf_and_scale(llvm):
    cells = random_amr(3)
    scene = mi.load_dict(volume_scene({"type": "amr", "data": cells, "transfer_function": "ramp",
                                       "density_scale": 5.0}, res=16))
    med = mi_amr.amr_media(scene)[0]
    params = mi.traverse(scene)
    k_scale = _key(params, "density_scale")
    k_rgba = _key(params, "tf_rgba")
    k_dom = _key(params, "tf_domain")
    assert dr.width(params[k_rgba]) == 4 * len(med.tf)
    before = med.majorant_grid.copy()
    params[k_scale] = 10.0
    params.update()
    np.testing.assert_allclose(med.majorant_grid, 2 * before, rtol=1e-6)
    # zero opacity everywhere: every majorant becomes 0
    rgba = np.array(params[k_rgba]).reshape(-1, 4)
    rgba[:, 3] = 0
    params[k_rgba] = mi.Float(rgba.ravel())
    params.update()
    assert med.majorant_grid.max() == 0 and med.global_majorant == 0
    params[k_dom] = mi.Float([0.0, 2.0])
    params.update()
    assert med.tf.domain == (0.0, 2.0)


def _structure(ir: str) -> str:
    """Kernel IR with register and kernel names erased: what is left is the
    code itself (operations, types and every literal constant)."""
    ir = re.sub(r"drjit_[0-9a-f]{32}", "drjit_K", ir)
    return re.sub(r"%[A-Za-z_]*\d+(?:_[A-Za-z0-9]+)*", "%r", ir)


@pytest.mark.parametrize("reconstruction,refinement", [("tent", 1), ("nearest", 1), ("nearest", 2)])
def test02_tf_change_recompiles_no_kernel(llvm, reconstruction, refinement):
    """Change the TF of a loaded scene: the next render launches only kernels
    whose code equals that of kernels before the change (no TF value is
    baked into code, so nothing needs compiling: Dr.Jit's kernel cache has
    them), and its image equals a freshly loaded scene with the new TF
    (same seed). The grid resolution is fixed: its automatic choice depends
    on the initial TF. A two-level grid (refinement 2) decides again which
    coarse macrocells to refine, on the device.

    Register and kernel names are compared away (they follow the order in
    which Dr.Jit meets variables); the code itself must be the same.
    ``nearest`` grids also carry value masks (per-bin maxima and byte tables
    are recomputed on the change)."""
    cells = random_amr(4)
    base = {"type": "amr", "data": cells, "grid_resolution": 8, "reconstruction": reconstruction,
            "grid_refinement": refinement}
    import gc
    gc.collect()
    dr.eval()                 # nothing left over from earlier tests joins the kernels below
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()                                    # clear
    try:
        scene = mi.load_dict(volume_scene(dict(base, transfer_function="spiky", density_scale=20.0),
                                          res=16, integrator="amrvolpath"))
        mi.render(scene, spp=2, seed=0)
        # Mitsuba builds media in worker threads, whose kernels this thread's
        # history does not list: one TF update here records the majorant kernel
        mi_amr.set_transfer_function(scene, "spiky", density_scale=20.0)
        first = np.array(mi.render(scene, spp=2, seed=0))
        before = {_structure(h["ir"].getvalue()) for h in dr.kernel_history()
                  if h.get("type") == dr.KernelType.JIT}
        tf = mi_amr.TransferFunction.from_colormap("magma", [(0, 0), (0.5, 1), (1, 0.2)],
                                                   cells.value_range, n=64)   # other size and values
        mi_amr.set_transfer_function(scene, tf, density_scale=35.0)
        second = np.array(mi.render(scene, spp=2, seed=0))
        history = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert history, "no kernel was launched"
    new = [h for h in history if _structure(h["ir"].getvalue()) not in before]
    assert not new, [h["ir"].getvalue()[:3000] for h in new]
    assert np.isfinite(second).all() and np.abs(second - first).max() > 1e-3
    fresh = mi.load_dict(volume_scene(dict(base, transfer_function=tf, density_scale=35.0),
                                      res=16, integrator="amrvolpath"))
    np.testing.assert_array_equal(np.array(mi.render(fresh, spp=2, seed=0)), second)


def test03_kdtree_is_rebuilt_and_says_so(llvm):
    cells = random_amr(5)
    med = mi.load_dict({"type": "amr", "data": cells, "traversal": "kdtree", "transfer_function": "spiky"})
    assert "kdtree_rebuild" not in med.build_seconds
    mi_amr.set_transfer_function(med, "foggy")
    assert med.build_seconds["kdtree_rebuild"] > 0
    with pytest.raises(ValueError, match="density_scale"):
        mi_amr.set_transfer_function(med, density_scale=-1.0)
