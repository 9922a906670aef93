"""A virtual D455: pixel rays, the stereo noise model, the artefacts a real one shows.

The error is a stereo camera's: Gaussian in disparity (sub-pixel matching error, the same at
every range), so the depth RMS grows with the square of depth (sigma_z = z² · subpixel /
(f · baseline)) and the depth error is skewed (the mean depth reads sigma_z² / z far), half of
its variance spatially correlated (the blobs a block matcher makes), then quantised to
the depth unit like the camera's uint16 image. Invalid pixels are those a D455 also loses: the
left band only the left imager sees (width f · baseline / z px), grazing surfaces, random holes,
and anything outside the depth range.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.ndimage import gaussian_filter
from scipy.special import ndtri

from silo_agent.base.d455 import BASELINE_M, CORRELATED_SHARE, CORRELATION_PX, SUBPIXEL_PX
from silo_agent.sim.mesh import CLUTTER, GRAIN
from silo_agent.sim.raycast import Hits, Raycaster

CLUTTER_RGB = (140, 140, 148)
LIGHT = np.array([0.3, -0.4, 0.87]) / np.linalg.norm([0.3, -0.4, 0.87])


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float

    def to_json(self) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "ppx": self.ppx,
            "ppy": self.ppy,
        }


def d455_intrinsics(focal_px: float, width: int = 848, height: int = 480) -> Intrinsics:
    """Depth intrinsics of a D455 at `width` x `height` (focal length given at 848 px wide)."""
    f = focal_px * width / 848
    return Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)


@dataclass(frozen=True)
class NoiseModel:
    subpixel: float = SUBPIXEL_PX
    baseline_m: float = BASELINE_M
    correlated_share: float = CORRELATED_SHARE
    correlation_px: float = CORRELATION_PX  # Gaussian sigma of the correlated part
    depth_unit_m: float = 0.001  # D455 default depth unit
    min_depth_m: float = 0.4
    max_depth_m: float = 6.0
    grazing_start_deg: float = 75.0  # drop-out probability rises from 0 here ...
    grazing_end_deg: float = 88.0  # ... to 1 here (angle between ray and surface normal)
    hole_fraction: float = 0.01  # pixels lost in blobs
    speckle_fraction: float = 0.002  # isolated lost pixels
    surface_factor: float = 1.0  # real surfaces: 3-5x the ideal target's error at 2.5-5x
    mixed_edge_share: float = 0.0  # pixels along a depth edge reading a depth in between

    def rms_m(self, depth_m: np.ndarray | float, focal_px: float) -> np.ndarray | float:
        """The D455 depth RMS error at a depth."""
        ideal = np.square(depth_m) * self.subpixel / (focal_px * self.baseline_m)
        return self.surface_factor * ideal


@dataclass
class Frame:
    """One depth frame (and optional aligned colour) as the camera would deliver it."""

    depth: np.ndarray  # (H, W) uint16, 0 = invalid
    depth_unit_m: float
    intrinsics: Intrinsics
    color: np.ndarray | None = None  # (H, W, 3) uint8, aligned to depth

    def points(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Valid pixels deprojected to the camera optical frame, and their colours."""
        v, u = np.nonzero(self.depth)
        z = self.depth[v, u].astype(np.float64) * self.depth_unit_m
        k = self.intrinsics
        points = np.column_stack([(u - k.ppx) / k.fx * z, (v - k.ppy) / k.fy * z, z])
        colors = self.color[v, u] if self.color is not None else None
        return points.astype(np.float32), colors


def pixel_rays(k: Intrinsics) -> np.ndarray:
    """(H*W, 3) camera-frame ray per pixel, scaled to z = 1 so the hit parameter is depth."""
    u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
    return np.stack([(u - k.ppx) / k.fx, (v - k.ppy) / k.fy, np.ones(u.shape)], -1).reshape(-1, 3)


