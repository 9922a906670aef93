"""Filling of empty cells: the paper's B-spline interpolation (2.3.6), a membrane fill, and the
membrane held to the grain's angle of repose.

`bspline_fill`: a pyramid of coverage-weighted averages is built by B-spline low-pass and
decimation ("pull"); coming back down, each level keeps its own estimate where it has data
and takes the cubic B-spline interpolation of the coarser level where it has none ("push").
Observed cells keep their measured value exactly; the fill is smooth and continuous with
them. Cost O(cells). Its coarse levels average over wide areas, so a floor hole beside a pile
borrows pile height.

`membrane_fill`: the harmonic surface of each hole's own boundary, from its 5-point Laplace
equations. Which solver pays depends on the hole (bench/results/fill.md, issue 22), so each
hole (4-connected unknown cells) is classified before solving, at the cost of a chessboard
distance transform and a labelling (10-60 ms on 0.2-1.4 M cells):
- most holes (scattered cells, and the shadows on the accuracy bench's scenes, which percolate
  into components of 36,000-960,000 cells mostly one or two cells from data): scipy's
  conjugate gradients started from the solution on a grid twice as coarse (itself solved the
  same way, down to a small dense system), to a 1e-10 residual up to 30,000 unknowns, 1e-5
  above. On those scenes it converges in <= 52 iterations and beats the libraries: pyamg's
  setup alone costs more than the whole solve (on the bay batch of bench/silos.py (b), 94,000
  shallow unknowns a scan: 51 ms, 0.55 us an unknown, against 38 ms for the whole warm-started
  fill, and 35 ms more to solve), SuperLU 6x slower. The whole fill, hole sorting included,
  is 0.32x scipy's conjugate gradients from zero on a bay scan (bench/results/scaling.md);
  on a 12 m bin's 1 cm grid, whose 157,000 unknowns are scattered cells and thin shadows,
  the start gains little (it and the iteration from it 86 ms, the iteration from zero 97 ms)
  and the sorting (40 ms on 1.44 M cells) makes the fill 1.4x the plain iteration; the
  sorting stays, as without it a deep hole would take hundreds of iterations and a hole with
  no known cell beside it would make the system singular;
- a hole 24 cells or more from any known cell that is small (<= 30,000 cells) or compact
  (no more cells than 5 x its depth squared: a square hole has 4): pyamg's classical
  algebraic multigrid as the preconditioner of conjugate gradients, to 1e-10, without the
  coarse recursion. The warm-started iteration needs hundreds of iterations there (a 160,000-
  cell square hole 1.6 s against 0.53 s, 400,000 cells 4.0 s against 1.5 s, its arrays 2.7x
  the memory: 271 against 101 MB), and the few such holes (about 12,000 cells each) in a bay
  a third unobserved held the whole system's iteration back (its fill 0.29-0.47 s against
  0.22-0.24 s). Its import costs 0.03-0.04 s once scipy.sparse.linalg is loaded (0.08-0.11 s
  after numpy and scipy.ndimage alone), once a process, when first needed;
- a hole with no known cell next to it: left NaN, with a RuntimeWarning.
Outputs where no hole is routed to pyamg are those of the warm-started iteration alone.
SuperLU (exact) was 1.5-3x slower than pyamg on large holes with 2x its memory (1.3 GB at 1 M
unknowns), slower than the warm start on scattered ones: not used.

`repose_fill` (the default outside bins, `fill = "auto"`, or `fill = "repose"`): the
membrane, capped by the level surface that rises gently from the known cells around a hole and
raised to the flank that falls from the visible crest at the angle of repose
(`repose_bounds`), every decision in it continuous in the data so that a small change of the
cameras' poses changes the fill a little. bench/accuracy.py compares the three fills
(`--fills`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from silo_agent.reconstruct.residual import median

if TYPE_CHECKING:
    from scipy.sparse import csr_array

_KERNEL = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0  # cubic B-spline low-pass
_SATURATION = 4.0  # a coarse cell a quarter covered is trusted fully


def _blur_decimate(values: np.ndarray) -> np.ndarray:
    from scipy import ndimage  # imported when the B-spline fill runs: it is an option

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
# algebraic multigrid for a hole this many cells deep (chessboard distance to data) or more,
_AMG_MIN_DEPTH = 24
_AMG_SMALL_HOLE = 30_000  # if it has no more cells than this (its setup is then cheap)
_AMG_MAX_SPREAD = 5.0  # or no more than this times its depth squared (compact, not percolated)


@dataclass(frozen=True)
class LaplaceSystem:
    """The 5-point Laplace equations of the unknown cells: for unknown i,
    degree[i] * h[i] - sum of h over its unknown neighbours = rhs[i] (the known in-domain
    neighbours' heights). Neighbours outside `domain` do not take part: the region edge is a
    free (zero-flux) boundary, so a hole touching it is shaped by the data around it alone."""

    cells: np.ndarray  # flat grid index of each unknown, row-major: the unknowns' numbering
    neighbours: np.ndarray  # (4, n): number of the unknown above, left, right, below; n if none
    degree: np.ndarray  # in-domain neighbours of each unknown
    rhs: np.ndarray

    def matrix(self) -> csr_array:
        """The system's sparse matrix (rows and columns numbered as the unknowns), written
        row by row: a row's columns, up, left, itself, right, below, are already ascending.
        Indices in the numbering's int32 (half the int64's traffic); the diagonal is written
        at its slot of each row, not through a second masked copy of the values. Row lengths
        are summed over the four neighbour rows and the columns picked by `np.compress`: a sum
        along the short axis of (n, 5) and 2-D boolean indexing cost 3.1 ms on a bay scan's
        87,000 unknowns, these 0.9 ms."""
        from scipy.sparse import csr_array

        count = len(self.cells)
        up, left, right, down = self.neighbours
        dtype = self.neighbours.dtype
        linked_4 = self.neighbours < count
        linked = np.empty((count, 5), dtype=bool)
        linked[:, [0, 1, 3, 4]] = linked_4.T
        linked[:, 2] = True
        lengths = linked_4.sum(axis=0, dtype=dtype)
        lengths += 1
        starts = np.zeros(count + 1, dtype=dtype)
        np.cumsum(lengths, out=starts[1:])
        itself = np.arange(count, dtype=dtype)
        stacked = np.stack([up, left, itself, right, down], axis=1)
        columns = np.compress(linked.ravel(), stacked.ravel())
        values = np.full(columns.size, -1.0)
        values[starts[:-1] + linked_4[0] + linked_4[1]] = self.degree  # the diagonal
        return csr_array((values, columns, starts), shape=(count, count))

    def dense(self) -> np.ndarray:
        """The system's matrix as a dense array, for small systems."""
        return self.matrix().toarray()


