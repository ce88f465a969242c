"""Isosurfaces against yt's ``ds.surface`` on the same AMR output, and the
isosurface frame's cost (docs/performance/iso.md): ``python -m mi_amr.bench
--iso --out DIR``.

The data: the analytic radial field ``f(x) = |x - c|`` of
`mi_amr.data.radial_example` on 2 and 3 levels (level 0 `ROOT`^3 cells),
written as an Enzo output that yt reads with the same leaf cells. Its level
set ``f = RADIUS`` is a sphere that the level boundaries cut (faces and
edges of the refined boxes), and every camera ray's exact hit is
`ray_sphere`. Two surfaces of that level set are shot with the same
camera rays (`ISO_CAMERA`, one ray per pixel centre at `CRACK_RES`^2):

* yt's: ``ds.surface(ds.all_data(), "density", RADIUS)`` (marching cubes
  grid by grid over the cells no finer grid covers, on vertex values
  averaged from the cells), its triangles welded into one indexed mesh and
  intersected by Mitsuba (``scene.ray_intersect``);
* ours: the ``amr`` medium's isosurface on the tent reconstruction
  (`AMRMedium.iso_hit`, the walk's search), and on ``nearest`` to show the
  steps of a piecewise-constant field.

For every ray that passes well inside the sphere (within ``(1 - GRAZING)
R`` of its centre, so that it must cross any closed surface near the
sphere) a **crack** is a ray that passes through the surface: no hit, or a
hit on the back half of the sphere's chord (the back of the surface, seen
through a hole), located by the distance of its exact hit point to
the nearest level boundary (in level-0 cells; the crack share within one
of a boundary and elsewhere). The **distance error** of a front hit of a ray through is
``|t - t_exact| / RADIUS`` (the **radial error** ``||x - c| - R| / R``
of its point: how far the surface lies from the sphere, whatever the
angle); a **stray** hit is a hit of a ray that misses
the sphere, a **grazing miss** a miss of a ray that meets the sphere
within ``GRAZING R`` of its rim (a surface shrunk by averaging). yt's mesh also counts its **open edges**
(edges of one triangle only: a closed surface has none).

Then the pictures of both surfaces (yt's mesh under Mitsuba's ``path``,
ours under ``amrvolpath``, the same camera, lights and diffuse BSDF) side
by side, whole and zoomed on yt's cracks, with the zoomed crack maps
(``--iso-picture``), and the frame rate of an isosurface picture at
``--iso-res`` (512^2) on the block-structured data of ``--scale`` (10^7
and 10^8 cells), timed as ``--march`` times its frames.
"""

from __future__ import annotations

import gc
import math
import os
import statistics
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..data.io import load_volume
from ..data.radial_example import (boundary_distance, level_boundaries, radial_cells, ray_sphere,
                                   write_enzo_radial)
from ..images import write_png
from ..transfer.function import TransferFunction
from .harness import bench_scene, check_alone, write_report

#: The sphere: centre and radius of the level set ``f = RADIUS`` (unit cube).
CENTRE = (0.5, 0.5, 0.5)
RADIUS = 0.27
#: Level-0 cells per side of the radial data.
ROOT = 16
#: The view ``(origin, target, fov)``: from the side of the coarse cells,
#: facing the level boundaries x = 0.375 and y = 0.375 (the side from
#: which the gaps between yt's per-level surfaces show), 2.4 from the
#: centre (about the benchmark camera's distance), the field of view
#: spanning 0.8 of the unit cube there.
ISO_DIRECTION = np.array([-1.0, -0.8, 0.9]) / np.linalg.norm([-1.0, -0.8, 0.9])
ISO_CAMERA = (tuple(np.asarray(CENTRE) + 2.4 * ISO_DIRECTION), CENTRE, float(np.degrees(2.0 * np.arctan(0.4 / 2.4))))
#: Rays that pass within ``(1 - GRAZING) R`` of the centre cross any
#: closed surface within ``GRAZING R`` of the sphere: the cracks are counted
#: among them (a surface shrunk by averaging misses some grazing rays,
#: counted apart).
GRAZING = 0.05
#: How far inside the sphere the rays at the level boundaries aim (share of R).
BOUNDARY_DEPTH = 0.05
#: Rays aimed at the level boundaries per level count.
AIMED_RAYS = 100_000
#: Camera rays per side of the crack figures.
CRACK_RES = 512
#: The surfaces' BSDF in the pictures (a light grey diffuse, both sides).
GREY = {"type": "twosided", "surface": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}}
#: The pictures' exposure (linear scale before sRGB), and the zoomed
#: panels' width across (unit cube: about two level-0 cells).
EXPOSURE = 0.6
ZOOM_WIDTH = 0.12
#: The pictures' crack colour.
CRACK_RGB = np.array([1.0, 0.1, 0.05])


