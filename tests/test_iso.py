"""Isosurfaces of the amr medium (docs/design.md section 15,
docs/manual/isosurfaces.md): hits on the level set, normals, no cracks at
level boundaries, look-ups only in leaves whose range holds the value, the
path-traced surface against Mitsuba's own sphere, values moved without
compiling, and bad parameters refused.

The data: an analytic radial field written on two and three AMR levels
whose level boundaries cut the sphere (`mi_amr.data.radial_example`)."""

from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_amr
from mi_amr import AMRCells
from mi_amr.data.radial_example import boundary_distance, radial_cells, ray_sphere
from mi_amr.params import ParameterError
from mi_amr.testing import block_z_scores, render_passes

CENTRE = np.array([0.5, 0.5, 0.5])
#: The sphere: level boundaries pass through it on faces and edges.
RADIUS = 0.3
#: Hit accuracy asked by the issue: within 0.5% of the radius.
RADIUS_SHARE = 0.005


@pytest.fixture(scope="module")
def llvm():
    mi.set_variant("llvm_ad_rgb")
    mi_amr.register()


def medium(cells, iso, **extra):
    """An amr medium over the unit cube (local = world) with ``iso``."""
    return mi.load_dict({"type": "amr", "data": cells, "iso": iso, "transfer_function": "ramp", **extra})


def camera_rays(n: int, direction, seed: int = 0):
    """``n`` x ``n`` parallel rays along ``direction`` through a square
    that covers the sphere, from outside the unit cube (numpy o, d)."""
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    a = np.cross(d, [0.3, 0.5, 0.8])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    u = (np.arange(n) + 0.5) / n * 0.8 - 0.4
    U, V = np.meshgrid(u, u)
    o = CENTRE - 1.5 * d + U.reshape(-1, 1) * a + V.reshape(-1, 1) * b
    return o, np.broadcast_to(d, o.shape).copy()


def iso_hits(med, o, d, t_max=10.0):
    """`AMRMedium.iso_hit` on numpy rays: (t, found, p, n, lookups) as numpy."""
    ray = mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    hit = med.iso_hit(ray, mi.Float(t_max), True, count=True)
    dr.eval(hit)
    return (hit.t.numpy().astype(np.float64), hit.found.numpy(), np.array(hit.p.numpy()).T.astype(np.float64),
            np.array(hit.n.numpy()).T.astype(np.float64), hit.counts.lookups.numpy())


def values_at(med, p):
    """The medium's reconstruction at world points (local = world here);
    NaN where it has no value (outside the data)."""
    value, found = med.structures.sampler().eval(mi.Vector3f(*np.asarray(p, np.float32).T))
    return np.where(found.numpy(), value.numpy().astype(np.float64), np.nan)


# ---- hits, normals and cracks ---------------------------------------------------
#: Root cells per axis of the radial data of the accuracy test (coarse cell 1/32).
ROOT = 32
#: How far the tent (basis) reconstruction's level set may stray from the
#: analytic sphere within a coarse cell of a level boundary, in coarse cells:
#: there the weights of the missing cells are dropped and the rest
#: renormalised (docs/design.md section 3), which reproduces a linear field
#: only to first order (measured: 0.13 coarse cells at 16, 32 and 64 root
#: cells; 0.5% of the radius holds everywhere else).
BOUNDARY_DENT_CELLS = 0.2
#: A ray that dips below the iso value by less than this share of the value
#: range (a grazing sliver, narrower than the search's half-cell step) may
#: pass: 3 of 6,900 rays of the 2-level data (docs/design.md section 15).
GRAZE_SHARE = 1e-3


def first_crossings(med, o, d, iso, samples=480, t_end=3.0):
    """Where the reconstruction along each ray first reaches ``iso``, from
    ``samples`` look-ups on ``[0, t_end]``: (t of the first sample past it,
    inf where none is; the sample spacing)."""
    t = np.linspace(0.0, t_end, samples)
    p = o[:, None, :] + t[None, :, None] * d[:, None, :]
    f = values_at(med, p.reshape(-1, 3)).reshape(len(o), samples)
    side = np.where(np.isnan(f), 0.0, np.sign(f - iso))
    valid = ~np.isnan(f)
    start = side[np.arange(len(o)), np.argmax(valid, axis=1)]            # the side the ray enters on
    crossed = valid & ((side * start[:, None] < 0) | (side == 0))
    first = np.where(crossed.any(axis=1), np.argmax(crossed, axis=1), -1)
    return np.where(first >= 0, t[np.maximum(first, 0)], np.inf), t[1] - t[0]


