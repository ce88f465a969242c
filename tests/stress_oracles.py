"""Oracles and small data for the stress tests: exact optical depths of
boxes, ratio-tracking transmittance through a medium, and data that
probe one edge case each."""

import drjit as dr
import mitsuba as mi
import numpy as np

import mi_amr


def constant_cells(n=4, value=1.0):
    """n^3 level-0 cells of one value: with the `constant` TF, sigma_t = scale."""
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return mi_amr.AMRCells(g, np.zeros(len(g), int), np.full(len(g), value))


def box_lengths(o, d, lo, hi, t_max=np.inf):
    """Length (in the units of ``o``) of each ray ``o + t d`` (t in [0, t_max],
    float64, (R, 3)) inside each half-open box ``[lo, hi)`` ((B, 3)) -> (R, B).
    An axis along which a ray does not move counts as inside when
    ``lo <= o < hi`` there."""
    o, d = o[:, None, :], d[:, None, :]
    lo, hi = lo[None], hi[None]
    flat = d == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t0 = np.where(flat, np.where((lo <= o) & (o < hi), -np.inf, np.inf), np.minimum(ta, tb)).max(axis=2)
    t1 = np.where(flat, np.inf, np.maximum(ta, tb)).min(axis=2)
    t0 = np.maximum(t0, 0.0)
    t1 = np.minimum(t1, t_max)
    return np.clip(t1 - t0, 0.0, None) * np.linalg.norm(d[:, 0, :], axis=1)[:, None]


def optical_depth_nearest(cells, sigma, o, d, chunk=64):
    """Exact optical depth along rays in the unit cube (= data bounds, with
    an identity to_world) through piecewise-constant cells of extinction
    ``sigma`` per cell, t in [0, inf)."""
    lo, hi = cells.bounds
    ext = (hi - lo).astype(np.float64)
    clo = (cells.pos - lo) / ext
    chi = (cells.pos + cells.width[:, None] - lo) / ext
    out = np.zeros(len(o))
    for s in range(0, len(o), chunk):
        out[s:s + chunk] = box_lengths(o[s:s + chunk], d[s:s + chunk], clo, chi) @ sigma
    return out


def ratio_tracking(med, o, d, replicas, seed=0, control=False):
    """Ratio-tracking transmittance of ``replicas`` copies of each ray:
    ``(T (R, replicas), counts)`` with the rays in the medium's world space
    (residual ratio tracking against the minorants with ``control``)."""
    n = len(o) * replicas
    O = np.repeat(o, replicas, axis=0).astype(np.float32)
    D = np.repeat(d, replicas, axis=0).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(O.T.copy()), mi.Vector3f(D.T.copy()))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    estimate = med.transmittance(ray, mi.Float(np.inf), sampler, mi.Bool(True), control)
    return estimate.T.numpy().reshape(len(o), replicas), estimate.counts


def grid_majorant_at(med, u):
    """Majorant of the macrocell holding each local point ``u`` ((M, 3))."""
    g = med.structures.grid
    return dr.gather(mi.Float, g.majorant, g.flat(g.cell_of(mi.Vector3f(np.ascontiguousarray(u.T))))).numpy()


def assert_transmittance(T, expected, z_max=5.0, floor=2e-3):
    """Each ray's mean estimate equals its expected transmittance within
    ``z_max`` standard errors: estimated from the replicas, floored, and at
    least that of the Russian roulette below ``RATIO_RR_THRESHOLD`` (a ray
    whose transmittance ``T`` falls below the threshold ``q`` ends with
    ``q`` or 0, variance about ``T (q - T)``: where fewer than 30 replicas
    are expected to survive, their spread alone underestimates it)."""
    from mi_amr.device.tracking import RATIO_RR_THRESHOLD as q
    assert np.isfinite(T).all() and (T >= 0).all() and (T <= 1 + 1e-5).all()
    mean = T.mean(axis=1)
    n = T.shape[1]
    few = n * expected / q < 30
    roulette = np.where(few, np.sqrt(expected * np.maximum(q - expected, 0.0) / n), 0.0)
    se = np.maximum(np.maximum(T.std(axis=1) / np.sqrt(n), floor), roulette)
    z = (mean - expected) / se
    worst = int(np.argmax(np.abs(z)))
    assert np.abs(z).max() < z_max, (worst, mean[worst], expected[worst], se[worst])


