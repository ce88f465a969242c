"""Windowed reductions of blocks onto macrocells.

A block of ``B^3`` per-cell items (values, value-mask bits) reaches the
macrocells its items' supports overlap; `block_windows` folds each block
onto exactly those macrocells, whole when every item reaches one and the
same macrocell, else axis by axis over the window of items that reach each
(docs/design.md section 9). The macrocell grid's value ranges and the value
masks both reduce through it.
"""

from __future__ import annotations

import functools

import numpy as np

#: Distinct window patterns up to which blocks are reduced over plain slices.
WINDOW_PATTERNS = 8


@functools.lru_cache(maxsize=None)
def _row_mix(n: int) -> np.ndarray:
    """``n`` odd 64-bit multipliers that hash a row of window bounds (`block_window_reduce`)."""
    return np.random.default_rng(0x5EED + n).integers(1, 2**62, n, dtype=np.int64) | 1

def block_windows(q0, B, span, res, arrays):
    """Reduce blocks of per-cell items onto the macrocells they reach.

    ``q0`` (k, 3): level coordinates of each block's first cell; ``span(q,
    axis)``: first and last macrocell (``i0``, ``i1``) reached by the items
    at level coordinates ``q`` (k, B) along ``axis``; ``arrays``: ``(a, op,
    fill)`` with ``a`` (k, B, B, B) indexed [block, z, y, x]. A block whose
    items all reach one and the same macrocell is reduced whole; the others
    axis by axis over the window of items that reach each macrocell.
    Returns ``(idx, reduced, ok)``, flat: macrocell indices, the reduced
    arrays on them, and which entries are real (the others are padding)."""
    arrays = list(arrays)
    spans = [span(q0[:, axis, None] + np.arange(B)[None], axis) for axis in range(3)]
    whole = np.ones(len(q0), dtype=bool)
    for i0, i1 in spans:                              # (both grow with q)
        whole &= i0[:, 0] == i1[:, -1]
    any_whole, all_whole = bool(whole.any()), bool(whole.all())
    # the blocks of each path (None: all of them, so nothing is copied)
    whole_sel = None if all_whole else np.nonzero(whole)[0]
    rest_sel = None if not any_whole else np.nonzero(~whole)[0]

    def part(a, sel):
        return a if sel is None else a[sel]
    idx, reduced, ok = [], [[] for _ in arrays], []
    if any_whole:
        i0s = [part(i0, whole_sel)[:, 0] for i0, _ in spans]
        idx.append(i0s[0] + res[0] * (i0s[1] + res[1] * i0s[2]))
        for out, (a, op, _) in zip(reduced, arrays):
            out.append(part(op.reduce(a, axis=(1, 2, 3)), whole_sel))     # (a is not copied)
        ok.append(np.ones(len(idx[0]), dtype=bool))
    if not all_whole:
        r_idx, r_red, r_ok = _block_windows_general(
            [(part(i0, rest_sel), part(i1, rest_sel)) for i0, i1 in spans], res,
            [(part(a, rest_sel), op, fill) for a, op, fill in arrays])
        idx.append(r_idx.reshape(-1))
        ok.append(r_ok.reshape(-1))
        for out, r in zip(reduced, r_red):
            out.append(r.reshape(-1))
    def join(parts):                                  # (one path: no copy)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)
    return join(idx), [join(r) for r in reduced], join(ok)


def _block_windows_general(spans, res, arrays):
    """`block_windows` of blocks whose items reach several macrocells:
    ``spans`` the per-axis ``(i0, i1)`` (k, B) of their items."""
    first = []
    for axis in range(3):                              # x, y, z: array axes 3, 2, 1
        i0, i1 = spans[axis]
        j0 = i0[:, :1]
        n = int((i1[:, -1:] - j0).max()) + 1
        j = j0 + np.arange(n)[None]                         # (k, J) macrocells touched
        qa = (i1[:, None, :] < j[:, :, None]).sum(axis=2)   # first cell reaching j
        qb = (i0[:, None, :] <= j[:, :, None]).sum(axis=2) - 1
        arrays = [(block_window_reduce(a, 3 - axis, qa, qb, op, fill), op, fill) for a, op, fill in arrays]
        first.append((j0[:, 0], n, i1[:, -1]))
    (jx0, nx, jx1), (jy0, ny, jy1), (jz0, nz, jz1) = first
    jz, jy, jx = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    gx, gy, gz = jx0[:, None, None, None] + jx, jy0[:, None, None, None] + jy, jz0[:, None, None, None] + jz
    ok = ((gx <= jx1[:, None, None, None]) & (gy <= jy1[:, None, None, None])
          & (gz <= jz1[:, None, None, None]))
    return gx + res[0] * (gy + res[1] * gz), [a for a, _, _ in arrays], ok


def block_window_reduce(a, axis, qa, qb, op, fill):
    """Per block (axis 0 of ``a``), ``out[k, ..., j, ...] = op`` over
    ``a[k, ..., qa[k, j]:qb[k, j] + 1, ...]`` along ``axis`` (``fill`` for
    empty windows); ``qa``, ``qb``: (k, J). Blocks that share their windows
    (aligned data has a few patterns) are reduced over plain slices."""
    if not qa.size:
        out_shape = list(a.shape)
        out_shape[axis] = qa.shape[1]
        return np.full(out_shape, fill, dtype=a.dtype)
    # the patterns: rows hashed to one int64 (sorting rows is slow), each
    # row then compared with its group's first, so a collision cannot pass
    pattern = np.concatenate([qa, qb], axis=1)
    hashed = (pattern * _row_mix(pattern.shape[1])).sum(axis=1)          # wraps: a hash
    _, first, inverse = np.unique(hashed, return_index=True, return_inverse=True)
    rows = pattern[first]
    if len(rows) <= WINDOW_PATTERNS and np.array_equal(rows[inverse.reshape(-1)], pattern):
        out_shape = list(a.shape)
        out_shape[axis] = qa.shape[1]
        out = np.empty(out_shape, dtype=a.dtype)
        inverse = inverse.reshape(-1)
        J = qa.shape[1]
        for p, row in enumerate(rows):
            sel = slice(None) if len(rows) == 1 else np.nonzero(inverse == p)[0]
            sub = a[sel]
            for j in range(J):
                lo_j, hi_j = max(int(row[j]), 0), min(int(row[J + j]) + 1, a.shape[axis])
                target = (sel,) + (slice(None),) * (axis - 1) + (slice(j, j + 1),)
                if hi_j <= lo_j:
                    out[target] = fill
                else:
                    window = sub[(slice(None),) * axis + (slice(lo_j, hi_j),)]
                    out[target] = op.reduce(window, axis=axis, keepdims=True)
        return out
    n = a.shape[axis]
    width = int((qb - qa + 1).max())
    out_shape = list(a.shape)
    out_shape[axis] = qa.shape[1]
    out = np.full(out_shape, fill, dtype=a.dtype)
    shape = [qa.shape[0], 1, 1, 1]
    shape[axis] = qa.shape[1]
    for k in range(max(width, 0)):
        idx = qa + k
        valid = ((idx <= qb) & (idx < n)).reshape(shape)
        taken = np.take_along_axis(a, np.clip(idx, 0, n - 1).reshape(shape), axis=axis)
        op(out, np.where(valid, taken, fill), out=out)
    return out