# ---- The camera rays -----------------------------------------------------


def camera_sensor(res: int, camera=ISO_CAMERA) -> dict:
    """The perspective sensor of the benchmark view ``camera`` at ``res``^2
    (`bench_scene`'s)."""
    return bench_scene(None, res, {"type": "path"}, camera)["sensor"]


def camera_rays(res: int, camera=ISO_CAMERA) -> tuple[np.ndarray, np.ndarray]:
    """``(o, d)``: the world rays (float64, (res^2, 3), unit ``d``) of the
    sensor's pixel centres, row by row as the picture's pixels."""
    sensor = mi.load_dict(camera_sensor(res, camera))
    idx = dr.arange(mi.UInt32, res * res)
    film = mi.Point2f((mi.Float(idx % res) + 0.5) / res, (mi.Float(idx // res) + 0.5) / res)
    ray, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
    o = np.stack([np.array(ray.o[k], dtype=np.float64) for k in range(3)], axis=1)
    d = np.stack([np.array(ray.d[k], dtype=np.float64) for k in range(3)], axis=1)
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _ray(o, d) -> mi.Ray3f:
    return mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k]) for k in range(3)]),
                    mi.Vector3f(*[mi.Float(d[:, k]) for k in range(3)]))


def boundary_rays(levels: int, n: int, radius: float = RADIUS, centre=CENTRE, seed: int = 0,
                  depth: float = None, box: int | None = None):
    """``(o, d)``: ``n`` rays aimed at random points of the level
    boundaries (faces of the refined boxes inside the domain) just inside
    the sphere: on the circle where a face cuts it, moved towards the
    circle's centre by up to ``depth R`` (uniform), where the surfaces of
    the two levels meet, each from a random direction of the outer
    hemisphere of the sphere's normal there (cosine-distributed), starting
    2 units out. ``depth``: default `BOUNDARY_DEPTH`; ``box``: only the
    faces of this refined box (0: level 1's), default all."""
    depth = BOUNDARY_DEPTH if depth is None else depth
    rng = np.random.default_rng(seed)
    centre = np.asarray(centre, dtype=np.float64)
    points = []
    for k, (lo, hi) in enumerate(level_boundaries(levels)):
        if box is not None and k != box:
            continue
        for a in range(3):
            for plane in (lo[a], hi[a]):
                rho2 = radius ** 2 - (plane - centre[a]) ** 2
                if plane <= 0.0 or plane >= 1.0 or rho2 <= 0.0:
                    continue
                phi = rng.uniform(0.0, 2.0 * np.pi, 4 * n)
                b, c = [k for k in range(3) if k != a]
                x = np.empty((len(phi), 3))
                x[:, a] = plane
                rho = np.sqrt(rho2) - depth * radius * rng.random(len(phi))
                x[:, b] = centre[b] + rho * np.cos(phi)
                x[:, c] = centre[c] + rho * np.sin(phi)
                on_face = np.all((x[:, [b, c]] >= lo[[b, c]]) & (x[:, [b, c]] <= hi[[b, c]]), axis=1)
                points.append(x[on_face])
    points = np.concatenate(points)
    x = points[rng.choice(len(points), n, replace=len(points) < n)]
    normal = (x - centre) / np.linalg.norm(x - centre, axis=1, keepdims=True)
    # cosine-distributed directions about the normal (Malley): a disk sample lifted onto the hemisphere
    r, phi = np.sqrt(rng.random(n)), rng.uniform(0.0, 2.0 * np.pi, n)
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normal, u)
    w = (r * np.cos(phi))[:, None] * u + (r * np.sin(phi))[:, None] * v + np.sqrt(1.0 - r * r)[:, None] * normal
    return x + 2.0 * w, -w


