"""Leveling from the floor: each camera's own view of the plane z = floor_z (RANSAC, then
weighted least squares, the foot of any pile left out) sets its pitch, roll and height.

`calibrate --floor` and per-scan leveling (`level_scan`, `calibration.level`) share it; it
lives beside the reconstruction, not in the calibration tool, so that `process` and the
daemon level scans with numpy and scipy alone."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from silo_agent.config import CalibrationConfig
from silo_agent.grid.rigid import UP, about, pose_change, rotation_between
from silo_agent.scan import CameraCloud, Scan, Site, with_extrinsics

FLOOR_RANSAC_DISTANCE_M = 0.02  # inlier distance of the RANSAC floor plane
FLOOR_RANSAC_TRIALS = 1000  # candidate planes, each through 3 random points
FLOOR_RANSAC_SCORED = 2000  # points on which every candidate is scored (a fixed random subset)
FLOOR_REFINE_DISTANCE_M = 0.03  # points this close to the RANSAC plane refine it (least squares)
FLOOR_MIN_POINTS = 500  # fewer floor inliers: this camera does not see the floor
FLOOR_ROUGH_MARGIN_M = 0.001  # the float32 pre-test's band is this much wider than floor_band_m
FLOOR_CELL_M = 0.10  # cells in which a pile's foot is told from the floor
FLOOR_OFF_M = 0.015  # a cell whose points average this far off the plane is not floor
FLOOR_MARGIN_CELLS = 2  # and neither are its neighbours this many cells around
FLOOR_OFF_SIGMAS = 2.0  # ... or, further away, this many times one point's noise at its depth
ICP_SIGMA_M, ICP_SIGMA_PER_M2 = 0.002, 0.002  # point noise model: 2 mm + 2 mm x depth²


def fit_plane(
    points: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(Weighted) least-squares plane: (unit normal pointing up, weighted centroid)."""
    w = np.ones(len(points)) if weights is None else weights
    centroid = (w[:, None] * points).sum(axis=0) / w.sum()
    _, _, vt = np.linalg.svd(np.sqrt(w)[:, None] * (points - centroid), full_matrices=False)
    normal = vt[2]
    return (normal if normal[2] >= 0 else -normal), centroid


def level_on_plane(
    extrinsic: np.ndarray, normal: np.ndarray, centroid: np.ndarray, floor_z: float
) -> np.ndarray:
    """`extrinsic` corrected so that the floor it sees (plane `normal`, `centroid`, silo frame)
    becomes the plane z = floor_z: tilt about the floor's centroid, then lift."""
    correction = about(
        rotation_between(normal, UP), centroid, np.array([0.0, 0.0, floor_z - centroid[2]])
    )
    return correction @ extrinsic


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


def floor_points(
    camera: CameraCloud, extrinsic: np.ndarray, floor_z: float, settings: CalibrationConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The camera's points (silo frame) that are floor, and their expected noise (m).

    A RANSAC plane among the points near `floor_z` within `floor_max_range_m` of the camera;
    then only points near that plane and away from anything standing on it. The foot of a pile
    lies within a few cm of the floor: left in, it lifted the plane by 3 mm and tilted it 0.2 deg
    towards the pile (measured on the simulator's cone).
    """
    from scipy import ndimage

    # every scan outside bins runs this (per-scan leveling): a camera with too few points near
    # the floor's height (a wall camera at range, grain wall to wall) is let go after one
    # float32 product with its points (a millimetre's margin covers float32's rounding)
    raw = camera.points
    rough_z = raw @ extrinsic[2, :3].astype(np.float32) + np.float32(extrinsic[2, 3] - floor_z)
    rough_band = np.float32(settings.floor_band_m + FLOOR_ROUGH_MARGIN_M)
    if np.count_nonzero(np.abs(rough_z) <= rough_band) < FLOOR_MIN_POINTS:
        return np.empty((0, 3)), np.empty(0)
    del rough_z
    near = np.einsum("ij,ij->i", raw, raw) <= np.float32(settings.floor_max_range_m) ** 2
    cam = raw[near].astype(np.float64)
    z = cam @ extrinsic[2, :3] + extrinsic[2, 3]
    band = np.abs(z - floor_z) <= settings.floor_band_m
    if np.count_nonzero(band) < FLOOR_MIN_POINTS:
        return np.empty((0, 3)), np.empty(0)
    pts = cam @ extrinsic[:3, :3].T + extrinsic[:3, 3]
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


def floor_leveled(
    camera: CameraCloud, extrinsic: np.ndarray, floor_z: float, settings: CalibrationConfig
) -> tuple[np.ndarray | None, int]:
    """`extrinsic` leveled on the floor the camera sees (`floor_points`, a weighted
    `fit_plane`, `level_on_plane`) and how many floor points set it; None for the pose when
    they are fewer than FLOOR_MIN_POINTS (the camera does not see the floor)."""
    found, sigma = floor_points(camera, extrinsic, floor_z, settings)
    if len(found) < FLOOR_MIN_POINTS:
        return None, len(found)
    normal, centroid = fit_plane(found, 1 / sigma**2)
    return level_on_plane(extrinsic, normal, centroid, floor_z), len(found)


def level_scan(
    scan: Scan, settings: CalibrationConfig, site: Site | None = None
) -> tuple[Scan, dict[str, tuple[float, float]], list[str]]:
    """Per-scan leveling (`calibration.level`): every camera that sees bare floor is leveled
    on it as `calibrate --floor` levels it (`floor_leveled`).

    Why: a camera's height and tilt errors bias the whole floor it sees (0.1 deg and 3 mm per
    camera made the accuracy bench's four-view scans 1.5 % off, against 0.3 % placed exactly),
    and the floor is a reference in every scan that shows some of it. A camera that sees no
    floor, or would move more than `refine_max_deg` / `refine_max_m` (thin level grain taken
    for the floor, or a camera knocked: recalibrate), keeps its extrinsic, with a note. Only
    a flat floor at `floor_z` levels: not sloping ground (`base = "boundary"`) or a bin's
    hopper or sloped floor. Returns the scan, each leveled camera's correction (degrees,
    metres) and the notes."""
    site = site or scan.site
    if site.base != "floor" or (site.bin is not None and site.bin.floor != "flat"):
        return scan, {}, ["level: the floor is not a flat plane at floor_z; extrinsics unchanged"]
    poses = {c.serial: c.extrinsic for c in scan.cameras}
    corrections: dict[str, tuple[float, float]] = {}
    notes = []
    for camera in scan.cameras:
        leveled, _ = floor_leveled(camera, camera.extrinsic, site.floor_z, settings)
        if leveled is None:
            notes.append(f"level: {camera.serial} sees no bare floor; extrinsic unchanged")
            continue
        degrees, metres = pose_change(camera.extrinsic, leveled)
        if degrees > settings.refine_max_deg or metres > settings.refine_max_m:
            notes.append(
                f"level: {camera.serial} would turn {degrees:.2f} deg / move "
                f"{metres * 1000:.0f} mm, beyond refine_max_*; extrinsic unchanged (recalibrate?)"
            )
            continue
        poses[camera.serial] = leveled
        corrections[camera.serial] = (degrees, metres)
    if not corrections:
        return scan, {}, notes
    return replace(scan, cameras=with_extrinsics(scan.cameras, poses)), corrections, notes