@pytest.mark.parametrize("levels", [2, pytest.param(3, marks=pytest.mark.slow)])
def test01_hits_lie_on_the_level_set_and_no_ray_passes_through(llvm, levels):
    """Tent reconstruction of |x - c| on `levels` levels whose boundaries cut
    the sphere |x - c| = 0.3:

    * no crack: every ray along which the reconstruction goes inside the
      surface (dense look-ups below the iso value by more than a grazing
      sliver, `GRAZE_SHARE`) hits the surface, no later than that
      look-up, at the level boundaries in particular; so does every ray
      whose analytic ray meets the sphere (but for grazing ones within 2%
      of its rim); no ray along which it stays outside hits;
    * every hit lies on the level set: ``|f(x) - iso|`` within 1e-4 of the
      value range, its normal the reconstruction's gradient pointing to
      lower values (central differences of half a finest cell, and of a
      quarter: those differ on the kinks of the trilinear pieces);
    * against the analytic sphere: within 0.5% of the radius farther than
      a coarse cell from a level boundary, within `BOUNDARY_DENT_CELLS`
      coarse cells of it near one (the reconstruction's own error there)."""
    cells = radial_cells(levels=levels, root=ROOT)
    med = medium(cells, RADIUS)
    span = float(np.ptp(cells.value))
    coarse = 1.0 / ROOT
    near_boundary = 0
    for direction in ([0.0, 0.0, 1.0], [1.0, 0.7, 0.4], [-0.6, 1.0, -0.3]):
        o, d = camera_rays(56, direction)
        t, found, p, n, _ = iso_hits(med, o, d)
        # rays that go inside by more than a grazing sliver: GRAZE_SHARE of the range below the value
        deep, _ = first_crossings(med, o, d, RADIUS - GRAZE_SHARE * span)
        reaches = np.isfinite(deep)
        assert reaches.sum() > 600
        assert found[reaches].all(), f"{int((reaches & ~found).sum())} rays pass through the surface"
        assert np.all(t[reaches] <= deep[reaches] + 1e-4)
        touches, _ = first_crossings(med, o, d, RADIUS)
        assert not found[~np.isfinite(touches)].any()
        impact = np.linalg.norm(np.cross(CENTRE - o, d), axis=1)
        meets = np.isfinite(ray_sphere(o, d, CENTRE, RADIUS)) & (impact < 0.98 * RADIUS)
        assert found[meets].all()
        # on the level set, and the normal
        assert np.abs(values_at(med, p[found]) - RADIUS).max() < 1e-4 * span
        for share, least in ((0.5, 0.999), (0.25, 0.8)):
            eps = share / (ROOT << (levels - 1))            # half and a quarter of a finest cell
            g = np.stack([values_at(med, p[found] + eps * e) - values_at(med, p[found] - eps * e)
                          for e in np.eye(3)], axis=1)
            agree = np.sum(-g / np.linalg.norm(g, axis=1, keepdims=True) * n[found], axis=1)
            # the same step agrees everywhere; another one where the field is smooth (not on the
            # kinks of the trilinear pieces and of the level boundaries)
            assert agree.min() > least and np.percentile(agree, 99) > 0.999
        # against the analytic sphere
        error = np.abs(np.linalg.norm(p[found] - CENTRE, axis=1) - RADIUS)
        close = boundary_distance(p[found], levels) < coarse
        near_boundary += int(close.sum())
        assert error[~close].max() < RADIUS_SHARE * RADIUS
        assert error[close].max() < BOUNDARY_DENT_CELLS * coarse
    assert near_boundary > 200


def test02_nearest_reconstruction_shows_its_steps(llvm):
    """With ``nearest`` the field is constant per cell: its level set is
    made of cell faces, found exactly (steps from face to face, one cell
    each), so hits land on faces of the finest lattice up to a cell from
    the sphere, well off the tent surface's accuracy (the steps show),
    and no ray along which the field goes inside passes, not even one that
    clips a cell's corner."""
    cells = radial_cells(levels=2, root=ROOT)
    med = medium(cells, RADIUS, reconstruction="nearest")
    o, d = camera_rays(56, [1.0, 0.7, 0.4])
    t, found, p, n, lookups = iso_hits(med, o, d)
    inside, _ = first_crossings(med, o, d, RADIUS)
    reaches = np.isfinite(inside)
    assert reaches.sum() > 600 and found[reaches].all()
    assert np.all(t[found & reaches] <= inside[found & reaches] + 1e-4)
    error = np.abs(np.linalg.norm(p[found] - CENTRE, axis=1) - RADIUS)
    assert error.max() > 4 * RADIUS_SHARE * RADIUS          # the steps show
    assert error.max() < np.sqrt(3.0) / ROOT               # but within a coarse cell
    lattice = p[found] * (ROOT << 1)                        # finest cells
    assert np.min(np.abs(lattice - np.round(lattice)), axis=1).max() < 1e-3
    assert np.median(lookups[found]) < 20                   # a look-up per cell crossed near the surface