# ---- yt's surface --------------------------------------------------------


def yt_surface(ds, value: float, field=("gas", "density"), weld: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """yt's isosurface ``field = value`` of the whole data set
    (``ds.surface``) as an indexed mesh: ``(vertices (n, 3) float64, code
    units; faces (m, 3) int)``. Its triangles come as separate corners;
    corners closer than ``weld`` (code units: yt computes a vertex on an
    edge shared by two cells once per cell, equal up to rounding) become
    one vertex, so that only real gaps stay open."""
    surf = ds.surface(ds.all_data(), field, value)
    corners = np.asarray(surf.triangles.to("code_length").d, dtype=np.float64).reshape(-1, 3)
    pairs = cKDTree(corners).query_pairs(weld, output_type="ndarray")
    n = len(corners)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    first = np.full(label.max() + 1, n)
    np.minimum.at(first, label, np.arange(n))
    vertices = corners[first]
    faces = label.reshape(-1, 3)
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return vertices, faces[keep]


def open_edges(faces: np.ndarray) -> int:
    """Edges used by one triangle only (a closed surface has none)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())


def mesh_of(vertices: np.ndarray, faces: np.ndarray, bsdf=None) -> mi.Mesh:
    """A Mitsuba mesh of ``vertices`` and ``faces`` (world units) with ``bsdf``."""
    mesh = mi.Mesh("yt_surface", len(vertices), len(faces), props=_bsdf_props(bsdf))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    return mesh


def _bsdf_props(bsdf):
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf)
    return props


def mesh_hits(vertices, faces, o, d) -> np.ndarray:
    """World ``t`` of each ray's first hit of the mesh (inf where none)."""
    scene = mi.load_dict({"type": "scene", "surface": mesh_of(vertices, faces)})
    si = scene.ray_intersect(_ray(o, d))
    t = np.array(si.t, dtype=np.float64)
    return np.where(np.array(si.is_valid()), t, np.inf)


# ---- Our surface ---------------------------------------------------------


def iso_medium(cells, value: float, reconstruction: str = "tent", only: bool = True, bsdf=None) -> dict:
    """The ``amr`` medium dictionary of ``cells`` with the iso value
    ``value`` (``iso_only``: no density around), ``bsdf`` its surface's."""
    medium = {"type": "amr", "data": cells, "reconstruction": reconstruction, "iso": float(value),
              "iso_only": only, "density_scale": 1.0}
    if bsdf is not None:
        medium["iso_bsdf"] = bsdf
    return medium


def medium_hits(cells, value: float, o, d, reconstruction: str = "tent") -> np.ndarray:
    """World ``t`` of each ray's first isosurface hit of the ``amr`` medium
    on ``cells`` (`AMRMedium.iso_hit`; the unit cube in world space; inf
    where none)."""
    medium = mi.load_dict(iso_medium(cells, value, reconstruction))
    hit = medium.iso_hit(_ray(o, d), mi.Float(np.inf), mi.Bool(True))
    t = np.array(hit.t, dtype=np.float64)
    found = np.array(hit.found)
    del medium, hit
    gc.collect()
    return np.where(found, t, np.inf)


# ---- The figures ---------------------------------------------------------


def hit_figures(t, o, d, levels: int, radius: float = RADIUS, centre=CENTRE, root: int = ROOT) -> dict:
    """Cracks, stray hits and the distance error of the hits ``t`` of the
    rays ``(o, d)`` against the exact sphere (see the module docstring);
    boundary distances in level-0 cells (``root`` per side), "near" a
    boundary: within one."""
    t_exact = ray_sphere(o, d, centre, radius)
    on = np.isfinite(t_exact)
    hit = np.isfinite(t)
    closest = np.linalg.norm(np.cross(np.asarray(centre) - o, d), axis=1) / np.linalg.norm(d, axis=1)
    through = on & (closest <= (1.0 - GRAZING) * radius)
    with np.errstate(invalid="ignore"):
        err = (t - t_exact) / radius
    front = on & hit & (err < 0.5 * _chord(closest, radius) / radius)
    crack = through & ~front
    x = o[through] + t_exact[through, None] * d[through]
    dist = boundary_distance(x, levels) * root                      # level-0 cells
    near = dist <= 1.0
    dist_crack = dist[crack[through]]
    e = np.abs(err[front & through])                                # grazing rays amplify any offset
    ok = front & through
    radial = np.abs(np.linalg.norm(o[ok] + t[ok, None] * d[ok] - np.asarray(centre), axis=1) - radius) / radius
    return {"rays": int(len(t)), "rays_on_sphere": int(on.sum()), "rays_through": int(through.sum()),
            "cracks": int(crack.sum()), "cracks_hitting_behind": int((crack & hit).sum()),
            "crack_share": float(crack.sum() / max(through.sum(), 1)),
            "cracks_near_a_boundary": int((dist_crack <= 1.0).sum()),
            "rays_near_a_boundary": int(near.sum()),
            "crack_share_near_boundaries": float((dist_crack <= 1.0).sum() / max(near.sum(), 1)),
            "crack_share_elsewhere": float((dist_crack > 1.0).sum() / max((~near).sum(), 1)),
            "crack_boundary_distance_max": float(dist_crack.max()) if len(dist_crack) else None,
            "grazing_misses": int((on & ~through & ~hit).sum()),
            "stray_hits": int((~on & hit).sum()),
            "error_median": float(np.median(e)) if len(e) else None,
            "error_p99": float(np.quantile(e, 0.99)) if len(e) else None,
            "error_max": float(e.max()) if len(e) else None,
            "hits_within_0.5%": float((e <= 0.005).sum() / max(through.sum(), 1)),
            "radial_error_median": float(np.median(radial)) if len(radial) else None,
            "radial_error_max": float(radial.max()) if len(radial) else None}


def _chord(closest, radius):
    """Length of the sphere's chord along rays passing ``closest`` from its centre."""
    return 2.0 * np.sqrt(np.maximum(radius ** 2 - closest ** 2, 0.0))


def crack_mask(t, o, d, radius: float = RADIUS, centre=CENTRE) -> np.ndarray:
    """The cracks of `hit_figures`: rays that pass well inside the sphere
    and do not hit the surface near the exact hit."""
    t_exact = ray_sphere(o, d, centre, radius)
    closest = np.linalg.norm(np.cross(np.asarray(centre) - o, d), axis=1) / np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore"):
        front = np.isfinite(t) & (t - t_exact < 0.5 * _chord(closest, radius))
    return np.isfinite(t_exact) & (closest <= (1.0 - GRAZING) * radius) & ~front


#: The two sets of rays: the camera's pixel centres, and rays aimed at the
#: level boundaries just inside the sphere (`boundary_rays`).
RAY_SETS = {"camera": "camera rays", "boundary": "rays aimed at the level boundaries"}


def surfaces_compared(out: Path, levels_list=(2, 3), res: int = CRACK_RES, radius: float = RADIUS,
                      ours: bool = True, aimed: int = AIMED_RAYS) -> dict:
    """Per level count: yt's surface and ours (tent, nearest) on the same
    output, each shot with the same rays of each set (`RAY_SETS`: ``res``^2
    camera rays, ``aimed`` rays at the level boundaries): `hit_figures`
    per set and surface, yt's mesh size and open edges, and seconds.
    ``ours``: also the ``amr`` medium's."""
    import yt
    yt.set_log_level(40)
    records = {}
    for levels in levels_list:
        rays = {"camera": camera_rays(res), "boundary": boundary_rays(levels, aimed, radius)}
        path = write_enzo_radial(out / f"radial{levels}", levels, ROOT)
        ds = yt.load(str(path))
        t0 = time.perf_counter()
        vertices, faces = yt_surface(ds, radius)
        rec = {"levels": levels, "leaf_cells": int(len(radial_cells(levels, ROOT))), "data": str(path),
               "yt_mesh": {"triangles": int(len(faces)), "vertices": int(len(vertices)),
                           "open_edges": open_edges(faces), "surface_s": time.perf_counter() - t0}}
        for name, (o, d) in rays.items():
            rec[name] = {"yt": hit_figures(mesh_hits(vertices, faces, o, d), o, d, levels, radius)}
            print(_line(f"{levels} levels, {RAY_SETS[name]}, yt", rec[name]["yt"]), flush=True)
        if ours:
            cells = radial_cells(levels, ROOT)
            for method in ("tent", "nearest"):
                for name, (o, d) in rays.items():
                    check_alone(f"iso {method}")
                    t0 = time.perf_counter()
                    t = medium_hits(cells, radius, o, d, method)
                    rec[name][method] = dict(hit_figures(t, o, d, levels, radius), seconds=time.perf_counter() - t0)
                    print(_line(f"{levels} levels, {RAY_SETS[name]}, ours ({method})", rec[name][method]),
                          flush=True)
        records[levels] = rec
        del ds
        gc.collect()
    return records


def _line(name, f) -> str:
    return (f"  {name}: {f['cracks']} cracks of {f['rays_through']} rays through the sphere "
            f"({f['cracks_near_a_boundary']} within a level-0 cell of a level boundary), "
            f"{f['grazing_misses']} grazing misses, {f['stray_hits']} stray hits, error median "
            f"{_pct(f['error_median'])} max {_pct(f['error_max'])} of R")


# ---- The pictures --------------------------------------------------------


def lit_scene(res: int, integrator: dict, camera=ISO_CAMERA, medium=None) -> dict:
    """`bench_scene` with ``camera`` at ``res``^2 (without the volume when
    ``medium`` is None), its sun turned to come from above the camera's
    left shoulder (the benchmark's sun lights the far side of this view)."""
    scene = bench_scene(medium, res, integrator, camera)
    if medium is None:
        del scene["volume"]
    view = np.asarray(camera[0], dtype=np.float64) - np.asarray(camera[1], dtype=np.float64)
    view /= np.linalg.norm(view)
    left = np.cross([0.0, 1.0, 0.0], view)
    sun = view + 0.8 * np.array([0.0, 1.0, 0.0]) + 0.4 * left / max(np.linalg.norm(left), 1e-9)
    scene["sun"]["direction"] = (-sun / np.linalg.norm(sun)).tolist()
    return scene


def render_pair(vertices, faces, cells, res: int, spp: int, camera, radius: float = RADIUS) -> dict:
    """yt's mesh under ``path`` and our isosurface of ``cells`` under
    ``amrvolpath`` (``multi``, surfaces only), the same camera, lights and
    BSDF (`GREY`), and both crack maps (`crack_mask` of the pixel centres:
    the exact sphere grey, cracks red) at ``res``^2: ``{"yt", "ours",
    "yt_cracks", "ours_cracks"}`` (linear RGB arrays)."""
    scene = lit_scene(res, {"type": "path", "max_depth": 8}, camera)
    scene["surface"] = mesh_of(vertices, faces, GREY)
    theirs = np.array(mi.render(mi.load_dict(scene), spp=spp, seed=1))[..., :3]
    check_alone("iso picture")
    ours_scene = mi.load_dict(lit_scene(res, {"type": "amrvolpath", "mode": "multi", "max_depth": 8}, camera,
                                        iso_medium(cells, radius, bsdf=GREY)))
    ours = np.array(mi.render(ours_scene, spp=spp, seed=1))[..., :3]
    del ours_scene
    gc.collect()
    o, d = camera_rays(res, camera)
    sphere = np.isfinite(ray_sphere(o, d, CENTRE, radius))
    out = {"yt": theirs, "ours": ours}
    for name, t in (("yt", mesh_hits(vertices, faces, o, d)), ("ours", medium_hits(cells, radius, o, d))):
        m = np.where(sphere[:, None], 0.35, 0.01) * np.ones((1, 3))
        m[crack_mask(t, o, d, radius)] = CRACK_RGB
        out[f"{name}_cracks"] = m.reshape(res, res, 3)
    return out


def picture_row(levels: int, out: Path, res: int = 256, spp: int = 64, radius: float = RADIUS,
                zoom_width: float = ZOOM_WIDTH) -> dict:
    """One row of the figure for ``levels`` levels: `render_pair` in the
    view `ISO_CAMERA`, and zoomed (``zoom_width`` of the unit cube across)
    on the finest level's boundary: at the median aim point of the rays
    aimed there (`boundary_rays`) that pass through yt's surface, from
    their median direction."""
    import yt
    yt.set_log_level(40)
    ds = yt.load(str(write_enzo_radial(out / f"radial{levels}", levels, ROOT)))
    vertices, faces = yt_surface(ds, radius)
    cells = radial_cells(levels, ROOT)
    o, d = boundary_rays(levels, 20_000, radius, box=levels - 2, seed=3)
    cracks = crack_mask(mesh_hits(vertices, faces, o, d), o, d, radius)
    seen = cracks if cracks.any() else np.ones(len(o), dtype=bool)
    aim = o[seen] + 2.0 * d[seen]
    target = aim[np.argmin(np.linalg.norm(aim - np.median(aim, axis=0), axis=1))]     # a crack's own point
    direction = -np.median(d[seen], axis=0)
    direction /= np.linalg.norm(direction)
    distance = float(np.linalg.norm(np.asarray(ISO_CAMERA[0]) - np.asarray(CENTRE)))
    zoom = (tuple(target + distance * direction), tuple(target),
            float(np.degrees(2.0 * np.arctan(0.5 * zoom_width / distance))))
    return {"levels": levels, "full": render_pair(vertices, faces, cells, res, spp, ISO_CAMERA, radius),
            "zoom": render_pair(vertices, faces, cells, res, spp, zoom, radius), "zoom_camera": zoom}


def write_figure(path: Path, rows: list) -> None:
    """One PNG: per level count (rows of `picture_row`), yt's picture and
    ours, the same zoomed, and the zoomed crack maps of yt and ours,
    separated by white lines of 4 pixels."""
    lines = []
    for r in rows:
        panels = [EXPOSURE * r["full"]["yt"], EXPOSURE * r["full"]["ours"], EXPOSURE * r["zoom"]["yt"],
                  EXPOSURE * r["zoom"]["ours"], r["zoom"]["yt_cracks"], r["zoom"]["ours_cracks"]]
        gap = np.ones((panels[0].shape[0], 4, 3))
        lines.append(np.concatenate([x for panel in panels for x in (panel, gap)][:-1], axis=1))
    gap = np.ones((4, lines[0].shape[1], 3))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, np.concatenate([x for line in lines for x in (line, gap)][:-1], axis=0))


