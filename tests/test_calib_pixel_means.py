"""Pooled captures averaged per pixel (`pixel_means`): the noise shrinks, the surface stays."""

from __future__ import annotations

import numpy as np

from silo_agent.calibrate import pixel_means

SIGMA = 0.02  # m: depth noise along the ray
INTRINSICS = {"width": 240, "height": 160, "fx": 400.0, "fy": 400.0, "ppx": 119.5, "ppy": 79.5}


def _plane_capture(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """Every pixel of a plane seen at 50 deg incidence, 3 m away, with depth noise along each
    ray, deprojected as a D455 does: (points, the plane's unit normal, its offset)."""
    k = INTRINSICS
    u, v = np.meshgrid(np.arange(k["width"]), np.arange(k["height"]))
    rays = np.column_stack(
        [(u.ravel() - k["ppx"]) / k["fx"], (v.ravel() - k["ppy"]) / k["fy"], np.ones(u.size)]
    )
    normal = np.array([0.0, np.sin(np.radians(50)), -np.cos(np.radians(50))])
    offset = -3.0 * np.cos(np.radians(50))
    depth = offset / (rays @ normal)  # exact hit (z = depth: the rays have unit z)
    noisy = depth + SIGMA * rng.standard_normal(len(depth))
    return (rays * noisy[:, None]).astype(np.float32).astype(np.float64), normal, offset


def test_pooled_captures_are_averaged_per_pixel() -> None:
    rng = np.random.default_rng(1)
    captures = [_plane_capture(rng) for _ in range(4)]
    normal, offset = captures[0][1], captures[0][2]
    one = captures[0][0] @ normal - offset
    pooled, _ = pixel_means(np.vstack([c[0] for c in captures]), None, INTRINSICS)
    assert len(pooled) == INTRINSICS["width"] * INTRINSICS["height"]  # one point per pixel
    off = pooled @ normal - offset
    # four captures: the noise off the plane halves (a thicker slab would not shrink)
    assert np.sqrt(np.mean(off**2)) < 0.6 * np.sqrt(np.mean(one**2))
    assert abs(np.mean(off)) < 0.05 * SIGMA


def test_colours_are_averaged_with_their_pixels() -> None:
    rng = np.random.default_rng(2)
    points = [_plane_capture(rng)[0] for _ in range(2)]
    colours = [
        np.full((len(p), 3), value, dtype=np.uint8)
        for p, value in zip(points, (10, 30), strict=True)
    ]
    colours[1][0] = (200, 200, 200)  # pixel 0 of the second capture
    averaged, mixed = pixel_means(np.vstack(points), np.vstack(colours), INTRINSICS)
    assert mixed is not None and mixed.dtype == np.uint8 and len(mixed) == len(averaged)
    first_pixel = np.argmin(np.linalg.norm(averaged - (points[0][0] + points[1][0]) / 2, axis=1))
    assert tuple(mixed[first_pixel]) == (105, 105, 105)
    assert np.count_nonzero(np.all(mixed == 20, axis=1)) == len(mixed) - 1
