"""membrane_fill's vectorised equations against their plain definition, and its solution.

The Laplace system is built as a stencil from flat offsets, so these tests rebuild it cell by
cell on small grids, check the filled surface against the 5-point equations evaluated on the
output grid itself, and against scipy's sparse direct solver (an independent solver).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from silo_agent.reconstruct.fill import _classify_holes, laplace_system, membrane_fill

_STEPS = ((-1, 0), (0, -1), (0, 1), (1, 0))


def _reference_system(
    height: np.ndarray, unknown: np.ndarray, domain: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Dense matrix and right side from the definition, one cell at a time."""
    rows, cols = unknown.shape
    number = -np.ones(unknown.shape, dtype=int)
    number[unknown] = np.arange(unknown.sum())
    matrix = np.zeros((unknown.sum(), unknown.sum()))
    rhs = np.zeros(unknown.sum())
    for r, c in zip(*np.nonzero(unknown), strict=True):
        me = number[r, c]
        for dr, dc in _STEPS:
            nr, nc = r + dr, c + dc
            if not (0 <= nr < rows and 0 <= nc < cols and domain[nr, nc]):
                continue
            matrix[me, me] += 1.0
            if unknown[nr, nc]:
                matrix[me, number[nr, nc]] -= 1.0
            else:
                rhs[me] += height[nr, nc]
    return matrix, rhs


def _harmonic_residual(filled: np.ndarray, unknown: np.ndarray, domain: np.ndarray):
    """degree * h - sum of in-domain neighbours, at each unknown cell of the output grid."""
    padded = np.pad(np.where(domain, filled, 0.0), 1)
    inside = np.pad(domain, 1).astype(float)
    rows, cols = filled.shape
    residual = np.zeros(filled.shape)
    for dr, dc in _STEPS:
        view = (slice(1 + dr, 1 + dr + rows), slice(1 + dc, 1 + dc + cols))
        residual += inside[view] * np.where(unknown, filled, 0.0) - padded[view]
    return residual[unknown]