# ---- The frame rate --------------------------------------------------------


def iso_frame_rows(cell_counts, res: int, repeats: int, data_dir: Path, frozen: bool = True) -> list:
    """Frames/s of an isosurface picture at ``res``^2 on the block data of
    ``--scale`` (`mi_amr.bench.scale.data_file`), the iso value the data's
    median value: surfaces only under ``ray_march`` (shaded locally) and
    under ``multi`` at 1 spp (path traced), and the surface inside the
    volume under ``multi``; one scene alive at a time, the median of
    ``repeats`` passes (`mi_amr.bench.modes.time_passes`)."""
    from .modes import LARGE_SCALE, time_passes
    from .scale import data_file
    rows = []
    for n in cell_counts:
        path = data_file("blocks", int(n), Path(data_dir))
        volume = load_volume(path)
        value = float(np.median(np.concatenate([v for _, _, v in volume.cell_chunks()])))
        tf = TransferFunction.preset("spiky", volume.value_range)
        scenes = {}
        for name, only, integrator in (
                ("ray_march, surface only", True, {"type": "amrvolpath", "mode": "ray_march"}),
                ("multi 1 spp, surface only", True, {"type": "amrvolpath", "mode": "multi", "max_depth": 8}),
                ("multi 1 spp, surface in the volume", False,
                 {"type": "amrvolpath", "mode": "multi", "max_depth": 64})):
            medium = {"type": "amr", "data": volume, "transfer_function": tf, "density_scale": LARGE_SCALE,
                      "iso": value, "iso_only": only}
            scenes[name] = bench_scene(medium, res, integrator)
        load = os.getloadavg()
        timing = time_passes(scenes, 1, repeats, frozen=frozen)
        for config, t in timing.items():
            frame_s = statistics.median(t["wall"])
            rows.append({"cells": len(volume), "iso": value, "config": config, "res": res, "frame_s": frame_s,
                         "fps": 1.0 / frame_s, "wall": t["wall"], "cpu": t["cpu"],
                         "load_average": [load, os.getloadavg()]})
            print(f"  {len(volume):,} cells, {config}: {1e3 * frame_s:.0f} ms a frame "
                  f"({1.0 / frame_s:.2f} frames/s), load {load[0]:.1f}", flush=True)
        del volume
        gc.collect()
    return rows


