"""Calibration of a scan's cameras (`calibrate`) and the bounded per-scan refinement
(`refine`): leveling, registration, the rig kept where the configuration put it, and the
bounds on how far a camera may move."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from silo_agent.calibrate.errors import CalibrationError, SerialMismatch
from silo_agent.calibrate.register import PairRegistration, register
from silo_agent.config import CalibrationConfig, Config, SpacingConfig
from silo_agent.grid.geometry import euler_from_rotation
from silo_agent.grid.grid import Grid
from silo_agent.grid.rigid import UP, about, planar_procrustes, pose_change, rotation_between
from silo_agent.reconstruct.fuse import fuse_and_crop
from silo_agent.reconstruct.level import floor_leveled
from silo_agent.reconstruct.residual import PairResidual, registration_residuals
from silo_agent.scan import CameraCloud, Scan, Site, gravity_angles, gravity_of, with_extrinsics

# In a bin the cameras hang at the eave and see the floor and the grain 6-10 m away, where the
# D455's noise is a decimetre and more: on a simulated 8 m bin the floor fit alone was off by
# 0.6-2.2 deg at the cameras' true poses, and `calibrate` refused, or left the cameras further
# off than they were, with and without the floor (bench/results/calibration-bins.md). Said
# with every calibration of a bin, and with its refusal.
BIN_WARNING = (
    "in a bin the cameras see the floor and the grain from the eave, 6-10 m away, where the "
    "D455's noise is a decimetre and more: on a simulated 8 m bin the cameras came out further "
    "off than they went in; check the poses against the measured mounting before --write "
    "(docs/calibration.md, 'In a round bin')"
)


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
            "serial": self.serial,
            "extrinsic": self.after.tolist(),
            "rotate_deg": list(rotate),
            "translate_m": list(translate),
            "previous_extrinsic": self.before.tolist(),
            "correction_deg": degrees,
            "correction_m": metres,
            "leveled_by": self.leveled_by,
            "floor_points": self.floor_points,
            "gravity_angle_before_deg": self.gravity_angle_before_deg,
            "gravity_angle_after_deg": self.gravity_angle_after_deg,
        }


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
        return {
            "a": self.a,
            "b": self.b,
            "measured_m": self.measured_m,
            "sigma_m": self.sigma_m,
            "before_m": self.before_m,
            "after_m": self.after_m,
            "error_before_m": self.before_m - self.measured_m,
            "error_after_m": self.after_m - self.measured_m,
        }


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
                k: {
                    "before": _median(self.residual_before, k),
                    "after": _median(self.residual_after, k),
                }
                for k in keys
            },
            "spacing": [s.to_json() for s in self.spacings],
            "notes": self.notes,
        }

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
            lines.append(
                f"{k:<23} {_fmt(self.residual_before.get(k))} -> {_fmt(self.residual_after.get(k))}"
            )
        for p in self.pairs:
            state = "used" if p.used else "not used"
            lines.append(
                f"ICP {p.a}|{p.b}: fitness {p.fitness:.2f}, rmse "
                f"{p.rmse_m * 1000:.1f} mm, {state}{': ' + p.note if p.note else ''}"
            )
        if self.spacings:
            lines.append("spacing                 measured (±sigma) | before -> after (error; mm)")
        for sp in self.spacings:
            lines.append(
                f"{sp.a + '|' + sp.b:<23} {sp.measured_m * 1000:8.1f} (±{sp.sigma_m * 1000:.1f}) | "
                f"{sp.before_m * 1000:8.1f} ({(sp.before_m - sp.measured_m) * 1000:+.1f}) -> "
                f"{sp.after_m * 1000:8.1f} ({(sp.after_m - sp.measured_m) * 1000:+.1f})"
            )
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


def _median(residuals: Mapping[str, PairResidual], key: str) -> float | None:
    r = residuals.get(key)
    return None if r is None else r.median_m


def _fmt(r: PairResidual | None) -> str:
    if r is None:
        return "       (no overlap)     "
    return f"{r.median_m * 1000:+6.1f} ±{r.mad_m * 1000:4.1f} ({r.cells:5d})"


def scan_residuals(
    cameras: Sequence[CameraCloud], site: Site, grid_step: float, settings: CalibrationConfig
) -> dict[str, PairResidual]:
    """Registration residual of every camera pair, as every scan measures it."""
    grid = Grid.over(site.region, grid_step)
    fused = fuse_and_crop(list(cameras), site, grid)
    return registration_residuals(
        fused,
        grid,
        [c.serial for c in cameras],
        settings.residual_min_points,
        settings.residual_min_cells,
    )


def calibrate(
    scan: Scan,
    settings: CalibrationConfig,
    *,
    floor: bool,
    site: Site | None = None,
    start: Mapping[str, np.ndarray] | None = None,
    grid_step: float = 0.02,
) -> Calibration:
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
    configured = {
        c.serial: np.asarray((start or {}).get(c.serial, c.extrinsic), dtype=float) for c in cameras
    }
    unknown = sorted({s for sp in settings.spacing for s in (sp.a, sp.b) if s not in configured})
    if unknown:
        raise CalibrationError(
            f"calibration.spacing names cameras not in the scan: {', '.join(unknown)}"
        )
    notes: list[str] = [BIN_WARNING] if site.bin is not None else []
    poses = dict(configured)

    # 1. leveling and height from the floor, camera by camera
    leveled: dict[str, Literal["floor", "gravity", "none"]] = {s: "none" for s in poses}
    counts: dict[str, int] = {s: 0 for s in poses}
    if floor:
        for c in cameras:
            pose, counts[c.serial] = floor_leveled(c, poses[c.serial], site.floor_z, settings)
            if pose is None:
                notes.append(
                    f"{c.serial}: sees no floor (z = {site.floor_z:g}) within "
                    f"{settings.floor_max_range_m:g} m; not leveled by the floor"
                )
                continue
            poses[c.serial] = pose
            leveled[c.serial] = "floor"

    # 2. relative registration (yaw and plan position only, where the floor leveled)
    pairs: list[PairRegistration] = []
    if len(cameras) > 1:
        fixed = frozenset(s for s, how in leveled.items() if how == "floor")
        corrections, pairs = register(
            cameras,
            poses,
            site,
            settings,
            settings.prior_deg,
            settings.prior_m,
            fixed,
            settings.spacing,
        )
        linked = {s for p in pairs if p.used for s in (p.a, p.b)}
        for c in cameras:
            if c.serial not in linked:
                spaced = any(c.serial in (sp.a, sp.b) for sp in settings.spacing)
                notes.append(
                    f"{c.serial}: no overlap with another camera; not registered"
                    + (" (only its measured spacing moved it)" if spaced else "")
                )
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
                poses[c.serial] = (
                    about(rotation_between(down, -UP), poses[c.serial][:3, 3]) @ poses[c.serial]
                )
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
        notes.append(
            "no floor and no gravity vector: the rig's tilt and height are kept as "
            "configured (on average)"
        )
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
            + (f"; {BIN_WARNING}" if site.bin is not None else "")
        )

    before_clouds = with_extrinsics(cameras, configured)
    after_clouds = with_extrinsics(cameras, poses)
    angles_before, angles_after = gravity_angles(before_clouds), gravity_angles(after_clouds)
    return Calibration(
        cameras=[
            CameraCalibration(
                c.serial,
                configured[c.serial],
                poses[c.serial],
                leveled[c.serial],
                counts[c.serial],
                angles_before.get(c.serial),
                angles_after.get(c.serial),
            )
            for c in cameras
        ],
        pairs=pairs,
        residual_before=scan_residuals(before_clouds, site, grid_step, settings),
        residual_after=scan_residuals(after_clouds, site, grid_step, settings),
        notes=notes,
        spacings=[
            SpacingCheck(
                sp.a, sp.b, sp.distance_m, sp.sigma_m, _spacing(configured, sp), _spacing(poses, sp)
            )
            for sp in settings.spacing
        ],
    )


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


def refine(
    scan: Scan, settings: CalibrationConfig, site: Site | None = None
) -> tuple[Scan, list[str]]:
    """Per-scan refinement (`calibration.refine`): a bounded relative registration on the
    overlaps, the rig kept where its extrinsics put it on average. Returns the scan unchanged,
    with a note, when a camera would move more than `refine_max_deg` / `refine_max_m`."""
    site = site or scan.site
    if len(scan.cameras) < 2:
        return scan, []
    poses = {c.serial: c.extrinsic for c in scan.cameras}
    corrections, pairs = register(
        scan.cameras, poses, site, settings, settings.refine_max_deg / 2, settings.refine_max_m / 2
    )
    if not any(p.used for p in pairs):
        return scan, ["refine: no overlapping pair; extrinsics unchanged"]
    moved = {s: corrections[s] @ poses[s] for s in poses}
    g = _rigid_fit(list(moved.values()), list(poses.values()))
    moved = {s: g @ p for s, p in moved.items()}
    for s in poses:
        degrees, metres = pose_change(poses[s], moved[s])
        if degrees > settings.refine_max_deg or metres > settings.refine_max_m:
            return scan, [
                f"refine: {s} would turn {degrees:.2f} deg / move {metres * 1000:.0f} "
                "mm, beyond refine_max_*; extrinsics unchanged (recalibrate?)"
            ]
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