def face_rays(n_cells, rng, count):
    """Rays (local unit-cube coordinates) on the faces, edges and corners of
    a grid of ``n_cells`` cells per axis: axis-parallel along cell edges,
    inside face planes, from cell corners, grazing the bounding box and its
    top faces (outside: half-open), with direction components of 0 and 1e-30."""
    k = lambda *shape: rng.integers(0, n_cells + 1, shape) / n_cells   # noqa: E731
    o, d = [], []
    # along z on cell edges (x, y on grid planes), incl. the box faces and edges
    m = count // 5
    o.append(np.column_stack([k(m), k(m), np.full(m, -0.25)]))
    d.append(np.tile([0.0, 0.0, 1.0], (m, 1)))
    # inside an x face plane, oblique in y/z
    o.append(np.column_stack([k(m), rng.random(m), np.full(m, -0.25)]))
    d.append(np.tile([0.0, 0.37, 1.0], (m, 1)))
    # from interior cell corners, axis-parallel (both signs) or diagonal
    c = rng.integers(1, n_cells, (m, 3)) / n_cells
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                     [1, 1, 1], [-1, 1, -1], [1, -1, 0], [0, 1, -1]], dtype=np.float64)
    o.append(c)
    d.append(dirs[rng.integers(0, len(dirs), m)])
    # on face planes with 1e-30 components (the ray stays on the plane in float32)
    o.append(np.column_stack([k(m), k(m), np.full(m, -0.25)]))
    d.append(np.tile([1e-30, 1e-30, 1.0], (m, 1)))
    # grazing the bounding box: on its lower faces (inside) and upper faces (outside)
    rest = count - 4 * m
    face = rng.integers(0, 2, rest).astype(np.float64)
    o.append(np.column_stack([face, rng.random(rest), np.full(rest, -0.25)]))
    d.append(np.tile([0.0, 0.2, 1.0], (rest, 1)))
    d = np.concatenate(d)
    return np.concatenate(o), d / np.linalg.norm(d, axis=1, keepdims=True)


def spiky_cells():
    """Random 3-level data whose values are multiples of 1/4."""
    from conftest import random_amr
    return random_amr(seed=7, n=16, levels=3, quantize=4)


def single_entry_tf(value, n=65, domain=(0.0, 1.0)):
    """Opacity 1 in the one table entry at ``value``, 0 elsewhere."""
    rgba = np.zeros((n, 4))
    rgba[:, :3] = 0.8
    k = int(round((value - domain[0]) / (domain[1] - domain[0]) * (n - 1)))
    rgba[k, 3] = 1.0
    return mi_amr.TransferFunction(rgba, domain)


def level_jump_cells(jump, seed=0):
    """A level-``jump`` cell beside level-0 cells: the cell fills
    [0, 2^J)^3; beside it (x in [2^J, 2^(J+1))) one branch refines towards
    the shared face, level by level down to 0."""
    rng = np.random.default_rng(seed)
    pos, lev = [[0, 0, 0]], [jump]
    corner = np.array([1 << jump, 0, 0])
    for L in range(jump - 1, -1, -1):
        kids = corner + (np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)]) << L)
        keep = kids if L == 0 else kids[1:]          # child 0 (touching the cell) refines on
        pos += keep.tolist()
        lev += [L] * len(keep)
    if jump == 0:
        pos, lev = [[0, 0, 0], [1, 0, 0]], [0, 0]
    return mi_amr.AMRCells(pos, lev, rng.random(len(pos)))

