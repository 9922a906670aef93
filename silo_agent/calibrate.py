"""Camera calibration: leveling, relative registration, bounded corrections, drift detection.

Why: most of the residual volume error comes from camera placement. Hand-set extrinsics leave
the two surfaces of an overlap apart, and a 1 cm height bias over a whole floor is a large
volume. One calibration scan (or several taken one after another, pooled by `pool_scans` so
that their noise averages) fixes that:

1. *Relative registration*: point-to-plane ICP between every two cameras whose views overlap,
   starting from the configured extrinsics, all pairs solved as one least-squares pose graph
   with a prior on each camera's correction (open3d's multiway registration drifted along
   what the scene cannot show), so that all overlaps agree at once.
2. *Leveling* fixes what relative registration cannot see (the whole rig's tilt and height):
   with `floor`, each camera's own view of the floor plane `z = floor_z` (RANSAC, then least
   squares) sets its pitch, roll and height; otherwise the cameras' accelerometer gravity
   vectors set the rig's tilt and the configured (mounted) heights its height.
3. The rig's yaw and plan position, which a floor and gravity cannot see, stay where the
   configured extrinsics put them on average (2-D Procrustes on the camera poses). Its scale,
   which a scan without walls hardly shows, comes from measured camera spacings
   (`[[calibration.spacing]]`) when the config has them: one more residual per spacing in
   the joint registration.
4. A camera corrected by more than `max_correction_deg` / `max_correction_m` is refused with the
   reason: a calibration that far off is a wrong scan or a wrong config, not a small error.

Every scan measures the height disagreement of camera pairs (reconstruct/residual.py); the
`DriftMonitor` / `drift_step` here turns those and the gravity vectors into raise/clear events
(pure: previous state in, new state and events out), for the alarm publisher to forward.

open3d is imported lazily by the function that needs it (voxels and normals for ICP); the
rest is numpy and scipy.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np

from silo_agent.config import (
    CalibrationConfig,
    Config,
    ConfigError,
    SpacingConfig,
    parse_config,
)
from silo_agent.geometry import euler_from_rotation, gravity_angle_deg
from silo_agent.reconstruct.grid import Grid, fuse_and_crop
from silo_agent.reconstruct.residual import PairResidual, registration_residuals
from silo_agent.scan import CameraCloud, Scan, Site

UP = np.array([0.0, 0.0, 1.0])
FLOOR_RANSAC_DISTANCE_M = 0.02  # inlier distance of the RANSAC floor plane
FLOOR_RANSAC_TRIALS = 1000  # candidate planes, each through 3 random points
FLOOR_RANSAC_SCORED = 2000  # points on which every candidate is scored (a fixed random subset)
FLOOR_REFINE_DISTANCE_M = 0.03  # points this close to the RANSAC plane refine it (least squares)
FLOOR_MIN_POINTS = 500  # fewer floor inliers: this camera does not see the floor
FLOOR_CELL_M = 0.10  # cells in which a pile's foot is told from the floor
FLOOR_OFF_M = 0.015  # a cell whose points average this far off the plane is not floor
FLOOR_MARGIN_CELLS = 2  # and neither are its neighbours this many cells around
FLOOR_OFF_SIGMAS = 2.0  # ... or, further away, this many times one point's noise at its depth
ICP_ITERATIONS = 15  # per scale
ICP_SCALES = (1.0, 0.5, 0.25)  # correspondence distance, as fractions of icp_max_distance_m
ICP_MIN_INCIDENCE_COS = 0.17  # points seen more grazing than ~80 deg are not used
ICP_NORMAL_AGREEMENT_COS = 0.9  # correspondences whose normals differ by more (~25 deg) are
# two faces of a ridge or apex, seen from opposite sides: not the same surface
ICP_LEVEL_NORMAL_COS = 0.97  # normals within ~14 deg of vertical: a level surface
LOCKED_PRECISION = 1e12  # prior precision of a degree of freedom the floor already fixed
ICP_DATA_WEIGHT = 1.0  # data information scale (neighbouring points are not independent)
ICP_SIGMA_M, ICP_SIGMA_PER_M2 = 0.002, 0.002  # point noise model: 2 mm + 2 mm x depth²


class CalibrationError(Exception):
    """Calibration impossible or refused; the message says which camera and why."""


class SerialMismatch(CalibrationError):
    """The scan's cameras and the config's are not the same set of serials."""


class ScanMismatch(CalibrationError):
    """Calibration scans to be pooled are not of the same cameras or the same site."""


# ---------------------------------------------------------------- small geometry


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction `a` to direction `b`."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
        axis = np.cross(a, helper)
        s = np.linalg.norm(axis)
    k = axis / s
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    angle = np.arctan2(s, c)
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def pose_change(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """(degrees turned, metres moved) of a camera between two camera->silo transforms."""
    relative = after[:3, :3] @ before[:3, :3].T
    cosine = np.clip((np.trace(relative) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosine))), float(np.linalg.norm(after[:3, 3] - before[:3, 3]))


def about(rotation: np.ndarray, pivot: np.ndarray, shift: np.ndarray | None = None) -> np.ndarray:
    """4x4 silo-frame transform: rotate about `pivot`, then translate by `shift`."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = pivot - rotation @ pivot + (0 if shift is None else shift)
    return out


