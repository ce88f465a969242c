"""Denoising a rendered picture: Intel Open Image Denoise (``mitsuba_oidn``,
the ``mi-amr[view]`` extra; docs/manual/adaptive.md).

The denoised picture is a guess that looks converged, not an estimate: the
unbiased one is the rendered image (the EXR), which the denoised one never
replaces. `albedo_guide` is the guide the benchmark measured
(docs/performance/adaptive.md): the ray marcher's picture (``amrvolpath`` in
``ray_march`` mode, flat shading, brightness 1) through the scene's own
camera, the TF colour where collisions happen weighted by how likely they
are, noise-free (docs/design.md section 14). It left the denoised picture
further from the converged one than no guide on the data measured, so
pictures are denoised without it.
"""

from __future__ import annotations

import importlib

import numpy as np

import mitsuba as mi

from .adaptive import render_pixels
from .plugins.medium import AMRMedium, scene_media

#: Samples per pixel of the albedo guide (the marcher has no noise: they
#: only antialias the pixels' footprints).
GUIDE_SPP = 4


def denoiser_missing() -> str | None:
    """Why pictures cannot be denoised here (None: they can)."""
    try:
        importlib.import_module("mitsuba_oidn")      # the mi-amr[view] extra
    except ImportError as e:
        return f"denoising needs mitsuba-oidn: pip install 'mi-amr[view]' ({e})"
    return None


def albedo_guide(scene: mi.Scene, seed: int = 0, sensor: int = 0) -> np.ndarray | None:
    """The albedo guide of a loaded ``scene`` (module docstring): float32
    (H, W, 3) in [0, 1]; None when the scene has no ``amr`` medium."""
    if not any(isinstance(m, AMRMedium) for m in scene_media(scene)):
        return None
    marcher = mi.load_dict({"type": "amrvolpath", "mode": "ray_march", "shading": "flat", "brightness": 1.0})
    width, height = (int(v) for v in scene.sensors()[sensor].film().crop_size())
    sums = render_pixels(scene, np.arange(width * height, dtype=np.uint32), GUIDE_SPP, seed, sensor,
                         integrator=marcher)
    w = sums[..., -1:]
    colour = np.where(w > 0, sums[..., :3] / np.where(w > 0, w, 1.0), 0.0)
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def denoise(image: np.ndarray, albedo: np.ndarray | None = None) -> np.ndarray:
    """``image`` (linear RGB(A), HDR) through Open Image Denoise, with the
    noise-free ``albedo`` guide when given: float32 (H, W, 3). A
    `ValueError` when the denoiser is missing (`denoiser_missing`)."""
    missing = denoiser_missing()
    if missing is not None:
        raise ValueError(missing)
    import mitsuba_oidn
    colour = np.ascontiguousarray(np.asarray(image, dtype=np.float32)[..., :3])
    if albedo is None:
        return np.asarray(mitsuba_oidn.denoise(colour, hdr=True), dtype=np.float32)
    return np.asarray(mitsuba_oidn.denoise(colour, np.ascontiguousarray(albedo, np.float32), hdr=True,
                                           clean_aux=True), dtype=np.float32)
