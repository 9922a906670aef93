"""A storage bin's known geometry: wall (round or polygon), eave, floor (flat, conical hopper,
sloped), roof. Pure numpy, shared by the config, the scan manifest, the reconstruction (what is
wall, where the bottom is) and the simulator (what to build).

The silo frame's `floor_z` is the floor plane: for a hopper bin, the plane where the cone meets
the wall; the hopper lies below it and its volume counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from silo_agent.grid.geometry import check_polygon, points_in_polygon

FloorKind = Literal["flat", "hopper", "sloped"]
HeadspaceReference = Literal["eave", "roof"]
ROUND_WALL_SIDES = 720  # a round wall as a polygon of this many sides, of the circle's area
WALL_TOLERANCE_M = 0.01  # a region vertex this far outside the wall is still on it


@dataclass(frozen=True)
class BinShape:
    """The bin around the grain, silo frame, metres."""

    floor_z: float
    eave_z: float
    centre: tuple[float, float] = (0.0, 0.0)
    diameter_m: float | None = None  # round bin; else `wall` is the polygon
    wall: tuple[tuple[float, float], ...] | None = None
    floor: FloorKind = "flat"
    hopper_depth_m: float = 0.0  # floor plane down to the outlet
    outlet_diameter_m: float = 0.0
    floor_slope_deg: float = 0.0  # sloped floor: its tilt ...
    floor_downhill_deg: float = 0.0  # ... and the direction it falls towards (0 = +x, ccw)
    roof_pitch_deg: float = 30.0
    headspace_from: HeadspaceReference = "eave"

    # ------------------------------------------------------------ derived

    @property
    def radius_m(self) -> float:
        if self.diameter_m is None:
            raise ValueError("a polygon bin has no radius")
        return self.diameter_m / 2

    @property
    def outlet_radius_m(self) -> float:
        return self.outlet_diameter_m / 2

    @property
    def hopper_angle_deg(self) -> float:
        """Slope of the hopper cone from the horizontal."""
        run = self.radius_m - self.outlet_radius_m
        return math.degrees(math.atan2(self.hopper_depth_m, run))

    @property
    def hopper_slope(self) -> float:
        """Rise per metre of the hopper's cone (0 without a hopper)."""
        if self.floor != "hopper":
            return 0.0
        return self.hopper_depth_m / (self.radius_m - self.outlet_radius_m)

    @property
    def roof_peak_z(self) -> float:
        """Top of the roof: a cone over a round wall, a pyramid-like rise over a polygon's
        inscribed half-width otherwise."""
        if self.diameter_m is not None:
            half = self.radius_m
        else:
            wall = self.wall_polygon()
            half = float(np.min(np.ptp(wall, axis=0))) / 2
        return self.eave_z + half * math.tan(math.radians(self.roof_pitch_deg))

    @property
    def reference_z(self) -> float:
        """What headspace is measured from: the eave, or the roof peak."""
        return self.eave_z if self.headspace_from == "eave" else self.roof_peak_z

    def wall_polygon(self, sides: int = ROUND_WALL_SIDES) -> np.ndarray:
        """(V, 2) wall polygon; a round wall as `sides` vertices on a circle whose radius makes
        the polygon's area the circle's (so a region drawn on it integrates the whole bin)."""
        if self.wall is not None:
            return np.asarray(self.wall, dtype=float)
        angle = 2 * np.pi / sides
        radius = self.radius_m * math.sqrt(angle / math.sin(angle))
        theta = np.arange(sides) * angle
        cx, cy = self.centre
        return np.column_stack([cx + radius * np.cos(theta), cy + radius * np.sin(theta)])

    def bottom(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the bin's bottom (floor or hopper cone) under each (x, y)."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        if self.floor == "hopper":
            r = np.hypot(x - self.centre[0], y - self.centre[1])
            run = self.radius_m - self.outlet_radius_m
            below = self.hopper_depth_m * np.clip((self.radius_m - r) / run, 0.0, 1.0)
            return self.floor_z - below
        if self.floor == "sloped":
            fall = math.tan(math.radians(self.floor_slope_deg))
            ux = math.cos(math.radians(self.floor_downhill_deg))
            uy = math.sin(math.radians(self.floor_downhill_deg))
            along = (x - self.centre[0]) * ux + (y - self.centre[1]) * uy
            return self.floor_z - fall * along
        return np.full(np.broadcast(x, y).shape, self.floor_z)

    def bottom_slope(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Rise per metre of the bin's bottom under each (x, y): a hopper's cone between the
        outlet and the wall, a sloped floor's tilt, 0 on a flat floor or over the outlet."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        shape = np.broadcast(x, y).shape
        if self.floor == "hopper":
            r = np.hypot(x - self.centre[0], y - self.centre[1])
            inside = (r > self.outlet_radius_m) & (r < self.radius_m)
            return np.where(inside, self.hopper_slope, 0.0)
        if self.floor == "sloped":
            return np.full(shape, math.tan(math.radians(self.floor_slope_deg)))
        return np.zeros(shape)

    def uphill_lines(
        self, x: np.ndarray, y: np.ndarray, spacing_m: float
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """(line, along, lines) of each (x, y) on a hopper's cone: which of its `lines` lines
        of steepest ascent (sectors about `spacing_m` wide at the wall, numbered round it) it
        lies on, and how far up it (the distance from the centre). Not for other floors."""
        if self.floor != "hopper":
            raise ValueError("uphill lines are a hopper's")
        dx = np.asarray(x, dtype=float) - self.centre[0]
        dy = np.asarray(y, dtype=float) - self.centre[1]
        sectors = max(8, round(2 * np.pi * self.radius_m / spacing_m))
        turn = (np.arctan2(dy, dx) + np.pi) / (2 * np.pi)  # 0..1
        line = np.minimum((turn * sectors).astype(np.intp), sectors - 1)
        return line, np.hypot(dx, dy), sectors

    def hopper_volume_m3(self) -> float:
        """The cone frustum below the floor plane (0 without a hopper)."""
        if self.floor != "hopper":
            return 0.0
        big, small = self.radius_m, self.outlet_radius_m
        return math.pi * self.hopper_depth_m * (big * big + big * small + small * small) / 3

    def wall_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Horizontal distance inward from each (x, y) to the wall (negative outside)."""
        if self.diameter_m is not None:
            return self.radius_m - np.hypot(x - self.centre[0], y - self.centre[1])
        wall = self.wall_polygon()
        px, py = np.asarray(x, dtype=float)[..., None], np.asarray(y, dtype=float)[..., None]
        a, b = wall, np.roll(wall, -1, axis=0)
        d = b - a
        t = np.clip(((px - a[:, 0]) * d[:, 0] + (py - a[:, 1]) * d[:, 1]) / (d**2).sum(1), 0, 1)
        gap = np.hypot(px - (a[:, 0] + t * d[:, 0]), py - (a[:, 1] + t * d[:, 1])).min(-1)
        inside = points_in_polygon(np.ravel(x), np.ravel(y), wall).reshape(gap.shape)
        return np.where(inside, gap, -gap)

    def ray_wall_depth(self, ox: float, oy: float, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """Ray parameter where rays from (ox, oy) inside the bin, horizontal directions
        (dx, dy), leave through the wall. The directions need not be unit; the result is in
        their units (depth, for a camera's z = 1 rays). Rays with no horizontal part: inf."""
        if self.diameter_m is not None:
            px, py = ox - self.centre[0], oy - self.centre[1]
            a = dx * dx + dy * dy
            b = px * dx + py * dy
            c = px * px + py * py - self.radius_m**2
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.where(
                    a > 1e-12, (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a, np.inf
                )
        wall = self.wall_polygon()
        best = np.full(np.broadcast(ox, dx).shape, np.inf)
        for a_pt, b_pt in zip(wall, np.roll(wall, -1, axis=0), strict=True):  # edges, not points
            ex, ey = b_pt - a_pt
            denom = dx * ey - dy * ex
            wx, wy = a_pt[0] - ox, a_pt[1] - oy
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (wx * ey - wy * ex) / denom
                s = (wx * dy - wy * dx) / denom
            hit = (np.abs(denom) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
            best = np.where(hit, np.minimum(best, t), best)
        return best

    # ------------------------------------------------------------ checks and wire form

    def problems(self) -> list[tuple[str, str]]:
        """(key, problem) for every way this geometry contradicts itself."""
        out: list[tuple[str, str]] = []
        if (self.diameter_m is None) == (self.wall is None):
            out.append(("diameter_m", "give either a round bin's diameter_m or a wall polygon"))
            return out
        if self.diameter_m is not None and not self.diameter_m > 0:
            out.append(("diameter_m", f"must be positive, got {self.diameter_m}"))
            return out
        if self.wall is not None:
            problem = check_polygon(np.asarray(self.wall, dtype=float).reshape(-1, 2))
            if problem:
                out.append(("wall", problem))
                return out
        if self.eave_z <= self.floor_z:
            out.append(("eave_height_m", f"the eave ({self.eave_z}) must be above the floor"))
        if self.floor == "hopper":
            if self.diameter_m is None:
                out.append(("floor", "a conical hopper needs a round bin (diameter_m)"))
                return out
            if not 0 < self.outlet_diameter_m < self.diameter_m:
                out.append(
                    (
                        "outlet_diameter_m",
                        f"must be above 0 and below the bin's diameter {self.diameter_m}, "
                        f"got {self.outlet_diameter_m}",
                    )
                )
            elif not self.hopper_depth_m > 0:
                out.append(("hopper_depth_m", "a hopper floor needs a depth or an angle"))
        if self.floor == "sloped" and not 0 <= self.floor_slope_deg < 60:
            out.append(("floor_slope_deg", f"must be in [0, 60), got {self.floor_slope_deg}"))
        if not 0 <= self.roof_pitch_deg < 80:
            out.append(("roof_pitch_deg", f"must be in [0, 80), got {self.roof_pitch_deg}"))
        return out

    def region_problem(self, region: np.ndarray) -> str | None:
        """Why a region polygon does not fit inside this wall, or None."""
        outside = self.wall_distance(region[:, 0], region[:, 1]) < -WALL_TOLERANCE_M
        if np.any(outside):
            first = region[int(np.argmax(outside))].tolist()
            return f"region vertex {first} lies outside the bin's wall"
        return None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"eave_z": self.eave_z, "floor": self.floor}
        if self.diameter_m is not None:
            out |= {"centre": list(self.centre), "diameter_m": self.diameter_m}
        else:
            out["wall"] = [list(p) for p in self.wall or ()]
        if self.floor == "hopper":
            out |= {
                "hopper_depth_m": self.hopper_depth_m,
                "outlet_diameter_m": self.outlet_diameter_m,
            }
        if self.floor == "sloped":
            out |= {
                "floor_slope_deg": self.floor_slope_deg,
                "floor_downhill_deg": self.floor_downhill_deg,
            }
        out |= {"roof_pitch_deg": self.roof_pitch_deg, "headspace_from": self.headspace_from}
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any], floor_z: float) -> BinShape:
        """The manifest's `site.bin` (already schema-checked)."""
        wall = data.get("wall")
        return cls(
            floor_z=floor_z,
            eave_z=float(data["eave_z"]),
            centre=tuple(data.get("centre", (0.0, 0.0))),
            diameter_m=data.get("diameter_m"),
            wall=tuple(tuple(p) for p in wall) if wall is not None else None,
            floor=data.get("floor", "flat"),
            hopper_depth_m=float(data.get("hopper_depth_m", 0.0)),
            outlet_diameter_m=float(data.get("outlet_diameter_m", 0.0)),
            floor_slope_deg=float(data.get("floor_slope_deg", 0.0)),
            floor_downhill_deg=float(data.get("floor_downhill_deg", 0.0)),
            roof_pitch_deg=float(data.get("roof_pitch_deg", 30.0)),
            headspace_from=data.get("headspace_from", "eave"),
        )
