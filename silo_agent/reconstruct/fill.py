"""Filling of empty cells: the paper's B-spline interpolation (2.3.6) and a membrane fill.

`bspline_fill`: a pyramid of coverage-weighted averages is built by B-spline low-pass and
decimation ("pull"); coming back down, each level keeps its own estimate where it has data
and takes the cubic B-spline interpolation of the coarser level where it has none ("push").
Observed cells keep their measured value exactly; the fill is smooth and continuous with
them. Cost O(cells). Its coarse levels average over wide areas, so a floor hole beside a pile
borrows pile height.

`membrane_fill` (default): the harmonic surface of each hole's own boundary, solved exactly.
bench/accuracy.py compares both.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import linalg as sparse_linalg

_KERNEL = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0  # cubic B-spline low-pass
_SATURATION = 4.0  # a coarse cell a quarter covered is trusted fully


def _blur_decimate(values: np.ndarray) -> np.ndarray:
    out = ndimage.convolve1d(values, _KERNEL, axis=0, mode="constant")
    out = ndimage.convolve1d(out, _KERNEL, axis=1, mode="constant")
    return out[::2, ::2]


def bspline_fill(height: np.ndarray, known: np.ndarray) -> np.ndarray:
    """`height` with every cell not in `known` filled; known cells unchanged."""
    if not np.any(known):
        raise ValueError("no observed cell to fill from")
    weight = known.astype(np.float64)
    weighted = np.where(known, height, 0.0)
    pyramid = [(weighted, weight)]
    while max(weight.shape) > 2:
        weighted, weight = _blur_decimate(weighted), _blur_decimate(weight)
        pyramid.append((weighted, weight))

    weighted, weight = pyramid[-1]
    overall = float(np.sum(weighted) / np.sum(weight))
    with np.errstate(invalid="ignore", divide="ignore"):
        estimate = np.where(weight > 0, weighted / weight, overall)
    for level in range(len(pyramid) - 2, -1, -1):
        weighted, weight = pyramid[level]
        trust = weight if level == 0 else np.minimum(1.0, _SATURATION * weight)
        with np.errstate(invalid="ignore", divide="ignore"):
            own = np.where(weight > 0, weighted / weight, 0.0)
        need = trust < 1.0
        rows, cols = np.nonzero(need)
        coarse = ndimage.map_coordinates(
            estimate, [rows / 2.0, cols / 2.0], order=3, mode="nearest"
        )
        blended = own.copy()
        t = trust[need]
        blended[need] = t * own[need] + (1.0 - t) * coarse
        estimate = blended
    return np.where(known, height, estimate)


_DIRECT_MAX_UNKNOWNS = 30_000  # above this, CG warm-started from a coarse solve


def _laplace_system(
    height: np.ndarray, unknown: np.ndarray, domain: np.ndarray
) -> tuple[sparse.csr_matrix, np.ndarray]:
    """5-point Laplace equations for the unknown cells; known neighbours go to the right side.

    Only neighbours inside `domain` (the region) take part: the region edge is a free
    (zero-flux) boundary, so a hole touching it is shaped by the data around it alone.
    """
    rows, cols = height.shape
    index = np.full(height.shape, -1, dtype=np.int64)
    count = int(unknown.sum())
    index[unknown] = np.arange(count)
    r, c = np.nonzero(unknown)
    diagonal = np.zeros(count)
    rhs = np.zeros(count)
    row_ids, col_ids = [], []
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        nr, nc = r + dr, c + dc
        ok = (nr >= 0) & (nr < rows) & (nc >= 0) & (nc < cols)
        ok[ok] &= domain[nr[ok], nc[ok]]
        me = np.flatnonzero(ok)
        diagonal[me] += 1.0
        neighbour = index[nr[ok], nc[ok]]
        free = neighbour >= 0
        row_ids.append(me[free])
        col_ids.append(neighbour[free])
        rhs += np.bincount(me[~free], height[nr[ok][~free], nc[ok][~free]], minlength=count)
    off_rows, off_cols = np.concatenate(row_ids), np.concatenate(col_ids)
    matrix = sparse.csr_matrix(
        (
            np.concatenate([diagonal, -np.ones(len(off_rows))]),
            (
                np.concatenate([np.arange(count), off_rows]),
                np.concatenate([np.arange(count), off_cols]),
            ),
        ),
        shape=(count, count),
    )
    return matrix, rhs


def _coarsen(height: np.ndarray, known: np.ndarray, domain: np.ndarray):
    """2x2 block means of the known cells, for a cheap first solution of a large hole."""
    rows, cols = height.shape
    pr, pc = rows % 2, cols % 2
    pad = ((0, pr), (0, pc))
    h = np.pad(np.where(known, height, 0.0), pad)
    k = np.pad(known, pad).astype(float)
    d = np.pad(domain, pad)

    def blocks(a: np.ndarray) -> np.ndarray:
        return a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2).sum(axis=(1, 3))

    weight = blocks(k)
    with np.errstate(invalid="ignore", divide="ignore"):
        coarse = np.where(weight > 0, blocks(h) / weight, 0.0)
    return coarse, weight > 0, blocks(d.astype(float)) > 0


def membrane_fill(height: np.ndarray, known: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """Fill the unknown cells of `domain` with the discrete harmonic surface of their boundary.

    The fill is decided by the measured cells around each hole only (a floor hole next to a
    pile stays floor), is smooth, and never overshoots the boundary values.
    """
    if not np.any(known & domain):
        raise ValueError("no observed cell to fill from")
    unknown = domain & ~known
    count = int(unknown.sum())
    out = np.where(known, height, np.nan)
    if count == 0:
        return out
    matrix, rhs = _laplace_system(np.where(known, height, 0.0), unknown, domain)
    if count <= _DIRECT_MAX_UNKNOWNS:
        out[unknown] = sparse_linalg.spsolve(matrix.tocsc(), rhs)
        return out
    coarse_h, coarse_known, coarse_domain = _coarsen(height, known, domain)
    coarse = membrane_fill(coarse_h, coarse_known, coarse_domain)
    guess = np.repeat(np.repeat(np.nan_to_num(coarse), 2, axis=0), 2, axis=1)
    guess = guess[: height.shape[0], : height.shape[1]]
    solution, _ = sparse_linalg.cg(matrix, rhs, x0=guess[unknown], rtol=1e-5, maxiter=200)
    out[unknown] = solution
    return out