# ---- The report ------------------------------------------------------------


def report(result: dict, command: str) -> str:
    lines = ["# Isosurfaces against yt's ds.surface, and the isosurface frame", "", f"`{command}`", "",
             f"The radial field |x - c| on {ROOT}^3 root cells with 2 and 3 levels (mi_amr.data.radial_example, "
             f"written as an Enzo output yt reads with the same leaf cells), its level set {RADIUS} (a sphere "
             f"that the level boundaries cut). Rays: {result['res']}^2 camera rays (one per pixel centre, "
             f"the view of the pictures), and {result['aimed']:,} rays aimed at the level boundaries just inside "
             f"the sphere (within {BOUNDARY_DEPTH:g} R of the circles where they cut it) from random directions "
             f"of the outer hemisphere. Rays through: those passing within {1 - GRAZING:g} R of the centre. Crack: "
             "a ray through that passes through the surface (no hit, or a hit on the back half of the sphere's "
             "chord); near: its exact hit within one level-0 cell of a level boundary. Error: |t - t_exact| / R "
             "of the front hits of the rays through (near the rim any offset of the surface is amplified); "
             "radial error: ||x - c| - R| / R of their points; grazing miss: a miss within "
             f"{GRAZING:g} R of the sphere's rim.", "",
             "| levels | rays | surface | rays through | cracks | near a boundary | crack share near / elsewhere | "
             "farthest crack (level-0 cells) | grazing misses | stray hits | error median | error p99 | "
             "error max | rays through hit within 0.5% | radial error median | radial error max |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for levels, rec in result["surfaces"].items():
        for rays, ray_label in RAY_SETS.items():
            for name, label in (("yt", "yt ds.surface"), ("tent", "mi-amr tent"), ("nearest", "mi-amr nearest")):
                if name not in rec[rays]:
                    continue
                f = rec[rays][name]
                far = "-" if f["crack_boundary_distance_max"] is None else f"{f['crack_boundary_distance_max']:.2f}"
                lines.append(f"| {levels} | {ray_label} | {label} | {f['rays_through']:,} | {f['cracks']:,} | "
                             f"{f['cracks_near_a_boundary']:,} | {100 * f['crack_share_near_boundaries']:.2f}% / "
                             f"{100 * f['crack_share_elsewhere']:.3f}% | {far} | {f['grazing_misses']:,} | "
                             f"{f['stray_hits']:,} | {_pct(f['error_median'])} | {_pct(f['error_p99'])} | "
                             f"{_pct(f['error_max'])} | {100 * f['hits_within_0.5%']:.2f}% | "
                             f"{_pct(f['radial_error_median'])} | {_pct(f['radial_error_max'])} |")
    lines += ["", "yt's meshes: " + "; ".join(
        f"{levels} levels {rec['yt_mesh']['triangles']:,} triangles, {rec['yt_mesh']['open_edges']:,} open "
        f"edges, ds.surface {rec['yt_mesh']['surface_s']:.2f} s" for levels, rec in result["surfaces"].items()) + "."]
    if result.get("frames"):
        lines += ["", f"## The isosurface frame at {result['frames'][0]['res']}^2", "",
                  f"The iso value: the data's median value; {result['cpus']} CPUs; the median of the passes, one scene "
                  "alive at a time; CPU seconds: the process's own, less sensitive to other load than wall time.", "",
                  "| cells | config | frame ms (range) | frames/s | CPU s a frame | load average (1 min) |",
                  "|---|---|---|---|---|---|"]
        for r in result["frames"]:
            lines.append(f"| {r['cells']:,} | {r['config']} | {1e3 * r['frame_s']:.0f} "
                         f"({1e3 * min(r['wall']):.0f}-{1e3 * max(r['wall']):.0f}) | {r['fps']:.2f} | "
                         f"{statistics.median(r['cpu']):.2f} | "
                         f"{r['load_average'][0][0]:.1f} -> {r['load_average'][1][0]:.1f} |")
    return "\n".join(lines) + "\n"


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.3f}%"