def laplace_system(height: np.ndarray, unknown: np.ndarray, domain: np.ndarray) -> LaplaceSystem:
    """The equations of `unknown` cells (within `domain`) given the known heights around them.

    Neighbours are read by flat offsets into the grid padded by one cell (the pad is outside
    the domain); unknowns are numbered in int32 while they fit."""
    rows, cols = unknown.shape
    width = cols + 2
    size = (rows + 2) * width
    index = np.int32 if size < np.iinfo(np.int32).max else np.intp

    def padded(values: np.ndarray, dtype: type, where: np.ndarray | None = None) -> np.ndarray:
        out = np.zeros((rows + 2, width), dtype=dtype)
        np.copyto(out[1:-1, 1:-1], values, where=True if where is None else where)
        return out.ravel()

    padded_cells = np.flatnonzero(padded(unknown, bool))
    count = padded_cells.size
    number = np.full(size, count, dtype=index)
    number[padded_cells] = np.arange(count, dtype=index)
    inside = padded(domain, bool)
    source = padded(height, np.float64, where=domain & ~unknown)  # known, in domain
    neighbours = np.empty((4, count), dtype=index)
    degree = np.zeros(count)
    rhs = np.zeros(count)
    for slot, offset in enumerate((-width, -1, 1, width)):
        at = padded_cells + offset
        np.take(number, at, out=neighbours[slot])
        degree += inside[at]
        rhs += source[at]
    row, col = np.divmod(padded_cells, width)
    return LaplaceSystem((row - 1) * cols + (col - 1), neighbours, degree, rhs)


def _conjugate_gradients(
    system: LaplaceSystem, guess: np.ndarray, rtol: float, max_iterations: int
) -> np.ndarray:
    """scipy's conjugate gradients from `guess` until the residual is `rtol` of the right
    side's norm (the system is symmetric positive definite when every hole touches a known
    cell). The hand-written iteration it replaces was 1.4x faster on one bench fill and 1.3x
    slower on another (bench/scaling.py): no reason to keep our own."""
    from scipy.sparse.linalg import cg

    solution, _ = cg(
        system.matrix(), system.rhs, guess, rtol=rtol, atol=0.0, maxiter=max_iterations
    )
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
    h, k, d = np.where(known, height, 0.0), known.astype(np.uint8), domain
    if rows % 2 or cols % 2:  # padded to even sides (a copy of each)
        pad = ((0, rows % 2), (0, cols % 2))
        h, k, d = np.pad(h, pad), np.pad(k, pad), np.pad(d, pad)

    def blocks(a: np.ndarray) -> np.ndarray:
        # Strided adds: several times faster than reshape(...).sum(axis=(1, 3)).
        return a[::2, ::2] + a[1::2, ::2] + a[::2, 1::2] + a[1::2, 1::2]

    weight = blocks(k).astype(np.float64)  # counts of known cells, 0-4: exact
    coarse_known = weight > 0
    coarse = np.divide(blocks(h), weight, out=np.zeros_like(weight), where=coarse_known)
    return coarse, coarse_known, d[::2, ::2] | d[1::2, ::2] | d[::2, 1::2] | d[1::2, 1::2]