def _case(shape: tuple[int, int], seed: int, full_domain: bool):
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    height = 1.0 + 0.3 * np.sin(rows / 5.0) + 0.2 * np.cos(cols / 3.0)
    known = rng.random(shape) < 0.5
    known[: max(1, shape[0] // 2), : max(1, shape[1] // 3)] = False  # a hole on the grid edge
    if full_domain:
        domain = np.ones(shape, dtype=bool)
    else:  # a disk: holes touch a domain edge that is not the grid edge
        centre_r, centre_c = (shape[0] - 1) / 2, (shape[1] - 1) / 2
        radius = 0.45 * max(shape)
        domain = (rows - centre_r) ** 2 + (cols - centre_c) ** 2 <= radius**2
    known[domain.nonzero()[0][0], domain.nonzero()[1][0]] = True  # data in the domain
    return np.where(known, height, np.nan), known, domain


@pytest.mark.parametrize("shape", [(1, 7), (6, 1), (2, 3), (9, 14), (17, 12)])
@pytest.mark.parametrize("full_domain", [True, False])
def test_system_matches_the_cell_by_cell_definition(shape, full_domain) -> None:
    height, known, domain = _case(shape, seed=sum(shape), full_domain=full_domain)
    unknown = domain & ~known
    assert unknown.any()
    system = laplace_system(height, unknown, domain)
    expected_matrix, expected_rhs = _reference_system(np.where(known, height, 0.0), unknown, domain)
    np.testing.assert_array_equal(system.cells, np.flatnonzero(unknown))  # row-major numbering
    np.testing.assert_array_equal(system.dense(), expected_matrix)
    np.testing.assert_allclose(system.rhs, expected_rhs, rtol=0, atol=1e-12)
    values = np.random.default_rng(1).normal(size=len(system.cells))
    np.testing.assert_allclose(system.matrix() @ values, expected_matrix @ values, atol=1e-12)


def _scipy_solution(height: np.ndarray, known: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """The same equations solved by SuperLU, from the cell-by-cell definition."""
    unknown = domain & ~known
    matrix, rhs = _reference_system(np.where(known, height, 0.0), unknown, domain)
    out = np.where(known, height, np.nan)
    out[unknown] = sparse_linalg.spsolve(sparse.csc_matrix(matrix), rhs)
    return out


@pytest.mark.parametrize("full_domain", [True, False])
@pytest.mark.parametrize("order", ["C", "F"])
@pytest.mark.parametrize("shape", [(17, 23), (41, 57)])  # a dense solve; conjugate gradients
def test_fill_satisfies_the_equations_to_rounding(full_domain, order, shape) -> None:
    height, known, domain = _case(shape, seed=3, full_domain=full_domain)
    height, known, domain = (np.asarray(a, order=order) for a in (height, known, domain))
    filled = membrane_fill(height, known, domain)
    unknown = domain & ~known
    np.testing.assert_array_equal(filled[known], height[known])
    assert np.all(np.isnan(filled[~known & ~domain]))
    assert np.all(np.isfinite(filled[unknown]))
    rhs = laplace_system(height, unknown, domain).rhs
    residual = _harmonic_residual(filled, unknown, domain)
    assert np.linalg.norm(residual) <= 1.01e-10 * np.linalg.norm(rhs)
    np.testing.assert_allclose(filled, _scipy_solution(height, known, domain), atol=1e-8)


def test_iterative_fill_satisfies_the_equations_to_solver_tolerance() -> None:
    height, known, domain = _case((301, 257), seed=5, full_domain=False)
    unknown = domain & ~known
    assert unknown.sum() > 30_000  # the looser tolerance, warm-started from the coarse level
    filled = membrane_fill(height, known, domain)
    assert np.all(np.isfinite(filled[unknown]))
    rhs = laplace_system(height, unknown, domain).rhs
    residual = _harmonic_residual(filled, unknown, domain)
    assert np.linalg.norm(residual) <= 1.01e-5 * np.linalg.norm(rhs)  # slack: rounding


def test_nothing_to_fill_returns_the_known_heights() -> None:
    known = np.ones((3, 4), dtype=bool)
    known[0, 0] = False
    domain = known.copy()  # the one unknown cell lies outside the domain
    height = np.arange(12.0).reshape(3, 4)
    filled = membrane_fill(height, known, domain)
    np.testing.assert_array_equal(filled, np.where(known, height, np.nan))


def test_a_domain_cell_cut_off_from_data_gives_nan_and_a_warning() -> None:
    known = np.zeros((5, 9), dtype=bool)
    known[:, 0] = True
    domain = np.zeros((5, 9), dtype=bool)
    domain[:, :4] = True
    domain[2, 6] = True  # no in-domain neighbour: an exactly singular system
    height = np.where(known, 2.0, np.nan)
    with pytest.warns(RuntimeWarning, match="no observed cell to fill from"):
        filled = membrane_fill(height, known, domain)
    assert np.all(np.isnan(filled[domain & ~known]))


def _deep_and_scattered(side: int, seed: int):
    """A square hole `side` cells wide (deep: algebraic multigrid) beside scattered unknown
    cells (shallow: conjugate gradients) in one grid."""
    rng = np.random.default_rng(seed)
    shape = (side + 40, 2 * side + 60)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    height = 1.0 + 0.3 * np.sin(rows / 9.0) + 0.2 * np.cos(cols / 7.0)
    known = rng.random(shape) < 0.6
    known[:, side + 20 :] = True
    known[20 : 20 + side, 20 : 20 + side] = True
    known[20 : 20 + side, side + 40 : 2 * side + 40] = False  # the deep hole
    return np.where(known, height, np.nan), known, np.ones(shape, dtype=bool)


def test_a_deep_hole_is_solved_to_rounding_by_multigrid_beside_scattered_cells() -> None:
    height, known, domain = _deep_and_scattered(200, seed=7)
    unknown = domain & ~known
    deep, cut_off = _classify_holes(known, domain, unknown)
    assert deep.sum() == 200 * 200 and not cut_off.any()  # the square alone is deep
    assert unknown.sum() > 30_000  # the old path stopped at a 1e-5 residual here
    filled = membrane_fill(height, known, domain)
    np.testing.assert_array_equal(filled[known], height[known])
    assert np.all(np.isfinite(filled[unknown]))
    rhs = laplace_system(height, unknown, domain).rhs
    residual = _harmonic_residual(filled, unknown, domain)
    assert np.linalg.norm(residual) <= 1.01e-10 * np.linalg.norm(rhs)
    # each part on its own, too: the scattered cells' fill is not hidden by the hole's
    shallow = unknown & ~deep
    residual_grid = np.zeros(unknown.shape)
    residual_grid[unknown] = residual
    shallow_rhs = laplace_system(height, shallow, domain & ~deep).rhs
    assert np.linalg.norm(residual_grid[shallow]) <= 1.01e-10 * np.linalg.norm(shallow_rhs)


@pytest.mark.parametrize("full_domain", [True, False])
def test_multigrid_fill_matches_a_direct_solve(full_domain) -> None:
    height, known, domain = _case((90, 97), seed=11, full_domain=full_domain)
    known[10:70, 12:72] = False  # 30 cells deep: multigrid
    unknown = domain & ~known
    deep, _ = _classify_holes(known, domain, unknown)
    assert deep.sum() > 3000
    filled = membrane_fill(height, known, domain)
    # SuperLU on the equations (laplace_system is checked cell by cell above)
    system = laplace_system(np.where(known, height, 0.0), unknown, domain)
    expected = np.where(known, height, np.nan)
    np.put(expected, system.cells, sparse_linalg.spsolve(system.matrix().tocsc(), system.rhs))
    np.testing.assert_allclose(filled, expected, atol=1e-8)


def _classified_by_depth(known: np.ndarray, domain: np.ndarray, unknown: np.ndarray):
    """The deep holes by their definition: each hole's depth from the chessboard distance
    transform; deep if 24 or more, and 30,000 cells or fewer or no more than 5 x depth**2."""
    from scipy import ndimage

    distance = ndimage.distance_transform_cdt(~(known & domain), metric="chessboard")
    labels, count = ndimage.label(unknown)
    deep = np.zeros(unknown.shape, dtype=bool)
    for hole in range(1, count + 1):
        cells = labels == hole
        depth = int(distance[cells].max())
        size = int(cells.sum())
        if depth >= 24 and (size <= 30_000 or size <= 5 * depth**2):
            deep |= cells
    return deep


@pytest.mark.parametrize(
    "shape, hole, expect_deep",
    [
        ((90, 97), (slice(10, 70), slice(12, 72)), True),  # small and deep
        ((60, 60), (slice(5, 50), slice(5, 50)), False),  # 23 cells deep: not deep
        ((60, 60), (slice(5, 52), slice(5, 52)), True),  # 24 cells deep
        ((420, 420), (slice(10, 410), slice(10, 30)), False),  # 8,000 cells, 10 deep
        ((420, 420), (slice(10, 410), slice(10, 410)), True),  # 160,000 cells: compact
        ((30, 1300), (slice(0, 30), slice(20, 1280)), True),  # 37,800, deep to the grid edge
        ((110, 1300), (slice(0, 100), slice(20, 1280)), False),  # 126,000, 50 deep: spread
    ],
)
def test_deep_holes_are_those_of_their_definition(shape, hole, expect_deep) -> None:
    rng = np.random.default_rng(3)
    known = rng.random(shape) < 0.6
    rows, cols = hole
    ring = (slice(max(rows.start - 1, 0), rows.stop + 1), slice(cols.start - 1, cols.stop + 1))
    known[ring] = True  # the hole's depth is set by its own size
    known[hole] = False
    for domain in (np.ones(shape, dtype=bool), rng.random(shape) < 0.97):
        unknown = domain & ~known
        deep, cut_off = _classify_holes(known, domain, unknown)
        assert np.array_equal(deep, _classified_by_depth(known, domain, unknown) & ~cut_off)
        assert np.any(deep[hole]) == expect_deep


def test_a_large_cut_off_part_gives_nan_and_a_warning_and_the_rest_is_filled() -> None:
    shape = (60, 60)
    known = np.zeros(shape, dtype=bool)
    known[:, 0] = True
    domain = np.zeros(shape, dtype=bool)
    domain[:, :30] = True
    domain[10:50, 40:] = True  # an island of the region with no observed cell
    height = np.where(known, 1.0 + np.arange(60.0)[:, None] / 60.0, np.nan)
    unknown = domain & ~known
    with pytest.warns(RuntimeWarning, match="no observed cell to fill from"):
        filled = membrane_fill(height, known, domain)
    island = unknown & (np.arange(60) >= 40)[None, :]
    assert island.sum() == 800 and np.all(np.isnan(filled[island]))
    rest = unknown & ~island
    assert np.all(np.isfinite(filled[rest]))
    residual = _harmonic_residual(np.where(island, 0.0, filled), rest, domain & ~island)
    rhs = laplace_system(height, rest, domain & ~island).rhs
    assert np.linalg.norm(residual) <= 1.01e-10 * np.linalg.norm(rhs)
