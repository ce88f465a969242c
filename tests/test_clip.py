"""The ``amr`` medium's clip plane (``clip_normal``, ``clip_offset``;
`AMRMedium.set_clip_plane`): the medium is empty on the plane's far side in
every integrator and mode, shadow rays included, and clipping only narrows
the walks (never more look-ups)."""

import mitsuba as mi
import numpy as np
import pytest

from mi_amr import AMRCells, TransferFunction
from mi_amr.params import plugin_error
from mi_amr.testing import block_z_scores, render_passes

from test_emission import flat_tf, mean_and_error, ortho_scene, uniform_cells

ENV = np.array([0.6, 0.7, 0.9])
ALBEDO = np.array([0.8, 0.5, 0.2])


def lit(medium, integrator="amrvolpath", **options):
    """`ortho_scene` (rays along +z through x, y in [0.2, 0.8]) under a
    constant environment and a sun from the +x side (its shadow rays cross
    the clipped half)."""
    d = ortho_scene(medium, **options)
    d["integrator"]["type"] = integrator
    d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": ENV.tolist()}}
    d["sun"] = {"type": "directional", "direction": [-1.0, 0.2, 0.4], "irradiance": {"type": "rgb", "value": 3.0}}
    return d


def test01_the_clipped_half_is_empty_and_the_kept_half_the_slab(llvm):
    """A homogeneous slab (optical depth 1.3 along the rays) clipped at
    x = 0.5, emission_absorption: pixels whose rays run at x > 0.5 see the
    environment exactly; the others albedo (1 - e^-tau) + L e^-tau within
    five standard errors."""
    sigma = 1.3
    med = {"type": "amr", "data": uniform_cells(8, 0.5), "transfer_function": flat_tf(ALBEDO, 1.0),
           "density_scale": sigma, "reconstruction": "nearest", "clip_normal": [1, 0, 0], "clip_offset": 0.5}
    d = ortho_scene(med, res=16, mode="emission_absorption")
    d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": ENV.tolist()}}
    img = np.array(mi.render(mi.load_dict(d), spp=32, seed=3), np.float64)
    sensor = mi.load_dict(d["sensor"])
    rays = [sensor.sample_ray(0.0, 0.5, mi.Point2f((i + 0.5) / 16, 0.5), mi.Point2f(0.5))[0] for i in range(16)]
    x = np.array([r.o.x[0] + r.d.x[0] * (0.5 - r.o.z[0]) / r.d.z[0] for r in rays])   # where each column
    #                                                                                  # crosses the slab
    clipped, kept = x > 0.52, x < 0.48
    assert clipped.sum() >= 6 and kept.sum() >= 6
    np.testing.assert_allclose(img[:, clipped], np.broadcast_to(ENV, img[:, clipped].shape), rtol=1e-6)
    mean, err = mean_and_error(img[:, kept])
    expected = ALBEDO * (1 - np.exp(-sigma)) + ENV * np.exp(-sigma)
    assert np.all(np.abs(mean - expected) < 5 * err + 1e-4), (mean, expected, err)


def _half_removed(cells: AMRCells) -> AMRCells:
    """The cells with value 0 (transparent under the ramp TF) at x >= 4
    (the far side of the plane x = 0.5 of the 8-cell cube)."""
    v = np.where(cells.pos[:, 0] >= 4, 0.0, cells.values)
    return AMRCells(cells.pos, cells.level, v)


@pytest.mark.parametrize("integrator,mode", [("amrvolpath", "emission_absorption"), ("amrvolpath", "single"),
                                             ("amrvolpath", "multi"), ("volpath", None)])
def test02_clipped_equals_the_data_with_that_half_removed(llvm, integrator, mode):
    """A field whose opacity varies, lit by a sun from the clipped side:
    clipped at x = 0.5 it renders as the same field with every cell past
    the plane made transparent, per 8x8 block within Monte Carlo error (in
    each mode, and in Mitsuba's volpath through the medium's interface):
    the clip acts on free flights and shadow rays alike."""
    rng = np.random.default_rng(4)
    g = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    cells = AMRCells(g, np.zeros(len(g), np.int32), rng.uniform(0.2, 1.0, len(g)))
    tf = TransferFunction.from_colormap("viridis", [(0.0, 0.0), (1.0, 1.0)], (0.0, 1.0))
    base = {"type": "amr", "transfer_function": tf, "density_scale": 4.0, "reconstruction": "nearest"}
    options = {} if mode is None else {"mode": mode}
    clipped = mi.load_dict(lit(dict(base, data=cells, clip_normal=[1, 0, 0], clip_offset=0.5), integrator,
                               res=16, **options))
    a = render_passes(clipped, 8, 8, seed0=0)
    del clipped
    removed = mi.load_dict(lit(dict(base, data=_half_removed(cells)), integrator, res=16, **options))
    b = render_passes(removed, 8, 8, seed0=100)
    z = block_z_scores(a, b, block=8)
    assert np.abs(z).max() < 5.0, z
    assert np.abs(a.mean(0)[:, :8] - a.mean(0)[:, 8:]).mean() > 0.01          # the halves differ


def test03_clipping_never_costs_more_and_moves_without_a_rebuild(llvm):
    """The same frame with the plane through the middle makes fewer
    density look-ups than without it; `set_clip_plane` moves the plane in
    the loaded scene (no reload) and None removes it; bad planes are
    refused in one line."""
    rng = np.random.default_rng(5)
    g = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    cells = AMRCells(g, np.zeros(len(g), np.int32), rng.uniform(0.2, 1.0, len(g)))
    tf = TransferFunction.from_colormap("viridis", [(0.0, 0.0), (1.0, 1.0)], (0.0, 1.0))
    med = {"type": "amr", "data": cells, "transfer_function": tf, "density_scale": 3.0, "reconstruction": "nearest"}
    scene = mi.load_dict(lit(med, res=16, mode="multi", counters=True))
    medium = scene.shapes()[0].interior_medium()

    def lookups():
        scene.integrator().reset_counters()
        mi.render(scene, spp=4, seed=1)
        c = scene.integrator().counters()
        return c["lookups"] + c["shadow_lookups"]
    whole = lookups()
    medium.set_clip_plane([1, 0, 0], 0.5)
    half = lookups()
    medium.set_clip_plane(None)
    again = lookups()
    assert half < 0.8 * whole and again == whole, (whole, half, again)
    for bad, words in (({"clip_offset": 0.2}, "clip_offset needs clip_normal"),
                       ({"clip_normal": [0, 0, 0]}, "clip_normal must be a nonzero")):
        with pytest.raises(Exception) as e:
            mi.load_dict(dict(med, **bad))
        line = plugin_error(str(e.value))
        assert "\n" not in line and words in line, line