def _classify_holes(
    known: np.ndarray, domain: np.ndarray, unknown: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(deep, cut_off) cells of `unknown`. Holes are 4-connected, as the equations couple
    cells. Deep: a hole with a cell _AMG_MIN_DEPTH or more cells (chessboard distance) from any
    known cell, small or compact (see _AMG_SMALL_HOLE, _AMG_MAX_SPREAD). Cut off: a hole with
    no known cell of `domain` next to it (its equations are singular).

    A cell is deep when no anchor lies within _AMG_MIN_DEPTH - 1 cells of it (a maximum
    filter: 2.5 ms on a bay scan's 0.4 M cells, against 4.3 ms for the chessboard distance
    transform); the distance itself, a hole's depth, is computed only if a hole with deep
    cells is too large to be deep by its size alone."""
    from scipy import ndimage

    anchors = known & domain
    reach = 2 * _AMG_MIN_DEPTH - 1
    near = ndimage.maximum_filter(anchors, size=reach, mode="constant", cval=False)
    labels, count = ndimage.label(unknown)
    flat = labels.ravel()

    def labels_of(cells: np.ndarray) -> np.ndarray:
        # np.compress: 2-D boolean indexing of the labels is several times slower
        return np.compress(cells.ravel(), flat)

    # flags per hole by indexing with the labels of the cells that raise them (O(cells))
    deep_hole = np.zeros(count + 1, dtype=bool)
    deep_cells = unknown & ~near
    deep_hole[labels_of(deep_cells)] = True
    candidates = np.flatnonzero(deep_hole)
    if candidates.size:
        size = np.bincount(labels_of(unknown), minlength=count + 1)[candidates]
        small = size <= _AMG_SMALL_HOLE
        if not np.all(small):
            distance = ndimage.distance_transform_cdt(~anchors, metric="chessboard")
            # each hole's depth over its deep cells only; ndimage.maximum argsorts every
            # cell of the grid (0.4 s on 1.44 M cells, against 0.01 s)
            depth = np.zeros(count + 1, dtype=distance.dtype)
            np.maximum.at(depth, labels_of(deep_cells), distance[deep_cells])
            compact = size <= _AMG_MAX_SPREAD * depth[candidates].astype(np.int64) ** 2
            small |= compact
        deep_hole[candidates] = small
    padded = np.pad(anchors, 1)
    beside = padded[:-2, 1:-1] | padded[2:, 1:-1] | padded[1:-1, :-2] | padded[1:-1, 2:]
    anchored_hole = np.zeros(count + 1, dtype=bool)  # a known 4-neighbour in the domain
    anchored_hole[labels_of(beside)] = True
    # each hole's kind, spread to its cells by one gather: 0 shallow (or no hole), 1 deep,
    # 2 cut off
    kind = np.where(anchored_hole, deep_hole, 2).astype(np.uint8)
    kind[0] = 0  # label 0: not a hole
    cells = kind[labels]
    return cells == 1, cells == 2


def membrane_fill(height: np.ndarray, known: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """Fill the unknown cells of `domain` with the discrete harmonic surface of their boundary.

    The fill is decided by the measured cells around each hole only (a floor hole next to a
    pile stays floor), is smooth, and never overshoots the boundary values. A system small
    enough is solved directly. Otherwise each hole is solved by the method that suits it (see
    the module's docstring): a deep hole, small or compact, by algebraic multigrid (pyamg);
    the others (scattered cells, shadows percolating among them) by conjugate gradients from
    the fill of the grid coarsened 2 x 2, which leaves only the fine detail to iterate on.
    The two sets of holes share no equation. A hole with no known cell next to it is left
    NaN, with a RuntimeWarning.
    """
    if not np.any(known & domain):
        raise ValueError("no observed cell to fill from")
    unknown = domain & ~known
    if np.count_nonzero(unknown) <= _DENSE_MAX_UNKNOWNS:
        return _warm_cg_fill(height, known, domain)
    deep, cut_off = _classify_holes(known, domain, unknown)
    if np.any(cut_off):
        warnings.warn(
            "membrane fill: a part of the region has no observed cell to fill from",
            RuntimeWarning,
            stacklevel=2,
        )
    if not np.any(deep | cut_off):
        return _warm_cg_fill(height, known, domain)  # the path as it was
    shallow = unknown & ~deep & ~cut_off
    out = _warm_cg_fill(height, known, domain & ~deep & ~cut_off)
    if np.any(deep):  # the deep cells, NaN in `out`, written into it
        _multigrid_fill(height, known, domain & ~shallow & ~cut_off, out)
    return out


def _warm_cg_fill(height: np.ndarray, known: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """The membrane by conjugate gradients warm-started from the 2 x 2 coarser fill (itself
    solved the same way, down to a dense solve)."""
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
    coarse = np.nan_to_num(_warm_cg_fill(*_coarsen(height, known, domain)))
    r, c = np.divmod(system.cells, height.shape[1])
    guess = coarse[r // 2, c // 2]  # each fine cell starts from its coarse block's value
    rtol = _EXACT_RTOL if count <= _EXACT_MAX_UNKNOWNS else _LARGE_RTOL
    np.put(out, system.cells, _conjugate_gradients(system, guess, rtol, _MAX_ITERATIONS))
    return out


def _multigrid_fill(
    height: np.ndarray, known: np.ndarray, domain: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """The membrane by pyamg's classical (Ruge-Stuben) algebraic multigrid as a conjugate
    gradients preconditioner, to _EXACT_RTOL whatever the size (every hole must touch a known
    cell: the system is then symmetric positive definite).

    Direct interpolation, and one forward Gauss-Seidel sweep before the coarse correction and
    one backward after it (still a symmetric preconditioner, as conjugate gradients need),
    not pyamg's classical interpolation and symmetric sweeps both ways: on the deep holes of
    the bay batch (bench/silos.py (b), 25-38 k unknowns a scan) setup and solve 53-59 ms
    against 63-72 ms, 13 iterations against 10, the same solution to 2e-9 m. On the same
    holes, not faster: smoothed aggregation (120 ms) or root-node (195 ms) hierarchies,
    SuperLU (90-106 ms), Ruge-Stuben with PMIS splitting (181 ms), a float32 hierarchy,
    scipy's conjugate gradients around the hierarchy, fewer levels over a dense coarse solve.

    The unknown cells' solution is written into `out` if given (the other cells are left as
    they are), else into a copy of the known heights, NaN elsewhere."""
    import pyamg

    if out is None:
        out = np.where(known, height, np.nan)
    system = laplace_system(height, domain & ~known, domain)
    hierarchy = pyamg.ruge_stuben_solver(
        system.matrix(),
        interpolation="direct",
        presmoother=("gauss_seidel", {"sweep": "forward"}),
        postsmoother=("gauss_seidel", {"sweep": "backward"}),
    )
    solution = hierarchy.solve(system.rhs, tol=_EXACT_RTOL, maxiter=_MAX_ITERATIONS, accel="cg")
    np.put(out, system.cells, solution)
    return out


REPOSE_NODE_M = 0.03  # the repose bounds' sources: a lattice this fine, in metres
REPOSE_TARGET_M = 0.1  # the bounds are computed on a lattice this fine, interpolated between
REPOSE_SMOOTH_M = 0.03  # over Gaussian means of this sigma (one noisy cell sets no bound)
HOLE_DENSITY = 0.25  # where the points are this share of the typical density, half a hole
LEVEL_SLOPE = 0.02  # a level surface (a floor, levelled grain) rises no more than 2 %
GAP_M = 0.03  # no hole within this of a known cell, wholly one from twice as far
DOUBT_M = 0.1  # a source wholly in a hole is lowered (raised for `level`) this far: no bound
SELF_REACH_M = 0.1  # a source is levelled against all sources this near it
RIM_NODES = 2  # the holes' bounds are taken from the sources this many nodes from a hole
SOURCE_RING_M = 0.12  # sources: lattice nodes this near a node of a hole
_PAIRS_PER_CHUNK = 1 << 20  # (target, source) distances held at once
_TILE_PAIRS = 64  # `_envelopes`: about sqrt(pairs) / this tiles of targets


def _envelopes(
    target: tuple[np.ndarray, np.ndarray],
    source: tuple[np.ndarray, np.ndarray],
    bounds: list[tuple[np.ndarray, float, bool]],
) -> list[np.ndarray]:
    """At each target, for each (height, slope, upper) of `bounds`: the min over sources of
    height + slope * distance (`upper`), or the max of height - slope * distance; positions in
    any unit the slope is per.

    The targets are taken in square tiles (about sqrt(pairs) / _TILE_PAIRS of them over their
    extent), and a tile against those sources only that can set a bound somewhere in it: for
    `upper`, a source whose height + slope x (its least distance to the tile's box) is above
    the least height + slope x (greatest distance) of any source (that one bounds every
    target of the tile lower) sets none; for a lower bound the same turned over. The pairs
    kept are computed as over all of them, so the envelopes are the same to the bit (a margin
    of 1e-5 of the values' scale covers the pairs' float32 rounding). On the bay batch of
    bench/silos.py (b) a tenth to a fifth of the pairs are kept: the repose bounds' two calls
    40 ms a scan against 12 ms."""
    ty, tx = (np.asarray(a, dtype=np.float32) for a in target)
    sy, sx = (np.asarray(a, dtype=np.float32) for a in source)
    heights = [np.asarray(h, dtype=np.float32) for h, _, _ in bounds]
    outs = [np.empty(len(ty)) for _ in bounds]
    if len(ty) == 0 or len(sy) == 0:
        return _pair_envelopes(ty, tx, sy, sx, heights, bounds)
    span = max(float(np.ptp(ty)), float(np.ptp(tx)), 1e-9)
    side = span / max(1, round(np.sqrt(np.sqrt(float(len(ty)) * len(sy)) / _TILE_PAIRS)))
    tile_r = np.floor((ty - ty.min()) / side).astype(np.intp)
    tile_c = np.floor((tx - tx.min()) / side).astype(np.intp)
    tile = tile_r * (int(tile_c.max()) + 1) + tile_c
    order = np.argsort(tile, kind="stable")
    key = tile[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], len(order)]
    by, bx = ty[order], tx[order]
    y0, y1 = np.minimum.reduceat(by, starts), np.maximum.reduceat(by, starts)
    x0, x1 = np.minimum.reduceat(bx, starts), np.maximum.reduceat(bx, starts)
    sy64, sx64 = sy.astype(np.float64), sx.astype(np.float64)
    h64 = [h.astype(np.float64) for h in heights]
    scale = max(float(np.max(np.abs(h))) for h in h64) + max(
        slope for _, slope, _ in bounds
    ) * float(np.hypot(np.ptp(np.r_[ty, sy]), np.ptp(np.r_[tx, sx])))
    margin = 1e-5 * scale
    # a loop over tiles (tens), each a few vector operations over the sources
    for first, last, ya, yb, xa, xb in zip(starts, ends, y0, y1, x0, x1, strict=True):
        gap_y = np.maximum(np.maximum(ya - sy64, sy64 - yb), 0.0)
        gap_x = np.maximum(np.maximum(xa - sx64, sx64 - xb), 0.0)
        least = np.sqrt(gap_y * gap_y + gap_x * gap_x)
        span_y = np.maximum(sy64 - ya, yb - sy64)
        span_x = np.maximum(sx64 - xa, xb - sx64)
        most = np.sqrt(span_y * span_y + span_x * span_x)
        keep = np.zeros(len(sy), dtype=bool)
        for h, (_, slope, upper) in zip(h64, bounds, strict=True):
            if upper:
                keep |= h + slope * least <= float(np.min(h + slope * most)) + margin
            else:
                keep |= h - slope * least >= float(np.max(h - slope * most)) - margin
        kept = np.flatnonzero(keep)
        members = order[first:last]
        for out, part in zip(
            outs,
            _pair_envelopes(
                ty[members], tx[members], sy[kept], sx[kept], [h[kept] for h in heights], bounds
            ),
            strict=True,
        ):
            out[members] = part
    return outs


def _pair_envelopes(
    ty: np.ndarray,
    tx: np.ndarray,
    sy: np.ndarray,
    sx: np.ndarray,
    heights: list[np.ndarray],
    bounds: list[tuple[np.ndarray, float, bool]],
) -> list[np.ndarray]:
    """`_envelopes` over every (target, source) pair, in float32 (positions within a few
    thousand cells, heights to a micrometre: half the float64's time on these many pairs).
    The distances computed once (the repose bounds take a lower and an upper envelope over
    the same pairs; each is 40 % of the pairs' work, the distances the rest), and scaled once
    a slope. In chunks of targets, which bound the memory (a loop over chunks, not cells).
    No sources bound nothing: +inf for an upper envelope, -inf for a lower one (a min or max
    over no pairs; a few sources, none of them on the far bounds' every other node)."""
    slopes = sorted({slope for _, slope, _ in bounds})
    if len(sy) == 0:
        return [np.full(len(ty), np.inf if upper else -np.inf) for _, _, upper in bounds]
    outs = [np.empty(len(ty)) for _ in bounds]
    chunk = max(1, _PAIRS_PER_CHUNK // max(1, len(sy)))
    # the chunks' arrays allocated once (a fresh one a chunk is as many page faults)
    rows = min(chunk, len(ty))
    buffers = [np.empty((rows, len(sy)), dtype=np.float32) for _ in range(3)]
    for start in range(0, len(ty), chunk):
        at = slice(start, start + chunk)
        dy, dx, scratch = (b[: len(ty[at])] for b in buffers)
        np.subtract(ty[at, None], sy, out=dy)
        np.subtract(tx[at, None], sx, out=dx)
        dy *= dy
        dx *= dx
        dy += dx
        distance = np.sqrt(dy, out=dy)
        for slope in slopes:
            if slope == slopes[-1]:  # the last slope scales the distances in place
                reach = distance
                reach *= np.float32(slope)
            else:
                reach = np.multiply(distance, np.float32(slope), out=dx)
            for (_, bound_slope, upper), height, out in zip(bounds, heights, outs, strict=True):
                if bound_slope != slope:
                    continue
                if upper:
                    np.add(reach, height, out=scratch)
                    out[at] = scratch.min(axis=1)
                else:
                    np.subtract(height, reach, out=scratch)
                    out[at] = scratch.max(axis=1)
    return outs


class _LatticeMeans:
    """Gaussian means (sigma in cells, truncated at 4 sigma, zero outside the grid, as
    scipy.ndimage.gaussian_filter's) of grids of one shape, read bilinearly at the nodes of a
    lattice every `spacing` cells from the centre of cell (0, 0), as map_coordinates (order 1,
    mode "nearest") reads the filtered grid there. Both steps are linear and separable, so a
    mean at the nodes is R @ values @ C.T, R and C the sparse (nodes x cells) weights of the
    rows and the columns: only the nodes are computed, not the filtered grid (on the 3 cm
    lattice of a 1 cm grid a ninth of the cells; the bay batch of bench/silos.py (b): the
    repose bounds 66 ms a scan with six filters of the 1 cm grid and their samples, 33 ms
    so). The same values to rounding (the sums in another order: the bounds within 8e-16 m,
    `process --json`'s heights and positions within 3e-16 m, bench/accuracy.py's table
    unchanged)."""

    def __init__(self, shape: tuple[int, ...], sigma: float, spacing: float) -> None:
        self.axes = [np.arange(0.0, n - 1 + 1e-9, spacing) for n in shape]
        self.rows, self.cols = (
            _gaussian_interpolation(n, at, sigma) for n, at in zip(shape, self.axes, strict=True)
        )

    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        """Node positions (rows, cols) in cells, each of the lattice's shape."""
        rows, cols = np.meshgrid(*self.axes, indexing="ij")
        return rows, cols

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """The mean of `values` at each node."""
        return np.asarray(self.cols @ np.asarray(self.rows @ values).T).T

    def moments(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The means of `values`, of `values` x its cells' row and x their column."""
        count, nodes = self.rows.shape[0], self.cols.shape[0]
        both = np.asarray(
            _with_moment(self.cols) @ np.asarray(_with_moment(self.rows) @ values).T
        ).T
        return both[:count, :nodes], both[count:, :nodes], both[:count, nodes:]


def _with_moment(weights: csr_array) -> csr_array:
    """`weights` over `weights` x each entry's column: (2n, size) rows."""
    from scipy.sparse import csr_array

    count, size = weights.shape
    return csr_array(
        (
            np.concatenate([weights.data, weights.data * weights.indices]),
            np.concatenate([weights.indices, weights.indices]),
            np.concatenate([weights.indptr, weights.indptr[1:] + weights.nnz]),
        ),
        shape=(2 * count, size),
    )


def _gaussian_interpolation(size: int, at: np.ndarray, sigma: float) -> csr_array:
    """(len(at), size) weights of a line's Gaussian mean (`_LatticeMeans`) read linearly at
    positions `at` (cells, 0 .. size - 1)."""
    from scipy.sparse import csr_array

    radius = int(4.0 * sigma + 0.5)
    taps = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 / (sigma * sigma) * taps**2)
    kernel /= kernel.sum()
    padded = np.concatenate([[0.0], kernel, [0.0]])  # tap o at padded[o + radius + 1]
    low = np.minimum(np.floor(at).astype(np.intp), size - 1)
    high = np.minimum(low + 1, size - 1)
    frac = at - low
    offsets = np.arange(-radius, radius + 2)  # cells low + offsets take part
    column = low[:, None] + offsets
    weight = (1.0 - frac)[:, None] * padded[offsets + radius + 1] + frac[:, None] * padded[
        np.clip(offsets - (high - low)[:, None] + radius + 1, 0, padded.size - 1)
    ]
    keep = (column >= 0) & (column < size) & (weight != 0)
    row = np.broadcast_to(np.arange(len(at))[:, None], column.shape)
    return csr_array((weight[keep], (row[keep], column[keep])), shape=(len(at), size))


def _hole_share(density: np.ndarray) -> np.ndarray:
    """How much of a hole a place is, from its point density over the typical one: 1 up to
    half HOLE_DENSITY, 0 from HOLE_DENSITY, linear between (no switch on noisy counts)."""
    return np.clip(2.0 - 2.0 * density / HOLE_DENSITY, 0.0, 1.0)


def repose_bounds(
    height: np.ndarray,
    known: np.ndarray,
    unknown: np.ndarray,
    points: np.ndarray,
    slope: float,
    step: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lower, level, share) for every `unknown` cell, from the known cells around it;
    `points` is the number of points each cell held.

    Grain stands no steeper than its angle of repose: a surface at distance d from a known
    height h lies no lower than h - slope * d, so below the crest of a pile an unseen flank
    falls no faster than the repose slope (`lower`). `level` is the least surface rising from
    the known cells at LEVEL_SLOPE: what a level surface (a floor, levelled grain) reaches.
    `share` is how much of a hole the cell is (`_hole_share`): a shadow holds few points (a
    few that depth noise carried in), while on a grid finer than the points' spacing most
    cells of a well-seen surface are empty and no hole; and a cell within GAP_M of a known
    cell is none either, one 2 x GAP_M away wholly: on a 1 cm grid the gaps between a sparse
    floor's points took a hole's share and the bounds lowered the fill there, by up to 1.5 pp
    against a 10 cm grid's (with GAP_M 1 cm still 0.73 pp). The price: the shadows speckled
    with cells that depth noise carried in are no hole either (on the bay-cone scene, where
    the block-wise fill gained 0.9 pp with two views, all of them).

    Every decision is continuous in the data, so that a small change of the cameras' poses
    changes the bounds a little, not a block at a time (with holes and sources picked per
    0.1 m block, the calibration rig of tests/test_calib_recover.py read 1.0-1.1 % apart with
    its calibrated and its true poses: one block beside the crest turned from hole to source
    and raised the whole unseen flank 4 cm). The known heights and the point density are
    Gaussian means (sigma REPOSE_SMOOTH_M) sampled on a lattice of REPOSE_NODE_M (in metres:
    the same at every grid step); each source stands at the centroid of the known cells it
    averages (at a hole's rim they lie to one side: on a slope their mean is the height there,
    not at the node). A node is a source in proportion to how well seen it is: one in a hole
    is lowered by up to DOUBT_M for `lower` (raised for `level`), so a source fades in as its
    points do. The sources are the nodes within SOURCE_RING_M of a hole. A source steeper
    than repose above its neighbours is not grain (wall points carried in by depth noise, a
    post): for `lower` each source is first lowered to the largest repose-steep surface under
    the others, for `level` raised to the least above (against every source within
    SELF_REACH_M, every other lattice row and column beyond). The bounds are then taken from
    the sources within RIM_NODES of a hole (one farther out bounds no more than those between
    it and the hole do, once levelled against them) on a lattice of REPOSE_TARGET_M, and
    interpolated bilinearly to the cells.
    """
    from scipy import ndimage

    cell_rows, cell_cols = np.nonzero(unknown)
    cells = (cell_rows, cell_cols)
    unbounded = np.full(len(cell_rows), np.inf)
    sigma = REPOSE_SMOOTH_M / step
    region = known | unknown
    means = _LatticeMeans(known.shape, sigma, REPOSE_NODE_M / step)
    known_f = known.astype(np.float64)
    node_weight, node_r, node_c = means.moments(known_f)
    node_area = means(region.astype(np.float64))
    node_points = means(np.where(region, points, 0).astype(np.float64))

    def densities(area: np.ndarray, points_mean: np.ndarray) -> np.ndarray:
        """Point density at the nodes; 0 where almost none of the region is near."""
        return np.divide(points_mean, area, out=np.zeros_like(area), where=area > 1e-3)

    def hole_share(node_area: np.ndarray, node_density: np.ndarray) -> np.ndarray:
        return np.where(node_area > 1e-3, _hole_share(node_density / typical), 0.0)

    node_density = densities(node_area, node_points)
    seen = node_density > 0
    typical = median(node_density[seen]) if np.any(seen) else 0.0
    if typical <= 0:
        return -unbounded, unbounded, np.zeros(len(cells[0]))
    share = hole_share(node_area, node_density)
    hole = share > 0
    ring = max(1, int(np.ceil(SOURCE_RING_M / REPOSE_NODE_M)))
    near = ndimage.binary_dilation(hole, np.ones((3, 3), dtype=bool), iterations=ring)
    is_source = near & (share < 1) & (node_weight > 1e-3 * node_area)
    coarse = _LatticeMeans(known.shape, sigma, REPOSE_TARGET_M / step)
    target = coarse.nodes()
    target_area = coarse(region.astype(np.float64))
    target_share = hole_share(
        target_area, densities(target_area, coarse(np.where(region, points, 0).astype(np.float64)))
    )
    bounded = ndimage.binary_dilation(target_share > 0, np.ones((3, 3), dtype=bool))
    if not np.any(is_source) or not np.any(target_share > 0):
        return -unbounded, unbounded, np.zeros(len(cells[0]))
    # each source's height is the mean of the known cells around it, and it stands at their
    # centroid (on a slope their mean is the height there, not at the node: at the rim of a
    # hole the known cells lie to one side)
    weight_at = node_weight[is_source]
    source_height = means(np.where(known, height, 0.0))[is_source] / weight_at
    source_r = node_r[is_source] / weight_at
    source_c = node_c[is_source] / weight_at
    source = (source_r, source_c)
    doubt = DOUBT_M * share[is_source]
    cell_slope = slope * step
    # levelled against every source within SELF_REACH_M, and every other one of the lattice's
    # rows and columns farther off (a quarter of the pairs; a far source's bound changes
    # slowly); a doubtful source holds the others back no more than it bounds a hole
    reach = max(1, round(SELF_REACH_M / REPOSE_NODE_M))
    every_other = np.zeros_like(is_source)
    every_other[::2, ::2] = True
    every_other = every_other[is_source]
    sparse = (source[0][every_other], source[1][every_other])
    raised, lowered = source_height + doubt, source_height - doubt
    far_under, far_over = _envelopes(
        source,
        sparse,
        [(raised[every_other], cell_slope, True), (lowered[every_other], cell_slope, False)],
    )
    near_under, near_over = _local_envelopes(is_source, source, raised, lowered, cell_slope, reach)
    under = np.minimum(near_under, far_under)
    over = np.maximum(near_over, far_over)
    # the holes' bounds from the sources at their rims: one farther out bounds no more than
    # those between it and the hole, once levelled to repose against them
    rim = ndimage.binary_dilation(hole, np.ones((3, 3), dtype=bool), iterations=RIM_NODES)
    rim = rim[is_source]
    if not np.any(rim):
        return -unbounded, unbounded, np.zeros(len(cells[0]))
    rim_source = (source[0][rim], source[1][rim])
    where = (target[0][bounded], target[1][bounded])
    lower = np.full(target[0].shape, np.nan)
    level = np.full(target[0].shape, np.nan)
    lower[bounded], level[bounded] = _envelopes(
        where,
        rim_source,
        [
            ((under - doubt)[rim], cell_slope, False),
            ((over + doubt)[rim], LEVEL_SLOPE * step, True),
        ],
    )
    spacing = REPOSE_TARGET_M / step
    # a cell beside a known one is a gap between points on a grid finer than their spacing,
    # however few points the place holds: no hole (and its share not interpolated)
    gap = _near_distance(known, cells, int(np.ceil(2 * GAP_M / step)) + 1) * step
    apart = np.clip((gap - GAP_M) / GAP_M, 0.0, 1.0)
    away = apart > 0
    cell_share = np.zeros(len(apart))
    cell_share[away] = apart[away] * _lattice_to_cells(
        np.where(bounded, target_share, 0.0), (cells[0][away], cells[1][away]), spacing
    )
    held = cell_share > 0
    # the bounds interpolated at the cells they hold only (a sixth of the unknown cells on the
    # bay scans at 1 cm)
    held_cells = (cells[0][held], cells[1][held])
    lower_cells = np.full(len(held), -np.inf)
    level_cells = np.full(len(held), np.inf)
    lower_cells[held] = _lattice_to_cells(lower, held_cells, spacing)
    level_cells[held] = _lattice_to_cells(level, held_cells, spacing)
    return lower_cells, level_cells, np.where(held, cell_share, 0.0)


def _near_distance(
    known: np.ndarray, cells: tuple[np.ndarray, np.ndarray], limit: int
) -> np.ndarray:
    """At `cells`, the distance (in cells, between centres) to the nearest `known` cell: where
    it is `limit` or less, exactly ndimage.distance_transform_edt's of ~known (the square root
    of the same integer), farther inf. The nearest known cell of each row along it (running
    maximum and minimum of the known cells' columns), then the least dr^2 + that^2 over the
    rows within `limit`: O(cells x limit) in small integers, against the exact transform's
    feature transform over the whole grid (the bay batch of bench/silos.py (b), alternating
    runs: 7.6 ms a scan against 29 ms; then in int16, where it holds the values, rather than
    int32: 7.6 against 10.0 ms, under more load)."""
    rows, cols = known.shape
    far = limit + 1
    fits = cols + 2 * far < np.iinfo(np.int16).max and far * far + limit * limit < 2**15
    small = np.int16 if fits else np.int32  # int16 halves the passes' memory traffic
    column = np.arange(cols, dtype=small)
    left = np.where(known, column, small(-2 * far))
    np.maximum.accumulate(left, axis=1, out=left)
    right = np.where(known[:, ::-1], column[::-1], small(cols + 2 * far))
    np.minimum.accumulate(right, axis=1, out=right)
    along = np.minimum(column - left, right[:, ::-1] - column)
    np.minimum(along, far, out=along)
    square = along * along
    nearest = square.copy()
    for dr in range(1, min(limit, rows - 1) + 1):
        np.minimum(nearest[dr:], square[:-dr] + small(dr * dr), out=nearest[dr:])
        np.minimum(nearest[:-dr], square[dr:] + small(dr * dr), out=nearest[:-dr])
    at = nearest[cells]
    return np.where(at <= limit * limit, np.sqrt(at.astype(np.float64)), np.inf)


def _local_envelopes(
    where: np.ndarray,
    position: tuple[np.ndarray, np.ndarray],
    raised: np.ndarray,
    lowered: np.ndarray,
    slope: float,
    reach: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The upper envelope (as `_envelopes`) of `raised` and the lower of `lowered`, of the
    sources on themselves, over the sources within `reach` lattice nodes of each only (a
    source steeper than repose stands so above its near neighbours): the sources are the
    `where` nodes of a
    lattice, at `position`, in their order. Both over the same pairs, whose distances are
    computed once. Over the sources alone (a neighbour's number read from the padded
    lattice; a NaN stand-in where there is none), not the whole lattice: on the bay batch of
    bench/silos.py (b) a fifth of its nodes are sources, 2.6 ms a scan against 8.3 ms."""
    count = len(raised)
    rows, cols = where.shape
    width = cols + 2 * reach
    number = np.full((rows + 2 * reach, width), count, dtype=np.intp)
    number[reach : reach + rows, reach : reach + cols][where] = np.arange(count)
    node_r, node_c = np.nonzero(where)
    base = (node_r + reach) * width + node_c + reach
    flat = number.ravel()
    up, down, r, c = (np.append(v, np.nan) for v in (raised, lowered, *position))
    under = np.where(np.isnan(raised), np.inf, raised)
    over = np.where(np.isnan(lowered), -np.inf, lowered)
    r0, c0 = r[:count], c[:count]
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if (dr, dc) == (0, 0) or dr * dr + dc * dc > reach * reach:
                continue
            other = flat[base + (dr * width + dc)]
            distance = np.hypot(r[other] - r0, c[other] - c0)
            distance *= slope
            np.fmin(under, distance + up[other], out=under)
            np.fmax(over, down[other] - distance, out=over)
    return under, over


def _lattice_to_cells(
    values: np.ndarray, cells: tuple[np.ndarray, np.ndarray], spacing: float
) -> np.ndarray:
    """Lattice values interpolated bilinearly at cells (rows, cols); NaN where a node around
    is NaN."""

    def axis(at: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        position = np.clip(at / spacing, 0.0, size - 1.0)
        low = np.minimum(np.floor(position).astype(np.intp), size - 1)
        return low, np.minimum(low + 1, size - 1), position - low

    r0, r1, wr = axis(cells[0].astype(np.float64), values.shape[0])
    c0, c1, wc = axis(cells[1].astype(np.float64), values.shape[1])
    top = values[r0, c0] * (1 - wc) + values[r0, c1] * wc
    bottom = values[r1, c0] * (1 - wc) + values[r1, c1] * wc
    return top * (1 - wr) + bottom * wr


def repose_fill(
    height: np.ndarray,
    known: np.ndarray,
    domain: np.ndarray,
    points: np.ndarray,
    slope: float,
    step: float,
    level_floor: bool = True,
) -> np.ndarray:
    """The membrane fill, held to what grain at its angle of repose allows.

    A membrane across an unseen area is a soap film: it sags under a pile's unseen flank (a
    cone is not harmonic) and bulges over the floor in a pile's shadow, borrowing the pile's
    height. Grain either lies level or stands at its angle of repose: the fill is the
    membrane, no higher than a level surface from the known cells reaches, and no lower than
    the flank that continues from the visible crest at the repose slope. `level_floor`: the
    ground under the grain is level (a floor); on sloping ground (`base = "boundary"`) a level
    surface is no cap and only the repose flank applies.
    """
    filled = membrane_fill(height, known, domain)
    unknown = domain & ~known
    if not np.any(unknown):
        return filled
    lower, level, share = repose_bounds(height, known & domain, unknown, points, slope, step)
    membrane = filled[unknown]
    capped = np.minimum(membrane, level) if level_floor else membrane
    held = np.maximum(capped, lower)
    # in proportion to how much of a hole each cell is
    filled[unknown] = np.where(share > 0, membrane + share * (held - membrane), membrane)
    return filled
