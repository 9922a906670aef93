"""Relative registration: joint point-to-plane ICP over every overlapping camera pair, solved
as one least-squares pose graph with a prior on each camera's correction.

open3d is imported lazily by the function that needs it (voxels and normals); the rest is
numpy and scipy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from silo_agent.config import CalibrationConfig, SpacingConfig
from silo_agent.grid.rigid import about, rotation_between_axis
from silo_agent.reconstruct.level import point_sigma
from silo_agent.scan import CameraCloud, Site

ICP_ITERATIONS = 15  # per scale
ICP_SCALES = (1.0, 0.5, 0.25)  # correspondence distance, as fractions of icp_max_distance_m
ICP_MIN_INCIDENCE_COS = 0.17  # points seen more grazing than ~80 deg are not used
ICP_NORMAL_AGREEMENT_COS = 0.9  # correspondences whose normals differ by more (~25 deg) are
# two faces of a ridge or apex, seen from opposite sides: not the same surface
ICP_LEVEL_NORMAL_COS = 0.97  # normals within ~14 deg of vertical: a level surface
LOCKED_PRECISION = 1e12  # prior precision of a degree of freedom the floor already fixed
ICP_DATA_WEIGHT = 1.0  # data information scale (neighbouring points are not independent)


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
        return {
            "a": self.a,
            "b": self.b,
            "fitness": self.fitness,
            "rmse_m": self.rmse_m,
            "used": self.used,
            "note": self.note,
        }


@dataclass(frozen=True)
class _View:
    """One camera's down-sampled cloud for registration, in its own camera frame."""

    points: np.ndarray  # (N, 3) camera frame
    normals: np.ndarray  # (N, 3) camera frame
    sigma: np.ndarray  # (N,) expected depth noise of each point (m)
    tree: Any  # scipy cKDTree over `points`


def _view(
    camera: CameraCloud,
    extrinsic: np.ndarray,
    site: Site,
    settings: CalibrationConfig,
    drop_level: bool = False,
) -> _View:
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


def _small_motion(omega: np.ndarray, tau: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """4x4 silo-frame transform: rotate by the rotation vector `omega` about `pivot`, shift."""
    angle = float(np.linalg.norm(omega))
    rotation = np.eye(3) if angle < 1e-15 else rotation_between_axis(omega / angle, angle)
    return about(rotation, pivot, tau)


def register(
    cameras: Sequence[CameraCloud],
    poses: Mapping[str, np.ndarray],
    site: Site,
    settings: CalibrationConfig,
    prior_deg: float,
    prior_m: float,
    leveled: frozenset[str] = frozenset(),
    spacings: Sequence[SpacingConfig] = (),
) -> tuple[dict[str, np.ndarray], list[PairRegistration]]:
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
    prior = np.tile(
        np.r_[np.full(3, 1 / np.radians(prior_deg) ** 2), np.full(3, 1 / prior_m**2)], n
    )
    for k, serial in enumerate(serials):
        if serial in leveled:
            prior[[6 * k, 6 * k + 1, 6 * k + 5]] = LOCKED_PRECISION
    coarse = settings.icp_max_distance_m * ICP_SCALES[0]
    for i, j in pair_list:  # overlap: share of either camera's points near the other's
        scratch_h, scratch_g = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
        overlap[(i, j)] = max(
            _accumulate(views, current, i, j, coarse, scratch_h, scratch_g)[0],
            _accumulate(views, current, j, i, coarse, scratch_h, scratch_g)[0],
        )
    active = [p for p in pair_list if overlap[p] >= settings.min_overlap]
    for scale in ICP_SCALES if active or links else ():
        distance = settings.icp_max_distance_m * scale
        for _ in range(ICP_ITERATIONS):
            h = np.diag(prior).astype(float)
            g = np.zeros(6 * n)
            # accumulated correction so far, penalised by the prior (relative to the start)
            for k in range(n):
                omega, tau = _correction_params(poses[serials[k]], current[k])
                g[6 * k : 6 * k + 6] -= prior[6 * k : 6 * k + 6] * np.r_[omega, tau]
            for i, j in active:
                for a, b in ((i, j), (j, i)):  # points of b onto surface of a
                    stats = _accumulate(views, current, a, b, distance, h, g)
                    if a == i:
                        rmse[(i, j)] = stats[1]
            for a, b, measured, sigma in links:
                _add_spacing(current, a, b, measured, sigma, h, g)
            step = np.linalg.solve(h, g)
            for k in range(n):
                delta = _small_motion(
                    step[6 * k : 6 * k + 3], step[6 * k + 3 : 6 * k + 6], current[k][:3, 3]
                )
                current[k] = delta @ current[k]
            if np.max(np.abs(step[0::6])) < 1e-7 and np.max(np.abs(step)) < 1e-6:
                break
    pairs = []
    for i, j in pair_list:
        used = overlap[(i, j)] >= settings.min_overlap
        note = "" if used else f"overlap {overlap[(i, j)]:.2f} below min_overlap"
        pairs.append(
            PairRegistration(serials[i], serials[j], overlap[(i, j)], rmse[(i, j)], used, note)
        )
    corrections = {s: current[k] @ np.linalg.inv(poses[s]) for k, s in enumerate(serials)}
    return corrections, pairs


def _add_spacing(
    poses: Sequence[np.ndarray],
    a: int,
    b: int,
    measured: float,
    sigma: float,
    h: np.ndarray,
    g: np.ndarray,
) -> None:
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
        omega = (
            angle
            / (2 * np.sin(angle))
            * np.array(
                [
                    relative[2, 1] - relative[1, 2],
                    relative[0, 2] - relative[2, 0],
                    relative[1, 0] - relative[0, 1],
                ]
            )
        )
    return omega, now[:3, 3] - start[:3, 3]


def _accumulate(
    views: Sequence[_View],
    poses: Sequence[np.ndarray],
    a: int,
    b: int,
    distance: float,
    h: np.ndarray,
    g: np.ndarray,
) -> tuple[float, float]:
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
    agree = (
        np.abs(
            np.einsum(
                "ij,ij->i", vb.normals[found] @ pb[:3, :3].T, va.normals[idx[found]] @ pa[:3, :3].T
            )
        )
        >= ICP_NORMAL_AGREEMENT_COS
    )
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
        g[6 * k : 6 * k + 6] -= jk.T @ (w * r)
        for m, jm in blocks:
            h[6 * k : 6 * k + 6, 6 * m : 6 * m + 6] += (jk * w[:, None]).T @ jm
    rms = float(np.sqrt(np.sum(w * r * r) / np.sum(w) if np.sum(w) > 0 else 0.0))
    return share, rms


# ---------------------------------------------------------------- calibration
