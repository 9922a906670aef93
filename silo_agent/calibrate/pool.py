"""Pooling calibration scans taken one after another: per camera, the per-pixel mean of all
their points, so that the floor fit and the registration see the frames' noise averaged."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from silo_agent.calibrate.errors import ScanMismatch
from silo_agent.scan import Scan, Site, gravity_of


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


def pixel_means(
    points: np.ndarray, colors: np.ndarray | None, intrinsics: Mapping[str, Any]
) -> tuple[np.ndarray, np.ndarray | None]:
    """Camera-frame points (and colours) of several captures averaged per pixel: one point
    per pixel ray, the pixel found from the intrinsics the points were deprojected with."""
    cam = points.astype(np.float64)
    u = np.rint(cam[:, 0] / cam[:, 2] * intrinsics["fx"] + intrinsics["ppx"]).astype(np.int64)
    v = np.rint(cam[:, 1] / cam[:, 2] * intrinsics["fy"] + intrinsics["ppy"]).astype(np.int64)
    u -= u.min()
    _, inverse, count = np.unique(
        (v - v.min()) * (u.max() + 1) + u, return_inverse=True, return_counts=True
    )

    def mean(values: np.ndarray) -> np.ndarray:
        return (
            np.column_stack([np.bincount(inverse, values[:, k]) for k in range(values.shape[1])])
            / count[:, None]
        )

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
        added = [s for s in own if s not in serials]
        missing = [s for s in serials if s not in own]
        if added or missing or len(own) != len(serials):
            parts = []
            if added:
                parts.append(f"cameras not in {labels[0]}: {', '.join(added)}")
            if missing:
                parts.append(f"cameras of {labels[0]} missing: {', '.join(missing)}")
            if not parts:
                parts.append("a camera serial repeated")
            raise ScanMismatch(
                f"{label}: not the same cameras as {labels[0]} ("
                + "; ".join(parts)
                + "); pooled calibration scans must be of "
                "the same installation"
            )
        difference = _site_difference(first.site, scan.site)
        if difference is not None:
            raise ScanMismatch(
                f"{label}: site differs from {labels[0]}'s ({difference}); "
                "pooled calibration scans must be of the same installation"
            )
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
    return replace(
        first, cameras=cameras, extra={**first.extra, "pooled_scans": [s.scan_id for s in scans]}
    )