def test03_leaves_without_the_value_take_no_look_up(llvm):
    """Look-ups are counted: a ray whose leaves' value ranges all exclude
    the iso value takes none (an iso value outside the data: no ray looks
    anything up; rays near the corners of the cube, far from the sphere:
    none either), while rays that hit take some."""
    cells = radial_cells(levels=2, root=16)
    outside = medium(cells, 5.0)
    o, d = camera_rays(48, [1.0, 0.7, 0.4])
    *_, lookups = iso_hits(outside, o, d)
    assert lookups.max() == 0
    med = medium(cells, RADIUS)
    t, found, *_, lookups = iso_hits(med, o, d)
    assert found.any() and lookups[found].min() > 0
    # rays along z through the corner columns x, y < 0.1: f >= 0.56 there
    u = np.linspace(0.01, 0.09, 8)
    X, Y = np.meshgrid(u, u)
    o = np.stack([X.ravel(), Y.ravel(), np.full(X.size, -0.5)], 1)
    d = np.broadcast_to([0.0, 0.0, 1.0], o.shape).copy()
    *_, lookups = iso_hits(med, o, d)
    assert lookups.max() == 0


# ---- path traced, against Mitsuba's own sphere -------------------------------------
def _scene(surface: str, spp: int = 16):
    """A diffuse sphere of radius 0.3 on a grey floor under one directional
    light and a dim constant sky: ``surface`` ``iso`` (the level set of a
    field falling off from the centre, on two levels, the gas off) or
    ``sphere`` (Mitsuba's analytic shape)."""
    T = mi.ScalarTransform4f
    diffuse = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}}
    scene = {"type": "scene", "integrator": {"type": "amrvolpath", "max_depth": 6},
             "sensor": {"type": "perspective", "fov": 38, "to_world": T().look_at([0.5, -1.3, 1.0], [0.5, 0.5, 0.42],
                                                                                  [0, 0, 1]),
                        "sampler": {"type": "independent", "sample_count": spp},
                        "film": {"type": "hdrfilm", "width": 48, "height": 48, "rfilter": {"type": "box"}}},
             "sun": {"type": "directional", "direction": [-0.4, 0.5, -0.75], "irradiance": 2.5},
             "sky": {"type": "constant", "radiance": 0.15},
             "floor": {"type": "rectangle", "to_world": T().translate([0.5, 0.5, 0.1]) @ T().scale(3.0),
                       "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}}}
    if surface == "iso":
        cells = radial_cells(levels=2, root=16)
        falling = AMRCells(cells.pos, cells.level, -cells.value)          # lower outside: the normal points out
        scene["volume"] = {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]) @ T().scale(0.5),
                           "bsdf": {"type": "null"},
                           "interior": {"type": "amr", "data": falling, "iso": -RADIUS, "iso_only": True,
                                        "transfer_function": "ramp", "density_scale": 5.0, "surface": diffuse}}
    else:
        scene["ball"] = {"type": "sphere", "center": list(CENTRE), "radius": RADIUS, "bsdf": diffuse}
    return mi.load_dict(scene)


def test04_path_traced_level_set_equals_mitsubas_sphere(llvm):
    """The sphere level set, path traced with one diffuse BSDF under a
    directional light (its shadow on the floor included), equals Mitsuba's
    analytic sphere with the same BSDF within Monte Carlo error: per-block
    z-scores of 8 independent passes each below 5 (48 blocks)."""
    ours = render_passes(_scene("iso"), passes=8, spp=16, frozen=False)
    theirs = render_passes(_scene("sphere"), passes=8, spp=16, seed0=100, frozen=False)
    assert np.isfinite(ours).all()
    z = block_z_scores(ours, theirs, block=6)
    assert np.abs(z).max() < 5.0, np.round(z, 1)
    # the picture holds the sphere and its shadow: not a flat frame
    assert ours.mean(axis=0).std() > 0.05


