"""Thinning (docs/design.md section 5d): the walks keep the walked grid's
segments and look the density up only where a collision survives the finer
majorants. Every estimator must stay unbiased against exact answers, and
the look-ups must drop to those of the finer grid."""

import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr.building.components import thinning_resolution
from mi_amr.structures.cost_model import THINNING_CELLS_PER_MACROCELL, thinning_candidate

from test_emission import mean_and_error, two_level_cells
from test_minorants import dense_medium
from test_modes import ENV, check, lit_scene


@pytest.mark.parametrize("control", [False, True])
def test01_ratio_tracking_through_thinned_collisions_matches_the_optical_depth(llvm, control):
    """Ratio tracking (and residual ratio tracking against the minorants)
    through a random multi-level nearest field walked on a 2^3 grid and
    thinned by a 32^3 one: each ray's mean transmittance within 5 standard
    errors of exp(-optical depth), with fewer than half the look-ups of the
    same walk without thinning."""
    from stress_oracles import assert_transmittance, face_rays, optical_depth_nearest, ratio_tracking
    thinned = dense_medium("nearest", grid_resolution=2, grid_refinement=1, thinning_resolution=32)
    assert thinned.structures.device["thinning"].host_res == (32, 32, 32)
    cells = thinned.cells
    o, d = face_rays(32, np.random.default_rng(7), 200)
    sigma = 4.0 * thinned.tf(cells.value)[:, 3].astype(np.float64)
    expected = np.exp(-optical_depth_nearest(cells, sigma, o, np.where(np.abs(d) < 1e-12, 0.0, d)))
    T, counts = ratio_tracking(thinned, o, d, 256, control=control)
    assert counts.capped.numpy().sum() == 0
    assert_transmittance(T, expected)
    lookups = counts.lookups.numpy().mean()
    del thinned
    plain = dense_medium("nearest", grid_resolution=2, grid_refinement=1, thinning_resolution=0)
    assert "thinning" not in plain.structures.device
    _, plain_counts = ratio_tracking(plain, o, d, 256, control=control)
    assert lookups < 0.5 * plain_counts.lookups.numpy().mean()


@pytest.mark.parametrize("colours", [1, 2])
def test02_emission_absorption_on_a_thinned_two_level_field(llvm, colours):
    """emission_absorption on the two-level field (value 0.25 then 0.75 along
    the ray, alpha = value) walked as one macrocell (majorant 0.75 s) and
    thinned by a 4^3 grid (0.25 s in the first half): within 5 standard
    errors of the analytic answer, delta tracking (two colours) and
    decomposition tracking (one colour: a known albedo); the counters show
    the thinned collisions (null ones without a look-up), and a real
    collision costs fewer look-ups than without thinning."""
    s = 3.0
    c0 = np.array([0.9, 0.5, 0.1])
    c1 = np.array([0.3, 0.6, 0.9]) if colours == 2 else c0
    v = np.linspace(0.0, 1.0, 65)[:, None]          # fine entries: tight range maxima
    tf = mi_amr.TransferFunction(np.hstack([c0 + v * (c1 - c0), v]), (0.0, 1.0))

    def render(thinning):
        medium = {"type": "amr", "data": two_level_cells(), "transfer_function": tf, "density_scale": s,
                  "reconstruction": "nearest", "grid_resolution": 1, "grid_refinement": 1,
                  "thinning_resolution": thinning}
        scene = mi.load_dict(lit_scene(medium, "emission_absorption", counters=True))
        image = mi.render(scene, spp=32, seed=5)
        return image, scene.integrator().counters()

    image, c = render(4)
    mean, err = mean_and_error(image)
    tau_a, tau_b = s * 0.25 / 2, s * 0.75 / 2
    a, b = c0 + 0.25 * (c1 - c0), c0 + 0.75 * (c1 - c0)
    expected = (a * (1 - np.exp(-tau_a)) + np.exp(-tau_a) * b * (1 - np.exp(-tau_b))
                + np.exp(-tau_a - tau_b) * ENV)         # self-lit colours, the environment behind
    check(mean, err, expected)
    assert c["capped"] == 0 and c["lookups"] < c["null"] + c["real"]
    _, plain = render(0)
    assert plain["lookups"] <= plain["null"] + plain["real"]
    assert c["lookups"] / c["real"] < 0.8 * plain["lookups"] / plain["real"]


def test03_thinning_is_built_only_on_large_data(llvm):
    """By default the finer majorants exist only where they have at most one
    macrocell per `THINNING_CELLS_PER_MACROCELL` cells and are finer than
    the walked grid: not on small data, and never for a tree traversal;
    ``thinning_resolution`` forces them (0: none)."""
    small = dense_medium("nearest")                  # 7,540 cells: 8^3 thinning macrocells at most
    assert len(small.volume) < THINNING_CELLS_PER_MACROCELL * 16 ** 3
    assert thinning_candidate(small.volume) <= int(max(small.structures.grid.host.res)) == 8
    assert "thinning" not in small.structures.device
    assert thinning_resolution(small.structures) == 0
    forced = dense_medium("nearest", thinning_resolution=16)
    grid = forced.structures.device["thinning"]
    assert grid.host_res == (16, 16, 16) and grid.nbytes == 20 * 16 ** 3
    assert forced.resident_bytes >= forced.volume.nbytes + grid.nbytes
    tree = dense_medium("nearest", traversal="kdtree")
    assert "thinning" not in tree.structures.device
