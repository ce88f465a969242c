"""``emission_absorption`` equals a converged emission-absorption ray march
of the same field and TF (emission sigma_t times the colour, absorption
sigma_t): `mi_amr.reference.emission_absorption_march` on a three-level
field with a TF whose colour and opacity vary, per 4 x 4 pixel block within
Monte Carlo error (the render's variance from independent passes)."""

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr import TransferFunction
from mi_amr.testing import render_passes
from mi_amr.reference import emission_absorption_march

from conftest import random_amr

RES, SUB = 32, 4                     # pixels per side; reference rays per pixel side
ENV = np.array([0.3, 0.35, 0.45])


def scene_dict(cells, tf, density):
    T = mi.ScalarTransform4f
    return {"type": "scene",
            "integrator": {"type": "amrvolpath", "mode": "emission_absorption", "brightness": 1.5},
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": T().look_at([1.6, 1.2, 2.0], [0.5, 0.5, 0.5], [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": RES, "height": RES, "rfilter": {"type": "box"}}},
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": ENV.tolist()}},
            "cube": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                     "bsdf": {"type": "null"},
                     "interior": {"type": "amr", "data": cells, "transfer_function": tf,
                                  "density_scale": density, "reconstruction": "nearest"}}}


def pixel_rays(scene):
    """``SUB x SUB`` stratified rays per pixel (the box filter's footprint),
    from the scene's own sensor: (origins, dirs), pixels row by row."""
    sensor = scene.sensors()[0]
    n = RES * SUB
    idx = dr.arange(mi.UInt32, n * n)
    pos = mi.Point2f((mi.Float(idx % n) + 0.5) / n, (mi.Float(idx // n) + 0.5) / n)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    return [np.stack([np.asarray(c, np.float64) for c in (v.x, v.y, v.z)], axis=1) for v in (ray.o, ray.d)]


def block_means(img, block=4):
    h, w = img.shape[:2]
    return img.reshape(h // block, block, w // block, block, -1).mean(axis=(1, 3))


def test01_emission_absorption_is_the_ray_marched_integral(llvm):
    cells = random_amr(seed=3, n=16, levels=3)
    lo, hi = cells.value_range
    tf = TransferFunction.from_colormap("plasma", [(0.0, 0.0), (0.3, 0.15), (0.7, 0.9), (1.0, 0.5)], (lo, hi))
    scene = mi.load_dict(scene_dict(cells, tf, 6.0))
    passes = render_passes(scene, 8, 16, seed0=11)
    o, d = pixel_rays(scene)
    ref = emission_absorption_march(cells, tf, 6.0, o, d, background=ENV, brightness=1.5)
    ref = ref.reshape(RES, SUB, RES, SUB, 3).mean(axis=(1, 3))
    blocks = np.stack([block_means(p) for p in passes])                    # (passes, 8, 8, 3)
    mean, se = blocks.mean(0), blocks.std(0, ddof=1) / np.sqrt(len(blocks))
    want = block_means(ref)
    z = (mean - want) / np.sqrt(se ** 2 + (2e-3 * want) ** 2)              # + the march's own error
    assert np.abs(z).max() < 5.0, np.abs(z).max()
    assert (mean - ENV).std() > 0.05                                        # the field is seen, not the sky
    # and it has the power to tell a brightness 20% off
    off = emission_absorption_march(cells, tf, 6.0, o, d, background=ENV, brightness=1.2)
    off = block_means(off.reshape(RES, SUB, RES, SUB, 3).mean(axis=(1, 3)))
    assert np.abs((mean - off) / np.sqrt(se ** 2 + (2e-3 * off) ** 2)).max() > 10.0