# ---- values moved without compiling; modes; bad parameters -------------------------
def _structure(ir: str) -> str:
    """Kernel IR with register and kernel names erased (the code itself)."""
    return re.sub(r"%[A-Za-z_]*\d+(?:_[A-Za-z0-9]+)*", "%r", re.sub(r"drjit_[0-9a-f]{32}", "drjit_K", ir))


def test05_moving_adding_removing_values_compiles_nothing(llvm):
    """After the first render with surfaces, new iso values (another
    number of them, the surfaces alone or not) launch only kernels whose
    code was launched before, and the picture changes."""
    sc = mi_amr.scene(radial_cells(levels=2, root=16), iso=[0.3], res=32, spp=2, mode="ray_march")
    dr.eval()
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        first = np.asarray(sc.render())
        before = {_structure(h["ir"].getvalue()) for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT}
        sc.iso = [0.2, 0.35]
        sc.iso_only = True
        second = np.asarray(sc.render())
        sc.iso = []
        third = np.asarray(sc.render())
        history = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    new = [h for h in history if _structure(h["ir"].getvalue()) not in before]
    assert history and not new
    assert np.abs(second - first).max() > 0.05 and np.abs(third - second).max() > 0.05
    assert sc.medium.iso_values == () and sc.medium.has_iso


@pytest.mark.parametrize("mode", ["emission_absorption", pytest.param("single", marks=pytest.mark.slow)])
def test06_every_mode_draws_the_surface_inside_the_gas(llvm, mode):
    """In the other lighting modes the surface inside translucent gas is
    drawn too: the picture differs from the gas alone where the sphere is,
    and is finite."""
    cells = radial_cells(levels=2, root=16)
    sc = mi_amr.scene(cells, res=24, spp=8, mode=mode, iso=[0.3], density_scale=1.0)
    with_iso = np.asarray(sc.render())
    sc.iso = []
    without = np.asarray(sc.render())
    assert np.isfinite(with_iso).all()
    centre = (slice(9, 15), slice(9, 15))
    assert np.abs(with_iso[centre] - without[centre]).mean() > 0.02


@pytest.mark.parametrize("props,message", [
    ({"iso": "0.3 banana"}, "iso values must be numbers"),
    ({"iso": "1 2 3 4 5"}, "at most 4 iso values"),
    ({"iso": "nan"}, "finite"),
    ({"iso_only": True}, "iso_only needs iso values"),
    ({"iso": 0.3, "a": {"type": "diffuse"}, "b": {"type": "diffuse"}}, "2 nested BSDFs for 1 iso values"),
])
def test07_bad_iso_parameters_are_refused_in_one_line(llvm, props, message):
    cells = radial_cells(levels=2, root=8)
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "amr", "data": cells, **props})
    with pytest.raises(ValueError, match="positive"):
        mi_amr.plan_scene(cells, log=True, iso=[-1.0])
    with pytest.raises(ParameterError, match="at most 4"):
        medium(cells, 0.3).set_iso([0.1, 0.2, 0.3, 0.4, 0.5])


def test08_command_line_and_scene_files_carry_the_surfaces(llvm, tmp_path):
    """``--iso`` and ``--iso-only`` reach the plan in the field's units, the
    written XML scene holds them in the medium's (log10 of them for a log10
    plan), and the scene loads with them."""
    from mi_amr.scene_writer import write_scene_xml
    from mi_amr.tools.cli import build_parser
    from mi_amr.tools.render import plan_options
    cells = radial_cells(levels=2, root=8)
    args = build_parser().parse_args(["render", "data.amrb", "--iso", "0.2", "0.3", "--iso-only", "--log",
                                      "-o", "x.exr"])
    plan = mi_amr.plan_scene(cells, **plan_options(args))
    assert plan.iso == (0.2, 0.3) and plan.iso_only and plan.transform == "log10"
    data = mi_amr.save_cells(cells, tmp_path / "radial.amrb")
    xml = write_scene_xml(plan, data, tmp_path / "radial.xml", res=8, spp=1)
    loaded = mi.load_file(str(xml))
    med = next(m for m in mi_amr.scene_media(loaded) if isinstance(m, mi_amr.AMRMedium))
    np.testing.assert_allclose(med.iso_values, np.log10([0.2, 0.3]), rtol=1e-6)
    assert med.iso_only