def unit_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Gaussian-smoothed white noise with unit variance everywhere (periodic, so stationary)."""
    radius = int(4 * sigma_px + 0.5)
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma_px) ** 2)
    kernel /= kernel.sum()
    std = float(np.sum(kernel**2))  # 2-D separable: (sum k²)² is the variance, this its root
    return gaussian_filter(rng.standard_normal(shape), sigma_px, mode="wrap") / std


def noisy_depth(
    depth: np.ndarray, focal_px: float, noise: NoiseModel, rng: np.random.Generator
) -> np.ndarray:
    """True depth (H, W) (0: nothing hit) with the stereo error along each pixel's ray.

    A block matcher errs in disparity, not depth: inverse depth gets Gaussian noise of a
    constant RMS (`rms_m` at 1 m), so to first order depth gets `rms_m(z)`, and beyond it the
    skew of depth = f * baseline / disparity (at 9 m, 2.5x the ideal target, the mean depth
    reads 2 cm far). A disparity pushed to zero or below is no match: depth 0, invalid."""
    share = noise.correlated_share
    unit = np.sqrt(1 - share) * rng.standard_normal(depth.shape)
    unit += np.sqrt(share) * unit_noise(rng, depth.shape, noise.correlation_px)
    hit = depth > 0
    with np.errstate(divide="ignore"):
        inverse = np.where(hit, 1.0 / np.where(hit, depth, 1.0), 0.0)
    inverse -= float(noise.rms_m(1.0, focal_px)) * unit  # first order: depth + rms_m(z) * unit
    matched = hit & (inverse > 0)
    return np.where(matched, 1.0 / np.where(matched, inverse, 1.0), 0.0)


def dropouts(
    depth: np.ndarray,
    cos_incidence: np.ndarray,
    k: Intrinsics,
    noise: NoiseModel,
    rng: np.random.Generator,
) -> np.ndarray:
    """Pixels a D455 returns no depth for (True = invalid)."""
    columns = np.arange(k.width)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        band = columns < k.fx * noise.baseline_m / depth
    angle = np.degrees(np.arccos(np.clip(cos_incidence, 0.0, 1.0)))
    span = noise.grazing_end_deg - noise.grazing_start_deg
    grazing = rng.random(depth.shape) < np.clip((angle - noise.grazing_start_deg) / span, 0, 1)
    blobs = unit_noise(rng, depth.shape, 3.0) > ndtri(1 - noise.hole_fraction)
    speckle = rng.random(depth.shape) < noise.speckle_fraction
    out_of_range = ~((depth >= noise.min_depth_m) & (depth <= noise.max_depth_m))
    return band | grazing | blobs | speckle | out_of_range


def shade(hits: Hits, grain_rgb: tuple[int, int, int], shape: tuple[int, int]) -> np.ndarray:
    """Colour image: material colour times a Lambert term of the surface normal."""
    lambert = 0.35 + 0.65 * np.abs(hits.normals @ LIGHT)
    base = np.zeros((len(hits.t), 3))
    base[hits.material == GRAIN] = grain_rgb
    base[hits.material == CLUTTER] = CLUTTER_RGB
    rgb = np.clip(base * lambert[:, None], 0, 255).astype(np.uint8)
    return rgb.reshape(*shape, 3)


@dataclass(frozen=True)
class Trace:
    """What a camera's pixels see, noise-free: traced once, exposed into any number of frames."""

    depth: np.ndarray  # (H, W) true depth, inf where nothing is hit
    cos_incidence: np.ndarray  # (H, W) |cos| of the angle between ray and surface normal
    intrinsics: Intrinsics
    color: np.ndarray | None  # (H, W, 3) uint8


def trace(
    raycaster: Raycaster,
    pose: np.ndarray,
    k: Intrinsics,
    grain_rgb: tuple[int, int, int] | None = None,
) -> Trace:
    """Cast every pixel's ray from `pose` (the camera's true camera->silo transform)."""
    rays = pixel_rays(k)
    # einsum, not `rays @ R.T`: BLAS is slow on an inner dimension of 3
    directions = np.einsum("nj,ij->ni", rays, pose[:3, :3])
    origins = np.broadcast_to(pose[:3, 3], directions.shape)
    hits = raycaster.cast(origins, directions)
    shape = (k.height, k.width)
    norm = np.sqrt(np.einsum("ni,ni->n", rays, rays))  # a rotation keeps each ray's length
    cos_incidence = np.abs(np.einsum("ni,ni->n", hits.normals, directions)) / norm
    color = shade(hits, grain_rgb, shape) if grain_rgb is not None else None
    # the rays have unit z, so the hit parameter is the depth
    return Trace(hits.t.astype(np.float64).reshape(shape), cos_incidence.reshape(shape), k, color)


EDGE_JUMP = 0.05  # a depth edge: the 3 x 3 depth range above this share of the depth


def mixed_edges(depth: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """A stereo matcher's window straddling a depth edge (a robot's rim against the grain
    behind it) returns a depth in between for some pixels along it: `share` of the edge
    pixels read a uniform mix of the nearest and farthest depth around them."""
    finite = np.isfinite(depth)
    near = ndimage.minimum_filter(np.where(finite, depth, np.inf), 3)
    far = ndimage.maximum_filter(np.where(finite, depth, 0.0), 3)
    edge = finite & np.isfinite(near) & (far - near > EDGE_JUMP * near)
    mixed = edge & (rng.random(depth.shape) < share)
    with np.errstate(invalid="ignore"):  # inf - inf where no surface is near: not mixed
        return np.where(mixed, near + rng.random(depth.shape) * (far - near), depth)


def expose(seen: Trace, noise: NoiseModel, rng: np.random.Generator) -> Frame:
    """One noisy, quantised depth frame with the D455's invalid pixels."""
    hit = np.isfinite(seen.depth)
    true = seen.depth
    if noise.mixed_edge_share > 0:
        true = mixed_edges(true, noise.mixed_edge_share, rng)
    measured = noisy_depth(np.where(hit, true, 0.0), seen.intrinsics.fx, noise, rng)
    measured[~hit] = np.inf
    invalid = dropouts(measured, seen.cos_incidence, seen.intrinsics, noise, rng)
    counts = np.rint(np.where(invalid, 0.0, measured) / noise.depth_unit_m)
    depth = np.clip(counts, 0, np.iinfo(np.uint16).max).astype(np.uint16)
    return Frame(depth, noise.depth_unit_m, seen.intrinsics, seen.color)


def render(
    raycaster: Raycaster,
    pose: np.ndarray,
    k: Intrinsics,
    noise: NoiseModel,
    rng: np.random.Generator,
    grain_rgb: tuple[int, int, int] | None = None,
) -> Frame:
    """One frame seen from `pose` (the camera's true camera->silo transform)."""
    return expose(trace(raycaster, pose, k, grain_rgb), noise, rng)
