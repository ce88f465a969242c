"""The isosurface comparison's instruments (mi_amr.bench.iso): its crack
and error figures, the rays aimed at the level boundaries, yt's welded
mesh; yt's per-grid surface has cracks there and the count finds them."""

import numpy as np
import pytest

from mi_amr.bench.iso import (CENTRE, RADIUS, boundary_rays, camera_rays, crack_mask, hit_figures, mesh_hits,
                              open_edges, yt_surface)
from mi_amr.data.radial_example import boundary_distance, ray_sphere, write_enzo_radial


def test01_exact_hits_have_no_cracks_and_a_hole_is_counted(variant):
    o, d = camera_rays(64)
    t = ray_sphere(o, d, CENTRE, RADIUS)
    f = hit_figures(t, o, d, 2)
    assert f["rays_through"] > 1000 and f["cracks"] == 0 and f["stray_hits"] == 0
    assert f["error_max"] == 0.0 and f["hits_within_0.5%"] == 1.0
    # a hole: rays whose exact hit lies within 0.02 of a level boundary see the back of the sphere
    x = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    hole = np.isfinite(t) & (boundary_distance(x, 2) < 0.02)
    back = 2.0 * np.sum((CENTRE - o) * d, axis=1) - t                # the far crossing (unit d): 2 s - t_near
    t_holed = np.where(hole, back, t)
    f = hit_figures(t_holed, o, d, 2)
    through = crack_mask(t_holed, o, d)
    assert f["cracks"] == int(through.sum()) > 0
    assert f["cracks_near_a_boundary"] == f["cracks"] and f["crack_share_elsewhere"] == 0.0


def test02_rays_aimed_at_the_level_boundaries(variant):
    o, d = boundary_rays(3, 2000, seed=1)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-12)
    aim = o + 2.0 * d
    assert np.all(boundary_distance(aim, 3) < 1e-12)                # on a boundary face
    r = np.linalg.norm(aim - CENTRE, axis=1)
    assert np.all((r <= RADIUS + 1e-12) & (r >= 0.9 * RADIUS))      # just inside the sphere
    assert np.all(np.sum((aim - CENTRE) * (o - aim), axis=1) > 0.0)  # from the outer hemisphere
    assert np.all(np.isfinite(ray_sphere(o, d, CENTRE, RADIUS)))


def test03_yt_surface_is_closed_on_one_level_and_open_at_level_boundaries(tmp_path, variant):
    yt = pytest.importorskip("yt")
    for levels in (1, 2):
        ds = yt.load(str(write_enzo_radial(tmp_path / f"radial{levels}", levels)))
        vertices, faces = yt_surface(ds, RADIUS)
        r = np.linalg.norm(vertices - CENTRE, axis=1)
        assert np.all(np.abs(r - RADIUS) < 0.05 * RADIUS)
        if levels == 1:
            assert open_edges(faces) == 0
            continue
        assert open_edges(faces) > 0
        # every open edge lies on a level boundary; rays aimed there pass through (cracks), none elsewhere
        o, d = boundary_rays(levels, 4000, seed=2)
        f = hit_figures(mesh_hits(vertices, faces, o, d), o, d, levels)
        assert f["cracks"] > 0.05 * f["rays_through"]
        o, d = camera_rays(96)
        f = hit_figures(mesh_hits(vertices, faces, o, d), o, d, levels)
        assert f["crack_share_elsewhere"] == 0.0


@pytest.mark.slow
def test04_bench_iso_runs_and_finds_yt_cracks_and_none_of_ours(tmp_path, variant):
    """``python -m mi_amr.bench --iso`` end to end on 2 levels (no figure,
    no frame rate): yt's surface has cracks at the level boundaries, the
    tent isosurface none, on the same rays."""
    pytest.importorskip("yt")
    import json
    from mi_amr.bench.__main__ import main
    assert main(["--iso", "--iso-levels", "2", "--iso-crack-res", "96", "--iso-picture", "none", "--iso-cells",
                 "--out", str(tmp_path)]) == 0
    rec = json.loads((tmp_path / "iso.json").read_text())["surfaces"]["2"]
    assert rec["boundary"]["yt"]["cracks"] > 0.05 * rec["boundary"]["yt"]["rays_through"]
    assert rec["boundary"]["yt"]["crack_share_elsewhere"] == 0.0
    for rays in ("camera", "boundary"):
        assert rec[rays]["tent"]["cracks"] == 0 and rec[rays]["tent"]["rays_through"] > 1000
    assert "| 2 | rays aimed at the level boundaries | mi-amr tent |" in (tmp_path / "iso.md").read_text()
