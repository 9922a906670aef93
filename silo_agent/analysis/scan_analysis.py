"""A scan's analysis: what `process`, `scan` and the daemon call.

YOLO first when a model is configured (its robot boxes are cut out of the cloud before the
surface is built), then the reconstruction, then the piles of both detectors, with ids carried
over from the previous scan. This module sits above both `silo_agent.reconstruct` and
`silo_agent.detect`, which do not import each other's orchestration; its `ScanAnalysis`
carries the reconstruction's `Reconstruction` and what detection found on it, so the reconstruction
knows nothing of piles and robots. `analysis.summary.summarise` makes the published summary.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from silo_agent.config import CalibrationConfig, DetectionConfig, ReconstructionConfig
from silo_agent.detect import Pile, Robot, fused_points, match_ids, onnx_piles, robots_of
from silo_agent.detect.geometric import Surface, detect_piles
from silo_agent.grid.geometry import points_outside
from silo_agent.reconstruct import Reconstruction, reconstruct, released
from silo_agent.scan import Scan, Site

if TYPE_CHECKING:
    from silo_agent.detect.onnx_yolo import Located


@dataclass
class ScanAnalysis:
    """A scan's reconstruction and the piles (and robots) found on it."""

    reconstruction: Reconstruction
    piles: list[Pile]  # both detectors', ids carried over from the previous scan
    robots: list[Robot] | None  # None: no YOLO model configured

    def describe(self) -> str:
        """A few human-readable lines."""
        findings = [f"piles     {len(self.piles)}"]
        findings += [
            f"  #{p.id:<3} {p.detector:<9} at ({p.centroid[0]:.2f}, {p.centroid[1]:.2f})"
            f"  peak {p.peak_height_m:.3f} m  footprint {p.footprint_m2:.2f} m²"
            f"  volume {p.volume_m3:.4f} m³"
            for p in self.piles
        ]
        findings += [
            f"robot     at ({r.x:.2f}, {r.y:.2f})  seen by {r.camera}" for r in self.robots or []
        ]
        return self.reconstruction.describe(findings)


def analyse(
    scan: Scan,
    settings: ReconstructionConfig,
    detection: DetectionConfig,
    site: Site | None = None,
    previous: Sequence[Pile] = (),
    calibration: CalibrationConfig | None = None,
    release_points: bool = False,
) -> ScanAnalysis:
    """Reconstruct `scan` and detect its piles (and robot) as `detection` configures.

    `calibration` sets how the registration residual is measured; with `level` on (by default
    outside bins), each camera that sees bare floor is leveled on it first
    (silo_agent.reconstruct.level), and with `refine` on, a bounded registration of the
    overlaps adjusts the scan's extrinsics (silo_agent.calibrate).

    Parameters
    ----------
    scan : Scan
        The scan to analyse.
    settings : ReconstructionConfig
        How to reconstruct (see `reconstruct.reconstruct`).
    detection : DetectionConfig
        The geometric detector's settings and the YOLO model, if any.
    site : Site, optional
        Default the scan's own.
    previous : sequence of Pile
        The previous scan's piles: a pile that stayed in place keeps its id.
    calibration : CalibrationConfig, optional
        Residual thresholds, `level` and `refine`.
    release_points : bool
        The scan's clouds may lose their points once the reconstruction has read them
        (`reconstruct.released`; not with a YOLO model, whose piles read them after).

    Returns
    -------
    ScanAnalysis
        The reconstruction, the piles of both detectors and the robots (None without a model).

    Raises
    ------
    ModelError
        The configured ONNX model cannot be used.
    """
    site = site or scan.site
    found: list[Located] = []
    robots: list[Robot] = []
    onnx = detection.onnx
    if onnx is not None:
        from silo_agent.detect.onnx_yolo import YoloModel, locate

        found = locate(YoloModel(onnx.model), scan.cameras, onnx.confidence, onnx.iou)
        robots = robots_of(found, onnx.robot_classes)
    release_points = release_points and onnx is None
    adjusted_scan, adjusted = _per_scan_calibration(scan, calibration, site)
    if release_points and adjusted_scan is not scan:
        released(scan)  # the caller's copy: the adjusted scan holds the same points
    scan = adjusted_scan
    result = reconstruct(
        scan,
        settings,
        site,
        exclude=[r.disc for r in robots],
        calibration=calibration,
        release_points=release_points,
    )
    result.parameters |= adjusted
    found_robots = robots if onnx is not None else None
    if result.heightmap is None:
        return ScanAnalysis(result, [], found_robots)
    surface = Surface.for_piles(
        result.heightmap, site.base, site.floor_z, detection.background_m, result.information
    )
    piles: list[Pile] = []
    if detection.geometric:
        piles += detect_piles(surface, detection)
    if onnx is not None:
        cloud = fused_points(scan.cameras)
        cloud = cloud[points_outside(cloud, [r.disc for r in robots])]
        piles += onnx_piles(found, onnx.pile_classes, cloud, surface, onnx.cluster_radius_m)
    return ScanAnalysis(
        result, match_ids(previous, piles, detection.match_distance_m), found_robots
    )


def _per_scan_calibration(
    scan: Scan, calibration: CalibrationConfig | None, site: Site
) -> tuple[Scan, dict[str, Any]]:
    """`scan` leveled on the floor (`calibration.level`), then refined on its overlaps
    (`calibration.refine`), as configured; and what each did, for the result's parameters."""
    said: dict[str, Any] = {}
    if calibration is None:
        return scan, said
    if calibration.levels(site.bin is not None, site.base):
        from silo_agent.reconstruct.level import level_scan

        scan, leveled, notes = level_scan(scan, calibration, site)
        said["leveled"] = {
            serial: {"turned_deg": degrees, "moved_m": metres}
            for serial, (degrees, metres) in leveled.items()
        }
        said["level_notes"] = notes
    if calibration.refine:
        from silo_agent.calibrate import refine

        scan, notes = refine(scan, calibration, site)
        said["refined"] = not notes
        said["refine_notes"] = notes
    return scan, said
