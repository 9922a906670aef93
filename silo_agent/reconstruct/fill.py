"""Filling of empty cells: the paper's B-spline interpolation (2.3.6) and a membrane fill.

`bspline_fill`: a pyramid of coverage-weighted averages is built by B-spline low-pass and
decimation ("pull"); coming back down, each level keeps its own estimate where it has data
and takes the cubic B-spline interpolation of the coarser level where it has none ("push").
Observed cells keep their measured value exactly; the fill is smooth and continuous with
them. Cost O(cells). Its coarse levels average over wide areas, so a floor hole beside a pile
borrows pile height.

`membrane_fill` (default): the harmonic surface of each hole's own boundary. Its 5-point
Laplace equations are solved in numpy, without assembling a matrix: conjugate gradients
started from the solution on a grid twice as coarse (itself solved the same way, down to a
small dense system), so every scan's fill runs without importing scipy. bench/accuracy.py
compares both fills.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

_KERNEL = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0  # cubic B-spline low-pass
_SATURATION = 4.0  # a coarse cell a quarter covered is trusted fully


def _blur_decimate(values: np.ndarray) -> np.ndarray:
    from scipy import ndimage  # the B-spline fill is an option; the default fill needs no scipy

    out = ndimage.convolve1d(values, _KERNEL, axis=0, mode="constant")
    out = ndimage.convolve1d(out, _KERNEL, axis=1, mode="constant")
    return out[::2, ::2]


def bspline_fill(height: np.ndarray, known: np.ndarray) -> np.ndarray:
    """`height` with every cell not in `known` filled; known cells unchanged."""
    if not np.any(known):
        raise ValueError("no observed cell to fill from")
    from scipy import ndimage

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


_DENSE_MAX_UNKNOWNS = 400  # solved directly (numpy.linalg) at or below this many unknowns
_EXACT_MAX_UNKNOWNS = 30_000  # at or below: solved to rounding, as a direct solve would
_EXACT_RTOL = 1e-10  # relative residual of those
_LARGE_RTOL = 1e-5  # above: a large hole's fill, warm-started, needs no more than this
_MAX_ITERATIONS = 1000


@dataclass(frozen=True)
class LaplaceSystem:
    """The 5-point Laplace equations of the unknown cells, as a stencil: for unknown i,
    degree[i] * h[i] - sum of h over its unknown neighbours = rhs[i] (the known in-domain
    neighbours' heights). Neighbours outside `domain` do not take part: the region edge is a
    free (zero-flux) boundary, so a hole touching it is shaped by the data around it alone."""

    cells: np.ndarray  # flat grid index of each unknown, row-major: the unknowns' numbering
    neighbours: np.ndarray  # (4, n): number of the unknown above, left, right, below; n if none
    degree: np.ndarray  # in-domain neighbours of each unknown
    rhs: np.ndarray

    def apply(self, values: np.ndarray) -> np.ndarray:
        """The equations' left side for the unknowns' `values`."""
        padded = np.append(values, 0.0)  # slot n: "no unknown neighbour" reads zero
        up, left, right, down = (padded[n] for n in self.neighbours)
        return self.degree * values - (up + left + right + down)

    def dense(self) -> np.ndarray:
        """The system's matrix, for small systems."""
        count = len(self.cells)
        matrix = np.diag(self.degree)
        row = np.arange(count)
        for column in self.neighbours:
            linked = column < count
            matrix[row[linked], column[linked]] -= 1.0
        return matrix


def laplace_system(height: np.ndarray, unknown: np.ndarray, domain: np.ndarray) -> LaplaceSystem:
    """The equations of `unknown` cells (within `domain`) given the known heights around them.

    Neighbours are read by flat offsets into the grid padded by one cell (the pad is outside
    the domain)."""
    rows, cols = unknown.shape
    width = cols + 2
    padded_cells = np.flatnonzero(np.pad(unknown, 1))
    count = padded_cells.size
    number = np.full((rows + 2) * width, count, dtype=np.intp)
    number[padded_cells] = np.arange(count)
    inside = np.pad(domain, 1).ravel()
    source = np.pad(np.where(domain & ~unknown, height, 0.0), 1).ravel()  # known, in domain
    neighbours = np.empty((4, count), dtype=np.intp)
    degree = np.zeros(count)
    rhs = np.zeros(count)
    for slot, offset in enumerate((-width, -1, 1, width)):
        at = padded_cells + offset
        neighbours[slot] = number[at]
        degree += inside[at]
        rhs += source[at]
    row, col = np.divmod(padded_cells, width)
    return LaplaceSystem((row - 1) * cols + (col - 1), neighbours, degree, rhs)


def _conjugate_gradients(
    system: LaplaceSystem, guess: np.ndarray, rtol: float, max_iterations: int
) -> np.ndarray:
    """Conjugate gradients from `guess` until the residual is `rtol` of the right side's norm
    (the system is symmetric positive definite when every hole touches a known cell)."""
    rhs = system.rhs
    limit = (rtol * float(np.sqrt(rhs @ rhs))) ** 2
    if limit == 0.0:  # every known neighbour at height zero: so is the solution
        return np.zeros_like(rhs)
    solution = guess.astype(np.float64)
    residual = rhs - system.apply(solution)
    direction = residual.copy()
    squared = float(residual @ residual)
    for _ in range(max_iterations):
        if squared <= limit:
            break
        image = system.apply(direction)
        curvature = float(direction @ image)
        if curvature <= 0.0:  # a hole with no data at all: nothing more to learn
            break
        step = squared / curvature
        solution += step * direction
        residual -= step * image
        previous, squared = squared, float(residual @ residual)
        direction *= squared / previous
        direction += residual
    return solution


def _dense_solve(system: LaplaceSystem) -> np.ndarray:
    """Exact solution of a small system; all NaN (and a warning) if it is singular."""
    try:
        return np.linalg.solve(system.dense(), system.rhs)
    except np.linalg.LinAlgError:
        warnings.warn(
            "membrane fill: a part of the region has no observed cell to fill from",
            RuntimeWarning,
            stacklevel=3,
        )
        return np.full_like(system.rhs, np.nan)


def _coarsen(
    height: np.ndarray, known: np.ndarray, domain: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2x2 block means of the known cells, for a cheap first solution of a large hole."""
    rows, cols = height.shape
    pad = ((0, rows % 2), (0, cols % 2))
    h = np.pad(np.where(known, height, 0.0), pad)
    k = np.pad(known, pad).astype(np.float64)
    d = np.pad(domain, pad)

    def blocks(a: np.ndarray) -> np.ndarray:
        # Strided adds: several times faster than reshape(...).sum(axis=(1, 3)).
        return a[::2, ::2] + a[1::2, ::2] + a[::2, 1::2] + a[1::2, 1::2]

    weight = blocks(k)
    coarse_known = weight > 0
    coarse = np.divide(blocks(h), weight, out=np.zeros_like(weight), where=coarse_known)
    return coarse, coarse_known, d[::2, ::2] | d[1::2, ::2] | d[::2, 1::2] | d[1::2, 1::2]


def membrane_fill(height: np.ndarray, known: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """Fill the unknown cells of `domain` with the discrete harmonic surface of their boundary.

    The fill is decided by the measured cells around each hole only (a floor hole next to a
    pile stays floor), is smooth, and never overshoots the boundary values. A system small
    enough is solved directly; a larger one by conjugate gradients from the fill of the grid
    coarsened 2 x 2, which leaves only the fine detail to iterate on.
    """
    if not np.any(known & domain):
        raise ValueError("no observed cell to fill from")
    unknown = domain & ~known
    out = np.where(known, height, np.nan)
    if not np.any(unknown):
        return out
    system = laplace_system(height, unknown, domain)
    count = len(system.cells)
    if count <= _DENSE_MAX_UNKNOWNS:
        np.put(out, system.cells, _dense_solve(system))
        return out
    coarse = np.nan_to_num(membrane_fill(*_coarsen(height, known, domain)))
    r, c = np.divmod(system.cells, height.shape[1])
    guess = coarse[r // 2, c // 2]  # each fine cell starts from its coarse block's value
    rtol = _EXACT_RTOL if count <= _EXACT_MAX_UNKNOWNS else _LARGE_RTOL
    np.put(out, system.cells, _conjugate_gradients(system, guess, rtol, _MAX_ITERATIONS))
    return out