def fit_plane(points: np.ndarray, weights: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(Weighted) least-squares plane: (unit normal pointing up, weighted centroid)."""
    w = np.ones(len(points)) if weights is None else weights
    centroid = (w[:, None] * points).sum(axis=0) / w.sum()
    _, _, vt = np.linalg.svd(np.sqrt(w)[:, None] * (points - centroid), full_matrices=False)
    normal = vt[2]
    return (normal if normal[2] >= 0 else -normal), centroid


def level_on_plane(extrinsic: np.ndarray, normal: np.ndarray, centroid: np.ndarray,
                   floor_z: float) -> np.ndarray:
    """`extrinsic` corrected so that the floor it sees (plane `normal`, `centroid`, silo frame)
    becomes the plane z = floor_z: tilt about the floor's centroid, then lift."""
    correction = about(rotation_between(normal, UP), centroid,
                       np.array([0.0, 0.0, floor_z - centroid[2]]))
    return correction @ extrinsic


def planar_procrustes(moved: Sequence[np.ndarray], reference: Sequence[np.ndarray]) -> np.ndarray:
    """The rotation about z and x/y shift (4x4) that best puts the `moved` camera poses back on
    the `reference` ones (centres and 1 m ahead of them): the rig's yaw and plan position,
    which neither a floor nor gravity can observe, stay where the configuration had them."""
    def marks(poses: Sequence[np.ndarray]) -> np.ndarray:
        out = []
        for pose in poses:
            ahead = pose[:3, 2].copy()
            ahead[2] = 0.0
            norm = np.linalg.norm(ahead)
            out.append(pose[:2, 3])
            if norm > 1e-6:
                out.append(pose[:2, 3] + ahead[:2] / norm)
        return np.array(out)

    src, dst = marks(moved), marks(reference)
    sc, dc = src.mean(axis=0), dst.mean(axis=0)
    h = (src - sc).T @ (dst - dc)
    angle = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = np.cos(angle), np.sin(angle)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = dc - out[:2, :2] @ sc
    return out


# ---------------------------------------------------------------- results


@dataclass(frozen=True)
class CameraCalibration:
    """One camera's extrinsic before and after calibration, and how it was found."""

    serial: str
    before: np.ndarray
    after: np.ndarray
    leveled_by: Literal["floor", "gravity", "none"]
    floor_points: int = 0
    gravity_angle_before_deg: float | None = None
    gravity_angle_after_deg: float | None = None

    @property
    def correction(self) -> tuple[float, float]:
        """(degrees, metres) the calibration moved this camera."""
        return pose_change(self.before, self.after)

    def euler(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """The new extrinsic in the paper's form: (rotate_deg, translate_m)."""
        t = self.after[:3, 3]
        return euler_from_rotation(self.after[:3, :3]), (float(t[0]), float(t[1]), float(t[2]))

    def to_json(self) -> dict[str, Any]:
        degrees, metres = self.correction
        rotate, translate = self.euler()
        return {
            "serial": self.serial, "extrinsic": self.after.tolist(),
            "rotate_deg": list(rotate), "translate_m": list(translate),
            "previous_extrinsic": self.before.tolist(),
            "correction_deg": degrees, "correction_m": metres, "leveled_by": self.leveled_by,
            "floor_points": self.floor_points,
            "gravity_angle_before_deg": self.gravity_angle_before_deg,
            "gravity_angle_after_deg": self.gravity_angle_after_deg,
        }  # fmt: skip


@dataclass(frozen=True)
class PairRegistration:
    """Pairwise ICP of camera `b` onto camera `a`."""

    a: str
    b: str
    fitness: float  # share of b's points with a correspondence in a
    rmse_m: float
    used: bool
    note: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"a": self.a, "b": self.b, "fitness": self.fitness, "rmse_m": self.rmse_m,
                "used": self.used, "note": self.note}


@dataclass(frozen=True)
class SpacingCheck:
    """A measured camera spacing (`[[calibration.spacing]]`) against the distance between the
    two cameras' origins (extrinsic translations) before and after calibration."""

    a: str
    b: str
    measured_m: float
    sigma_m: float
    before_m: float
    after_m: float

    def to_json(self) -> dict[str, Any]:
        return {"a": self.a, "b": self.b, "measured_m": self.measured_m, "sigma_m": self.sigma_m,
                "before_m": self.before_m, "after_m": self.after_m,
                "error_before_m": self.before_m - self.measured_m,
                "error_after_m": self.after_m - self.measured_m}  # fmt: skip


@dataclass
class Calibration:
    cameras: list[CameraCalibration]
    pairs: list[PairRegistration]
    residual_before: dict[str, PairResidual]
    residual_after: dict[str, PairResidual]
    notes: list[str] = field(default_factory=list)
    spacings: list[SpacingCheck] = field(default_factory=list)

    def extrinsics(self) -> dict[str, np.ndarray]:
        return {c.serial: c.after for c in self.cameras}

    def to_json(self) -> dict[str, Any]:
        keys = sorted(set(self.residual_before) | set(self.residual_after))
        return {
            "cameras": [c.to_json() for c in self.cameras],
            "pairs": [p.to_json() for p in self.pairs],
            "registration_residual_m": {
                k: {"before": _median(self.residual_before, k),
                    "after": _median(self.residual_after, k)} for k in keys
            },
            "spacing": [s.to_json() for s in self.spacings],
            "notes": self.notes,
        }  # fmt: skip

    def describe(self) -> str:
        lines = ["camera            moved (deg, mm)  leveled   new rotate_deg / translate_m"]
        for c in self.cameras:
            degrees, metres = c.correction
            rotate, translate = c.euler()
            lines.append(
                f"{c.serial:<17} {degrees:6.3f} {metres * 1000:7.1f}   {c.leveled_by:<8}  "
                f"[{', '.join(f'{v:.4f}' for v in rotate)}] / "
                f"[{', '.join(f'{v:.4f}' for v in translate)}]"
            )
            for row in c.after[:3]:
                lines.append(" " * 18 + "  ".join(f"{v:+.6f}" for v in row))
        lines.append("pair                    residual before -> after (median, MAD, cells; mm)")
        for k in sorted(set(self.residual_before) | set(self.residual_after)):
            lines.append(f"{k:<23} {_fmt(self.residual_before.get(k))} -> "
                         f"{_fmt(self.residual_after.get(k))}")  # fmt: skip
        for p in self.pairs:
            state = "used" if p.used else "not used"
            lines.append(f"ICP {p.a}|{p.b}: fitness {p.fitness:.2f}, rmse "
                         f"{p.rmse_m * 1000:.1f} mm, {state}{': ' + p.note if p.note else ''}")
        if self.spacings:
            lines.append("spacing                 measured (±sigma) | before -> after (error; mm)")
        for sp in self.spacings:
            lines.append(
                f"{sp.a + '|' + sp.b:<23} {sp.measured_m * 1000:8.1f} (±{sp.sigma_m * 1000:.1f}) | "
                f"{sp.before_m * 1000:8.1f} ({(sp.before_m - sp.measured_m) * 1000:+.1f}) -> "
                f"{sp.after_m * 1000:8.1f} ({(sp.after_m - sp.measured_m) * 1000:+.1f})")
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


def _median(residuals: Mapping[str, PairResidual], key: str) -> float | None:
    r = residuals.get(key)
    return None if r is None else r.median_m


def _fmt(r: PairResidual | None) -> str:
    if r is None:
        return "       (no overlap)     "
    return f"{r.median_m * 1000:+6.1f} ±{r.mad_m * 1000:4.1f} ({r.cells:5d})"


# ---------------------------------------------------------------- measurements


def with_extrinsics(cameras: Sequence[CameraCloud], poses: Mapping[str, np.ndarray]
                    ) -> list[CameraCloud]:  # fmt: skip
    """The clouds with their extrinsics replaced (cameras missing from `poses` unchanged)."""
    return [replace(c, extrinsic=np.asarray(poses.get(c.serial, c.extrinsic), dtype=float))
            for c in cameras]  # fmt: skip


def scan_residuals(cameras: Sequence[CameraCloud], site: Site, grid_step: float,
                   settings: CalibrationConfig) -> dict[str, PairResidual]:
    """Registration residual of every camera pair, as every scan measures it."""
    grid = Grid.over(site.region, grid_step)
    fused = fuse_and_crop(list(cameras), site, grid)
    return registration_residuals(fused, grid, [c.serial for c in cameras],
                                  settings.residual_min_points, settings.residual_min_cells)


def gravity_of(camera: CameraCloud) -> np.ndarray | None:
    """The camera's IMU gravity vector (`gravity` in scan.json: down, camera axes), if any."""
    value = camera.extra.get("gravity")
    if value is None:
        return None
    vector = np.asarray(value, dtype=float)
    if vector.shape != (3,) or not np.all(np.isfinite(vector)) or np.linalg.norm(vector) < 1e-6:
        return None
    return vector


def gravity_angles(cameras: Sequence[CameraCloud]) -> dict[str, float]:
    """Per camera: degrees between its measured gravity and the vertical its extrinsic claims."""
    out = {}
    for camera in cameras:
        gravity = gravity_of(camera)
        if gravity is not None:
            out[camera.serial] = gravity_angle_deg(gravity, camera.extrinsic)
    return out


def point_sigma(depth: np.ndarray) -> np.ndarray:
    """Expected depth noise (m) of points at camera-frame depth `depth` (D455: grows with z²)."""
    return ICP_SIGMA_M + ICP_SIGMA_PER_M2 * depth * depth


def ransac_plane(points: np.ndarray, distance: float) -> np.ndarray | None:
    """The plane (unit normal pointing up, offset) that most of `points` lie within `distance`
    of; None when they all lie on one line. Seeded: the same points give the same plane, so one
    calibration scan gives one answer (open3d's `segment_plane` samples on several threads and
    did not: the floor height varied by up to 0.08 mm between two calls)."""
    rng = np.random.default_rng(0)
    trios = points[rng.integers(0, len(points), size=(FLOOR_RANSAC_TRIALS, 3))]
    normals = np.cross(trios[:, 1] - trios[:, 0], trios[:, 2] - trios[:, 0])
    length = np.linalg.norm(normals, axis=1)
    usable = length > 0
    if not usable.any():
        return None
    normals = normals[usable] / length[usable, None]
    normals *= np.where(normals[:, 2] < 0, -1.0, 1.0)[:, None]
    offsets = -np.einsum("ij,ij->i", normals, trios[usable, 0])
    scored = points[rng.choice(len(points), min(len(points), FLOOR_RANSAC_SCORED), replace=False)]
    support = (np.abs(scored @ normals.T + offsets) <= distance).sum(axis=0)
    best = int(np.argmax(support))
    return np.append(normals[best], offsets[best])


def floor_points(camera: CameraCloud, extrinsic: np.ndarray, floor_z: float,
                 settings: CalibrationConfig) -> tuple[np.ndarray, np.ndarray]:
    """The camera's points (silo frame) that are floor, and their expected noise (m).

    A RANSAC plane among the points near `floor_z` within `floor_max_range_m` of the camera;
    then only points near that plane and away from anything standing on it. The foot of a pile
    lies within a few cm of the floor: left in, it lifted the plane by 3 mm and tilted it 0.2 deg
    towards the pile (measured on the simulator's cone).
    """
    from scipy import ndimage

    cam = camera.points.astype(np.float64)
    cam = cam[np.linalg.norm(cam, axis=1) <= settings.floor_max_range_m]
    pts = cam @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    band = np.abs(pts[:, 2] - floor_z) <= settings.floor_band_m
    if band.sum() < FLOOR_MIN_POINTS:
        return np.empty((0, 3)), np.empty(0)
    plane = ransac_plane(pts[band], FLOOR_RANSAC_DISTANCE_M)
    if plane is None:
        return np.empty((0, 3)), np.empty(0)
    height = pts @ plane[:3] + plane[3]  # above the RANSAC plane
    if np.count_nonzero(np.abs(height[band]) <= FLOOR_RANSAC_DISTANCE_M) < FLOOR_MIN_POINTS:
        return np.empty((0, 3)), np.empty(0)
    # cells (FLOOR_CELL_M) whose points stand off the floor on average, and their margin: a
    # pile's foot. Further than the noise could put them (it is correlated over a cell, so one
    # point's sigma), on either side: at range noise alone makes such cells, and dropping only
    # the high ones at 1.5 cm left every wall camera's floor low (1.5 mm on average)
    low = pts[:, :2].min(axis=0)
    ij = np.floor((pts[:, :2] - low) / FLOOR_CELL_M).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 1)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    count = np.bincount(flat, minlength=shape[0] * shape[1])
    total = np.bincount(flat, height, shape[0] * shape[1])
    depth = np.bincount(flat, cam[:, 2], shape[0] * shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        limit = np.maximum(FLOOR_OFF_M, FLOOR_OFF_SIGMAS * point_sigma(depth / count))
        off = (np.abs(total / count) > limit).reshape(shape)
    off = ndimage.binary_dilation(off, iterations=FLOOR_MARGIN_CELLS)
    keep = (np.abs(height) <= FLOOR_REFINE_DISTANCE_M) & ~off.ravel()[flat]
    return pts[keep], point_sigma(cam[keep, 2])


# ---------------------------------------------------------------- registration


@dataclass(frozen=True)
class _View:
    """One camera's down-sampled cloud for registration, in its own camera frame."""

    points: np.ndarray  # (N, 3) camera frame
    normals: np.ndarray  # (N, 3) camera frame
    sigma: np.ndarray  # (N,) expected depth noise of each point (m)
    tree: Any  # scipy cKDTree over `points`


def _view(camera: CameraCloud, extrinsic: np.ndarray, site: Site,
          settings: CalibrationConfig, drop_level: bool = False) -> _View:
    """Voxel down-sampled (open3d) cloud under the ceiling, with normals and a noise model."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    cam = camera.points.astype(np.float64)
    if site.ceiling_z is not None:
        z = cam @ extrinsic[2, :3] + extrinsic[2, 3]
        cam = cam[z <= site.ceiling_z]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cam))
    cloud = cloud.voxel_down_sample(settings.icp_voxel_m)
    cloud.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=4 * settings.icp_voxel_m, max_nn=30)
    )
    points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
    # grazing views are where depth noise along the ray smears a surface sideways (silhouettes,
    # the far side of an apex): their points and normals are not to be trusted
    incidence = np.abs(np.einsum("ij,ij->i", points, normals)) / np.linalg.norm(points, axis=1)
    keep = incidence >= ICP_MIN_INCIDENCE_COS
    if drop_level:  # level surfaces only constrain tilt and height: useless to a leveled camera
        keep &= np.abs(normals @ extrinsic[2, :3]) < ICP_LEVEL_NORMAL_COS
    points, normals = points[keep], normals[keep]
    depth = points[:, 2]
    sigma = point_sigma(depth)
    return _View(points, normals, sigma, cKDTree(points))


def _skew(v: np.ndarray) -> np.ndarray:
    """Rows of cross-product matrices: _skew(v)[k] @ w == cross(v[k], w)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _small_motion(omega: np.ndarray, tau: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """4x4 silo-frame transform: rotate by the rotation vector `omega` about `pivot`, shift."""
    angle = float(np.linalg.norm(omega))
    rotation = np.eye(3) if angle < 1e-15 else rotation_between_axis(omega / angle, angle)
    return about(rotation, pivot, tau)


def rotation_between_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by `angle` (rad) about unit `axis`."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def register(cameras: Sequence[CameraCloud], poses: Mapping[str, np.ndarray], site: Site,
             settings: CalibrationConfig, prior_deg: float, prior_m: float,
             leveled: frozenset[str] = frozenset(),
             spacings: Sequence[SpacingConfig] = (),
             ) -> tuple[dict[str, np.ndarray], list[PairRegistration]]:  # fmt: skip
    """Relative registration of all cameras at once: joint point-to-plane ICP over every
    overlapping pair (each pair's correspondences, both ways), a pose graph solved as one
    least-squares problem per iteration, with a Gaussian prior of `prior_deg` / `prior_m` on
    each camera's correction (about its own centre).

    The prior matters: a cone on a floor leaves the rotation about the cone's axis unobservable,
    and plain pairwise ICP (and open3d's pose graph fed with it) wandered several degrees along
    it; with the prior, directions the data cannot see stay where the configuration put them.
    Cameras in `leveled` (already on the floor) keep their pitch, roll and height: only their
    yaw and plan position are solved for, from the surfaces that are not level.

    `spacings` (measured camera-to-camera distances) add one residual each,
    (|c_a - c_b| - distance_m) / sigma_m between the two cameras' origins, to the same normal
    equations: it acts on the two centres along their baseline only (not on rotations), so a
    pair with no usable overlap is moved apart or together, half each when their priors are
    equal, and a leveled camera's locked height stays. It holds the rig's scale, which scenes
    without walls do not show.
    Returns silo-frame corrections D per camera (new extrinsic = D @ old) and per-pair stats.
    """
    serials = [c.serial for c in cameras]
    n = len(cameras)
    index = {s: k for k, s in enumerate(serials)}  # calibrate() checked the spacings' serials
    links = [(index[sp.a], index[sp.b], sp.distance_m, sp.sigma_m) for sp in spacings]
    locked = len(leveled) == n
    views = [_view(c, poses[c.serial], site, settings, drop_level=locked) for c in cameras]
    current = [np.asarray(poses[s], dtype=float).copy() for s in serials]
    pair_list = [(i, j) for i in range(n) for j in range(i + 1, n)]
    overlap = {p: 0.0 for p in pair_list}
    rmse = {p: 0.0 for p in pair_list}
    prior = np.tile(np.r_[np.full(3, 1 / np.radians(prior_deg) ** 2),
                          np.full(3, 1 / prior_m**2)], n)  # fmt: skip
    for k, serial in enumerate(serials):
        if serial in leveled:
            prior[[6 * k, 6 * k + 1, 6 * k + 5]] = LOCKED_PRECISION
    coarse = settings.icp_max_distance_m * ICP_SCALES[0]
    for i, j in pair_list:  # overlap: share of either camera's points near the other's
        scratch_h, scratch_g = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
        overlap[(i, j)] = max(_accumulate(views, current, i, j, coarse, scratch_h, scratch_g)[0],
                              _accumulate(views, current, j, i, coarse, scratch_h, scratch_g)[0])
    active = [p for p in pair_list if overlap[p] >= settings.min_overlap]
    for scale in ICP_SCALES if active or links else ():
        distance = settings.icp_max_distance_m * scale
        for _ in range(ICP_ITERATIONS):
            h = np.diag(prior).astype(float)
            g = np.zeros(6 * n)
            # accumulated correction so far, penalised by the prior (relative to the start)
            for k in range(n):
                omega, tau = _correction_params(poses[serials[k]], current[k])
                g[6 * k: 6 * k + 6] -= prior[6 * k: 6 * k + 6] * np.r_[omega, tau]
            for i, j in active:
                for a, b in ((i, j), (j, i)):  # points of b onto surface of a
                    stats = _accumulate(views, current, a, b, distance, h, g)
                    if a == i:
                        rmse[(i, j)] = stats[1]
            for a, b, measured, sigma in links:
                _add_spacing(current, a, b, measured, sigma, h, g)
            step = np.linalg.solve(h, g)
            for k in range(n):
                delta = _small_motion(step[6 * k: 6 * k + 3], step[6 * k + 3: 6 * k + 6],
                                      current[k][:3, 3])
                current[k] = delta @ current[k]
            if np.max(np.abs(step[0::6])) < 1e-7 and np.max(np.abs(step)) < 1e-6:
                break
    pairs = []
    for i, j in pair_list:
        used = overlap[(i, j)] >= settings.min_overlap
        note = "" if used else f"overlap {overlap[(i, j)]:.2f} below min_overlap"
        pairs.append(PairRegistration(serials[i], serials[j], overlap[(i, j)], rmse[(i, j)],
                                      used, note))
    corrections = {s: current[k] @ np.linalg.inv(poses[s]) for k, s in enumerate(serials)}
    return corrections, pairs


def _add_spacing(poses: Sequence[np.ndarray], a: int, b: int, measured: float, sigma: float,
                 h: np.ndarray, g: np.ndarray) -> None:
    """Add the residual (|c_a - c_b| - measured) / sigma of two camera origins to (h, g).

    d r / d tau_a = u / sigma and d r / d tau_b = -u / sigma, u the unit baseline from b to a;
    the rotations (about each camera's own centre) do not move the centres."""
    diff = poses[a][:3, 3] - poses[b][:3, 3]
    length = float(np.linalg.norm(diff))
    if length < 1e-9:
        return  # two cameras configured at one point: no direction to push along
    u = diff / length
    w = 1.0 / sigma**2
    block = w * np.outer(u, u)
    ta, tb = slice(6 * a + 3, 6 * a + 6), slice(6 * b + 3, 6 * b + 6)
    h[ta, ta] += block
    h[tb, tb] += block
    h[ta, tb] -= block
    h[tb, ta] -= block
    g[ta] -= w * (length - measured) * u
    g[tb] += w * (length - measured) * u


def _correction_params(start: np.ndarray, now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vector and centre shift taking a camera from `start` to `now`."""
    relative = now[:3, :3] @ start[:3, :3].T
    angle = np.arccos(np.clip((np.trace(relative) - 1) / 2, -1.0, 1.0))
    if angle < 1e-12:
        omega = np.zeros(3)
    else:
        omega = angle / (2 * np.sin(angle)) * np.array([
            relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0],
            relative[1, 0] - relative[0, 1]])
    return omega, now[:3, 3] - start[:3, 3]


def _accumulate(views: Sequence[_View], poses: Sequence[np.ndarray], a: int, b: int,
                distance: float, h: np.ndarray, g: np.ndarray) -> tuple[float, float]:
    """Add the point-to-plane terms of camera b's points against camera a's surface to the
    normal equations (h, g). Returns (overlap share of b's points, weighted rmse)."""
    vb, va = views[b], views[a]
    pa, pb = poses[a], poses[b]
    world_b = vb.points @ pb[:3, :3].T + pb[:3, 3]
    in_a = (world_b - pa[:3, 3]) @ pa[:3, :3]
    dist, idx = va.tree.query(in_a, distance_upper_bound=distance)
    hit = np.isfinite(dist)
    share = float(hit.mean()) if len(hit) else 0.0
    # the two points must be the same surface: normals that agree (not both faces of a ridge)
    found = np.flatnonzero(hit)
    agree = np.abs(np.einsum("ij,ij->i", vb.normals[found] @ pb[:3, :3].T,
                             va.normals[idx[found]] @ pa[:3, :3].T)) >= ICP_NORMAL_AGREEMENT_COS
    hit[found[~agree]] = False
    if hit.sum() < 6:
        return share, 0.0
    q = world_b[hit]
    target = va.points[idx[hit]] @ pa[:3, :3].T + pa[:3, 3]
    normal = va.normals[idx[hit]] @ pa[:3, :3].T
    r = np.einsum("ij,ij->i", normal, q - target)
    sigma2 = vb.sigma[hit] ** 2 + va.sigma[idx[hit]] ** 2
    tukey = np.clip(1 - (r / distance) ** 2, 0, None) ** 2
    w = ICP_DATA_WEIGHT * tukey / sigma2
    # d r / d (omega_b, tau_b) = ((q - c_b) x n, n); for a the same with a minus sign
    jb = np.hstack([np.cross(q - pb[:3, 3], normal), normal])
    ja = -np.hstack([np.cross(target - pa[:3, 3], normal), normal])
    blocks = ((b, jb), (a, ja))
    for k, jk in blocks:
        g[6 * k: 6 * k + 6] -= jk.T @ (w * r)
        for m, jm in blocks:
            h[6 * k: 6 * k + 6, 6 * m: 6 * m + 6] += (jk * w[:, None]).T @ jm
    rms = float(np.sqrt(np.sum(w * r * r) / np.sum(w) if np.sum(w) > 0 else 0.0))
    return share, rms


# ---------------------------------------------------------------- calibration


def calibrate(
    scan: Scan, settings: CalibrationConfig, *, floor: bool, site: Site | None = None,
    start: Mapping[str, np.ndarray] | None = None, grid_step: float = 0.02,
) -> Calibration:  # fmt: skip
    """Calibrate the scan's cameras from `start` (default: the scan's extrinsics).

    `floor`: the floor plane z = floor_z is visible around the grain (empty floor, or a pile on
    it); it levels each camera and sets its height. Without it the cameras' gravity vectors
    (if present) level the rig and the configured heights stay. Raises `CalibrationError` when
    a camera would move more than the configured bound.
    """
    site = site or scan.site
    cameras = scan.cameras
    if len(cameras) == 0:
        raise CalibrationError("the scan has no cameras")
    configured = {c.serial: np.asarray((start or {}).get(c.serial, c.extrinsic), dtype=float)
                  for c in cameras}  # fmt: skip
    unknown = sorted({s for sp in settings.spacing for s in (sp.a, sp.b) if s not in configured})
    if unknown:
        raise CalibrationError(f"calibration.spacing names cameras not in the scan: "
                               f"{', '.join(unknown)}")
    notes: list[str] = []
    poses = dict(configured)

    # 1. leveling and height from the floor, camera by camera
    leveled: dict[str, Literal["floor", "gravity", "none"]] = {s: "none" for s in poses}
    counts: dict[str, int] = {s: 0 for s in poses}
    if floor:
        for c in cameras:
            found, sigma = floor_points(c, poses[c.serial], site.floor_z, settings)
            counts[c.serial] = len(found)
            if len(found) < FLOOR_MIN_POINTS:
                notes.append(f"{c.serial}: sees no floor (z = {site.floor_z:g}) within "
                             f"{settings.floor_max_range_m:g} m; not leveled by the floor")
                continue
            normal, centroid = fit_plane(found, 1 / sigma**2)
            poses[c.serial] = level_on_plane(poses[c.serial], normal, centroid, site.floor_z)
            leveled[c.serial] = "floor"

    # 2. relative registration (yaw and plan position only, where the floor leveled)
    pairs: list[PairRegistration] = []
    if len(cameras) > 1:
        fixed = frozenset(s for s, how in leveled.items() if how == "floor")
        corrections, pairs = register(cameras, poses, site, settings,
                                      settings.prior_deg, settings.prior_m, fixed,
                                      settings.spacing)
        linked = {s for p in pairs if p.used for s in (p.a, p.b)}
        for c in cameras:
            if c.serial not in linked:
                spaced = any(c.serial in (sp.a, sp.b) for sp in settings.spacing)
                notes.append(f"{c.serial}: no overlap with another camera; not registered"
                             + (" (only its measured spacing moved it)" if spaced else ""))
        poses = {s: corrections[s] @ poses[s] for s in poses}

    # 3. without a floor: the rig levelled by gravity, or kept as configured on average
    with_gravity = [c for c in cameras if gravity_of(c) is not None]
    if any(v == "floor" for v in leveled.values()):
        pass  # cameras without floor keep the level the graph gave them relative to the others
    elif with_gravity:
        linked = {s for p in pairs if p.used for s in (p.a, p.b)}
        for c in with_gravity:
            if c.serial not in linked:  # alone: its own accelerometer levels it, about its centre
                down = poses[c.serial][:3, :3] @ gravity_of(c)
                poses[c.serial] = about(rotation_between(down, -UP),
                                        poses[c.serial][:3, 3]) @ poses[c.serial]
        downs = [poses[c.serial][:3, :3] @ gravity_of(c) for c in with_gravity]
        mean_down = np.mean([d / np.linalg.norm(d) for d in downs], axis=0)
        pivot = np.mean([poses[s][:3, 3] for s in poses], axis=0)
        tilt = about(rotation_between(mean_down, -UP), pivot)
        height = np.mean([configured[s][2, 3] for s in poses])
        for s in poses:
            poses[s] = tilt @ poses[s]
        lift = height - np.mean([poses[s][2, 3] for s in poses])
        for s in poses:
            poses[s][2, 3] += lift
            leveled[s] = "gravity"
    else:
        notes.append("no floor and no gravity vector: the rig's tilt and height are kept as "
                     "configured (on average)")
        g = _rigid_fit([poses[s] for s in poses], [configured[s] for s in poses])
        poses = {s: g @ p for s, p in poses.items()}

    # 4. plan position and yaw stay as configured, on average
    if any(v != "none" for v in leveled.values()):
        g = planar_procrustes([poses[s] for s in poses], [configured[s] for s in poses])
        poses = {s: g @ p for s, p in poses.items()}

    # 5. bounded correction
    too_far = []
    for s in poses:
        degrees, metres = pose_change(configured[s], poses[s])
        if degrees > settings.max_correction_deg or metres > settings.max_correction_m:
            too_far.append(f"{s} would turn {degrees:.2f} deg and move {metres * 1000:.0f} mm")
    if too_far:
        raise CalibrationError(
            "refused: " + "; ".join(too_far) + f" (bounds: calibration.max_correction_deg = "
            f"{settings.max_correction_deg:g}, max_correction_m = {settings.max_correction_m:g})."
            " Check that the scan is of this installation, that the serials are the right "
            "cameras and that the configured extrinsics are roughly right"
        )

    before_clouds = with_extrinsics(cameras, configured)
    after_clouds = with_extrinsics(cameras, poses)
    angles_before, angles_after = gravity_angles(before_clouds), gravity_angles(after_clouds)
    return Calibration(
        cameras=[
            CameraCalibration(c.serial, configured[c.serial], poses[c.serial], leveled[c.serial],
                              counts[c.serial], angles_before.get(c.serial),
                              angles_after.get(c.serial))
            for c in cameras
        ],
        pairs=pairs,
        residual_before=scan_residuals(before_clouds, site, grid_step, settings),
        residual_after=scan_residuals(after_clouds, site, grid_step, settings),
        notes=notes,
        spacings=[SpacingCheck(sp.a, sp.b, sp.distance_m, sp.sigma_m,
                               _spacing(configured, sp), _spacing(poses, sp))
                  for sp in settings.spacing],
    )  # fmt: skip


def _spacing(poses: Mapping[str, np.ndarray], spacing: SpacingConfig) -> float:
    """Distance between the origins (extrinsic translations) of the spacing's two cameras."""
    return float(np.linalg.norm(poses[spacing.a][:3, 3] - poses[spacing.b][:3, 3]))


def _rigid_fit(moved: Sequence[np.ndarray], reference: Sequence[np.ndarray]) -> np.ndarray:
    """3-D Kabsch on camera centres and the points 1 m ahead of them (4x4, silo frame)."""
    src = np.array([p for pose in moved for p in (pose[:3, 3], pose[:3, 3] + pose[:3, 2])])
    dst = np.array([p for pose in reference for p in (pose[:3, 3], pose[:3, 3] + pose[:3, 2])])
    sc, dc = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - sc).T @ (dst - dc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = dc - rotation @ sc
    return out


def refine(scan: Scan, settings: CalibrationConfig, site: Site | None = None
           ) -> tuple[Scan, list[str]]:  # fmt: skip
    """Per-scan refinement (`calibration.refine`): a bounded relative registration on the
    overlaps, the rig kept where its extrinsics put it on average. Returns the scan unchanged,
    with a note, when a camera would move more than `refine_max_deg` / `refine_max_m`."""
    site = site or scan.site
    if len(scan.cameras) < 2:
        return scan, []
    poses = {c.serial: c.extrinsic for c in scan.cameras}
    corrections, pairs = register(scan.cameras, poses, site, settings,
                                  settings.refine_max_deg / 2, settings.refine_max_m / 2)
    if not any(p.used for p in pairs):
        return scan, ["refine: no overlapping pair; extrinsics unchanged"]
    moved = {s: corrections[s] @ poses[s] for s in poses}
    g = _rigid_fit(list(moved.values()), list(poses.values()))
    moved = {s: g @ p for s, p in moved.items()}
    for s in poses:
        degrees, metres = pose_change(poses[s], moved[s])
        if degrees > settings.refine_max_deg or metres > settings.refine_max_m:
            return scan, [f"refine: {s} would turn {degrees:.2f} deg / move {metres * 1000:.0f} "
                          "mm, beyond refine_max_*; extrinsics unchanged (recalibrate?)"]
    return replace(scan, cameras=with_extrinsics(scan.cameras, moved)), []


# ---------------------------------------------------------------- matching a config


def start_poses(config: Config, scan: Scan) -> dict[str, np.ndarray]:
    """Configured extrinsics of the scan's cameras, matched by serial (a sim camera placed by
    its `view` keeps the scan's). Unmatched serials, either way, are an error naming them."""
    configured = {c.serial: c for c in config.cameras}
    in_scan = [c.serial for c in scan.cameras]
    unknown = [s for s in in_scan if s not in configured]
    missing = [s for s in configured if s not in in_scan]
    if unknown or missing:
        parts = []
        if unknown:
            parts.append(f"scan cameras not in the config: {', '.join(unknown)}")
        if missing:
            parts.append(f"config cameras not in the scan: {', '.join(missing)}")
        raise SerialMismatch("serials do not match: " + "; ".join(parts))
    out = {}
    for camera in scan.cameras:
        matrix = configured[camera.serial].extrinsic_matrix()
        out[camera.serial] = camera.extrinsic if matrix is None else matrix
    return out


def _site_difference(a: Site, b: Site) -> str | None:
    """What differs between two sites' geometry (None: the same)."""
    if a.floor_z != b.floor_z:
        return f"floor_z {b.floor_z:g} instead of {a.floor_z:g}"
    if a.ceiling_z != b.ceiling_z:
        return f"ceiling_z {b.ceiling_z} instead of {a.ceiling_z}"
    if a.base != b.base:
        return f"base {b.base!r} instead of {a.base!r}"
    if a.region.shape != b.region.shape or not np.allclose(a.region, b.region, atol=1e-9):
        return "a different region"
    return None


def pixel_means(points: np.ndarray, colors: np.ndarray | None,
                intrinsics: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray | None]:
    """Camera-frame points (and colours) of several captures averaged per pixel: one point
    per pixel ray, the pixel found from the intrinsics the points were deprojected with."""
    cam = points.astype(np.float64)
    u = np.rint(cam[:, 0] / cam[:, 2] * intrinsics["fx"] + intrinsics["ppx"]).astype(np.int64)
    v = np.rint(cam[:, 1] / cam[:, 2] * intrinsics["fy"] + intrinsics["ppy"]).astype(np.int64)
    u -= u.min()
    _, inverse, count = np.unique((v - v.min()) * (u.max() + 1) + u, return_inverse=True,
                                  return_counts=True)  # fmt: skip

    def mean(values: np.ndarray) -> np.ndarray:
        return np.column_stack([np.bincount(inverse, values[:, k])
                                for k in range(values.shape[1])]) / count[:, None]  # fmt: skip

    averaged = mean(cam).astype(points.dtype)
    if colors is None:
        return averaged, None
    return averaged, np.rint(mean(colors.astype(np.float64))).astype(colors.dtype)


def pool_scans(scans: Sequence[Scan], names: Sequence[str] | None = None) -> Scan:
    """One scan holding, per camera, the per-pixel mean of all `scans`' points (several
    calibration scans of the same installation taken one after another: same cameras, same
    site, nothing moved).

    Each camera's points are averaged per pixel over the scans (its own frame; the pixel from
    its intrinsics), so the floor fit and the registration see one capture with N frames'
    independent noise averaged (one frame's floor fit is off by 0.1-0.2 mm of height, about
    1.5 pp of a pile's volume per mm). Pooled as N times the points instead, the noise along
    the rays stayed as wide: the floor fit's cut at 3 cm and the registration's 2 cm voxels
    then saw a thicker surface, not a sharper one (walled bay, four views, floor fitted on the
    true poses: +0.63 mm mean, 1.19 mm rms; per pixel: +0.01 mm, 0.50 mm; one scan: 1.40 mm
    rms). A camera without intrinsics has its points concatenated. The first scan gives the
    order, extrinsics, intrinsics and metadata; a camera's IMU gravity is the mean of its
    readings. Raises `ScanMismatch`, naming the scan (`names[k]`, default its scan id), when a
    scan's serials or site differ from the first one's.
    """
    if not scans:
        raise ScanMismatch("no calibration scan")
    labels = list(names) if names is not None else [s.scan_id for s in scans]
    first = scans[0]
    if len(scans) == 1:
        return first
    serials = [c.serial for c in first.cameras]
    for scan, label in zip(scans[1:], labels[1:], strict=True):
        own = [c.serial for c in scan.cameras]
        extra = [s for s in own if s not in serials]
        missing = [s for s in serials if s not in own]
        if extra or missing or len(own) != len(serials):
            parts = []
            if extra:
                parts.append(f"cameras not in {labels[0]}: {', '.join(extra)}")
            if missing:
                parts.append(f"cameras of {labels[0]} missing: {', '.join(missing)}")
            if not parts:
                parts.append("a camera serial repeated")
            raise ScanMismatch(f"{label}: not the same cameras as {labels[0]} ("
                               + "; ".join(parts) + "); pooled calibration scans must be of "
                               "the same installation")
        difference = _site_difference(first.site, scan.site)
        if difference is not None:
            raise ScanMismatch(f"{label}: site differs from {labels[0]}'s ({difference}); "
                               "pooled calibration scans must be of the same installation")
    cameras = []
    for camera in first.cameras:
        same = [next(c for c in scan.cameras if c.serial == camera.serial) for scan in scans]
        points = np.concatenate([c.points for c in same])
        colors = None
        if all(c.colors is not None for c in same):
            colors = np.concatenate([c.colors for c in same])
        if camera.intrinsics is not None:
            points, colors = pixel_means(points, colors, camera.intrinsics)
        extra = dict(camera.extra)
        gravities = [g for g in (gravity_of(c) for c in same) if g is not None]
        if gravities:
            extra["gravity"] = [float(v) for v in np.mean(gravities, axis=0)]
            extra.pop("gravity_angle_deg", None)  # of one reading; gravity_angles() recomputes
        extra["pooled_frames"] = len(same)
        cameras.append(replace(camera, points=points, colors=colors, extra=extra))
    return replace(first, cameras=cameras,
                   extra={**first.extra, "pooled_scans": [s.scan_id for s in scans]})


# ---------------------------------------------------------------- config rewrite


_TABLE = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\" -]+?)\s*\]\]?\s*(#.*)?$", re.MULTILINE)


def _value_end(text: str, start: int) -> int:
    """End offset of the TOML value starting at `start` (arrays may span lines, hold comments)."""
    depth, i = 0, start
    while i < len(text):
        ch = text[i]
        if ch in "\"'":
            close = text.find(ch, i + 1)
            i = len(text) if close < 0 else close + 1
            continue
        if ch == "#":
            newline = text.find("\n", i)
            i = len(text) if newline < 0 else newline
            continue
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
            if depth == 0:
                return i + 1
        elif ch == "\n" and depth == 0:
            return i
        i += 1
    return i


def _number(value: float) -> str:
    text = f"{value:.9f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _matrix_text(matrix: np.ndarray, indent: str) -> str:
    rows = [f"[{', '.join(_number(v) for v in row)}]" for row in matrix]
    pad = "\n" + indent + " " * len("extrinsic = [")
    return "extrinsic = [" + ("," + pad).join(rows) + "]"


def rewrite_config_text(text: str, poses: Mapping[str, np.ndarray]) -> str:
    """`text` with the extrinsics of the cameras in `poses` replaced, nothing else touched.

    Each camera keeps its form: a 4x4 `extrinsic` is rewritten as a matrix, a `rotate_deg` /
    `translate_m` pair in the paper's form; a camera with neither (a sim camera placed by its
    `view`) gets an `extrinsic` line after its serial. Comments stay, trailing ones too.
    """
    headers = list(_TABLE.finditer(text))
    spans = []  # (start, end) of every [[cameras]] table body
    for k, m in enumerate(headers):
        if m.group(0).strip().startswith("[[") and m.group(1).strip() == "cameras":
            end = headers[k + 1].start() if k + 1 < len(headers) else len(text)
            spans.append((m.end(), end))
    edits: list[tuple[int, int, str]] = []
    done = set()
    for start, end in spans:
        body = text[start:end]
        serial = re.search(r"^\s*serial\s*=\s*[\"']([^\"']+)[\"']", body, re.MULTILINE)
        if serial is None or serial.group(1) not in poses:
            continue
        pose = np.asarray(poses[serial.group(1)], dtype=float)
        done.add(serial.group(1))
        keys = {}
        for key in ("extrinsic", "rotate_deg", "translate_m"):
            m = re.search(rf"^([ \t]*){key}\s*=\s*", body, re.MULTILINE)
            if m is not None:
                keys[key] = (start + m.start(), _value_end(text, start + m.end()), m.group(1))
        if "extrinsic" in keys:
            a, b, indent = keys["extrinsic"]
            edits.append((a, b, indent + _matrix_text(pose, indent)))
        elif "rotate_deg" in keys or "translate_m" in keys:
            rotate = euler_from_rotation(pose[:3, :3])
            values = {"rotate_deg": rotate, "translate_m": tuple(pose[:3, 3])}
            for key, value in values.items():
                line = f"{key} = [{', '.join(_number(v) for v in value)}]"
                if key in keys:
                    a, b, indent = keys[key]
                    edits.append((a, b, indent + line))
                else:
                    other = keys["translate_m" if key == "rotate_deg" else "rotate_deg"]
                    edits.append((other[1], other[1], "\n" + other[2] + line))
        else:
            line_end = text.find("\n", start + serial.end())
            line_end = len(text) if line_end < 0 else line_end
            indent = re.match(r"[ \t]*", body[serial.start():]).group(0).lstrip("\n")
            edits.append((line_end, line_end, "\n" + indent + _matrix_text(pose, indent)))
    missing = sorted(set(poses) - done)
    if missing:
        raise CalibrationError(f"no [[cameras]] table with serial {', '.join(missing)}")
    for a, b, new in sorted(edits, reverse=True):
        text = text[:a] + new + text[b:]
    return text


def write_calibrated_config(path: Path, poses: Mapping[str, np.ndarray]) -> Path:
    """Rewrite the config file at `path` with the new extrinsics; keep the old one as a backup
    (`<name>.<UTC time>.bak`). The new text is validated before anything is written, and is
    written atomically. Returns the backup's path."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    new = rewrite_config_text(text, poses)
    import tomllib

    try:
        config = parse_config(tomllib.loads(new), f"{path} (rewritten)")
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{path}: the rewritten file is not valid TOML ({exc}); "
                               "nothing written") from None
    for camera in config.cameras:
        if camera.serial in poses:
            got = camera.extrinsic_matrix()
            if got is None or not np.allclose(got, poses[camera.serial], atol=1e-6):
                raise CalibrationError(f"{path}: the rewritten extrinsic of {camera.serial} does "
                                       "not read back; nothing written")
    backup = path.with_name(f"{path.name}.{datetime.now(UTC):%Y%m%dT%H%M%S%fZ}.bak")
    shutil.copy2(path, backup)
    fd, staging = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            out.write(new)
            out.flush()
            os.fsync(out.fileno())
        shutil.copymode(path, staging)
        os.replace(staging, path)
    except BaseException:
        Path(staging).unlink(missing_ok=True)
        raise
    return backup


# ---------------------------------------------------------------- drift


@dataclass(frozen=True)
class DriftEvent:
    """An alarm transition. `key` is stable per alarm: `"residual:<a>|<b>"` for a camera pair,
    `"gravity:<serial>"` for a camera whose IMU disagrees with its extrinsic."""

    kind: Literal["raised", "cleared"]
    key: str
    cameras: tuple[str, ...]
    value: float  # |median residual| (m) or gravity angle (deg) of the scan that decided
    threshold: float
    message: str

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "key": self.key, "cameras": list(self.cameras),
                "value": self.value, "threshold": self.threshold, "message": self.message}


@dataclass(frozen=True)
class DriftState:
    """What the detector remembers between scans: run lengths over / under the threshold per
    key (positive: scans in a row over, negative: in a row under) and the raised alarms."""

    runs: Mapping[str, int] = field(default_factory=dict)
    raised: frozenset[str] = frozenset()

    def to_json(self) -> dict[str, Any]:
        return {"runs": dict(self.runs), "raised": sorted(self.raised)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> DriftState:
        return cls({str(k): int(v) for k, v in data.get("runs", {}).items()},
                   frozenset(data.get("raised", ())))  # fmt: skip


def drift_step(
    state: DriftState,
    residuals: Mapping[str, PairResidual | float],
    gravity_deg: Mapping[str, float],
    settings: CalibrationConfig,
    gravity_tolerance_deg: Mapping[str, float] | float = 3.0,
) -> tuple[DriftState, list[DriftEvent]]:
    """One scan of the `calibration_drift` detector. Pure.

    - `residuals`: the scan's `registration_residual_m` (pair key -> median metres, or the
      `PairResidual`s of `Result.registration`);
    - `gravity_deg`: per camera, the angle between its IMU gravity and its extrinsic's vertical
      (`gravity_angles(scan.cameras)`, or `gravity_angle_deg` in scan.json);
    - `gravity_tolerance_deg`: per camera (its `[[cameras]] gravity_tolerance_deg`) or one value.

    An alarm is raised when its value is over the threshold (`drift_threshold_m` for |median|,
    the tolerance for gravity) in `drift_consecutive` scans in a row, and cleared after as
    many scans in a row under it. A key absent from a scan (pair without overlap, camera without
    IMU, failed camera) keeps its run and alarm unchanged: no news is not good news.
    """
    n = settings.drift_consecutive
    values: dict[str, tuple[float, float, tuple[str, ...], str]] = {}
    for key, r in residuals.items():
        median = r.median_m if isinstance(r, PairResidual) else float(r)
        a, _, b = key.partition("|")
        values[f"residual:{key}"] = (
            abs(median), settings.drift_threshold_m, (a, b),
            f"cameras {a} and {b} disagree by {median * 1000:+.1f} mm on the height of the "
            "cells both see",
        )
    for serial, angle in gravity_deg.items():
        tolerance = (gravity_tolerance_deg if isinstance(gravity_tolerance_deg, (int, float))
                     else gravity_tolerance_deg.get(serial, 3.0))  # fmt: skip
        values[f"gravity:{serial}"] = (
            float(angle), float(tolerance), (serial,),
            f"camera {serial}'s accelerometer is {angle:.2f} deg off the tilt its extrinsic "
            "claims",
        )
    runs = dict(state.runs)
    raised = set(state.raised)
    events: list[DriftEvent] = []
    for key, (value, threshold, cameras, text) in sorted(values.items()):
        over = value > threshold
        previous = runs.get(key, 0)
        run = (max(previous, 0) + 1) if over else (min(previous, 0) - 1)
        runs[key] = run
        if over and run >= n and key not in raised:
            raised.add(key)
            events.append(DriftEvent("raised", key, cameras, value, threshold,
                                     f"{text} ({n} scans in a row): recalibrate "
                                     "(silo-agent calibrate)"))
        elif not over and -run >= n and key in raised:
            raised.discard(key)
            events.append(DriftEvent("cleared", key, cameras, value, threshold,
                                     f"{text}: back within {threshold:g}"))
    return DriftState(runs, frozenset(raised)), events


class DriftMonitor:
    """A stateful wrapper of `drift_step` for the daemon: `update(result, scan)` per scan."""

    def __init__(self, settings: CalibrationConfig,
                 gravity_tolerance_deg: Mapping[str, float] | float = 3.0,
                 state: DriftState | None = None) -> None:  # fmt: skip
        self.settings = settings
        self.gravity_tolerance_deg = gravity_tolerance_deg
        self.state = state or DriftState()

    @classmethod
    def for_config(cls, config: Config, state: DriftState | None = None) -> DriftMonitor:
        tolerances = {c.serial: c.gravity_tolerance_deg for c in config.cameras}
        return cls(config.calibration, tolerances, state)

    def update(self, residuals: Mapping[str, PairResidual | float],
               cameras: Sequence[CameraCloud] = ()) -> list[DriftEvent]:
        """Feed one scan (`Result.registration` and the scan's cameras); the events it causes."""
        self.state, events = drift_step(self.state, residuals, gravity_angles(cameras),
                                        self.settings, self.gravity_tolerance_deg)
        return events

    @property
    def active(self) -> frozenset[str]:
        return self.state.raised