def main_args(args) -> int:
    mi.set_variant(args.variant)
    out = Path(args.out or "out/bench-iso")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ours = not args.iso_yt_only
    result = {"load_average_start": os.getloadavg(), "variant": args.variant,
              "res": args.iso_crack_res, "aimed": AIMED_RAYS, "radius": RADIUS, "root": ROOT, "camera": ISO_CAMERA,
              "cpus": os.cpu_count(),
              "surfaces": surfaces_compared(out, tuple(args.iso_levels), args.iso_crack_res, RADIUS, ours)}
    picture = out / "iso-vs-yt.png" if args.iso_picture is None else args.iso_picture
    if ours and str(picture) != "none":
        rows = [picture_row(levels, out, args.iso_picture_res, args.iso_picture_spp) for levels in args.iso_levels]
        write_figure(Path(picture), rows)
        result["picture"] = {"path": str(picture), "res": args.iso_picture_res, "spp": args.iso_picture_spp,
                             "zoom_cameras": {r["levels"]: r["zoom_camera"] for r in rows}}
    if ours and args.iso_cells:
        result["frames"] = iso_frame_rows(args.iso_cells, args.iso_res, args.repeats, Path(args.data_dir),
                                          args.frozen)
    result["seconds"] = time.perf_counter() - t0
    result["load_average_end"] = os.getloadavg()
    command = " ".join(["python -m mi_amr.bench"] + args.argv)
    write_report(out, "iso", result, report(result, command))
    finite = [f["rays_on_sphere"] > 0 for rec in result["surfaces"].values() for rays in RAY_SETS
              for f in rec[rays].values()]
    return 0 if all(finite) and all(math.isfinite(r["frame_s"]) for r in result.get("frames", [])) else 1
