"""Camera calibration, the offline tool: leveling, relative registration, bounded corrections.

Why: most of the residual volume error comes from camera placement. Hand-set extrinsics leave
the two surfaces of an overlap apart, and a 1 cm height bias over a whole floor is a large
volume. One calibration scan (or several taken one after another, pooled by `pool_scans` so
that their noise averages) fixes that:

1. *Relative registration* (`register.py`): point-to-plane ICP between every two cameras whose
   views overlap, starting from the configured extrinsics, all pairs solved as one
   least-squares pose graph with a prior on each camera's correction (open3d's multiway
   registration drifted along what the scene cannot show), so that all overlaps agree at once.
2. *Leveling* fixes what relative registration cannot see (the whole rig's tilt and height):
   with `floor` (`silo_agent.reconstruct.level`, which per-scan leveling shares), each
   camera's own view of the floor plane `z = floor_z` (RANSAC, then least squares) sets its
   pitch, roll and height; otherwise the cameras' accelerometer gravity vectors set the
   rig's tilt and the configured (mounted) heights its height.
3. The rig's yaw and plan position, which a floor and gravity cannot see, stay where the
   configured extrinsics put them on average (2-D Procrustes on the camera poses). Its scale,
   which a scan without walls hardly shows, comes from measured camera spacings
   (`[[calibration.spacing]]`) when the config has them: one more residual per spacing in
   the joint registration.
4. A camera corrected by more than `max_correction_deg` / `max_correction_m` is refused with the
   reason (`solve.py`): a calibration that far off is a wrong scan or a wrong config, not a
   small error.

`config_file.py` writes the result back into the site's config. Drift monitoring runs inside
the daemon and lives with the analysis (`silo_agent.analysis.drift`): the daemon does not
import this package, except `refine` when `calibration.refine` is on (per-scan leveling,
`calibration.level`, lives with the reconstruction: numpy and scipy only).
"""

from silo_agent.calibrate.config_file import rewrite_config_text, write_calibrated_config
from silo_agent.calibrate.errors import CalibrationError, ScanMismatch, SerialMismatch
from silo_agent.calibrate.pool import pixel_means, pool_scans
from silo_agent.calibrate.solve import (
    Calibration,
    calibrate,
    refine,
    scan_residuals,
    start_poses,
)
from silo_agent.reconstruct.level import fit_plane, floor_points, level_scan
from silo_agent.scan import with_extrinsics

__all__ = [
    "Calibration",
    "CalibrationError",
    "ScanMismatch",
    "SerialMismatch",
    "calibrate",
    "fit_plane",
    "floor_points",
    "level_scan",
    "pixel_means",
    "pool_scans",
    "refine",
    "rewrite_config_text",
    "scan_residuals",
    "start_poses",
    "with_extrinsics",
    "write_calibrated_config",
]
