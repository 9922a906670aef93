"""Scene library: grain surfaces as height fields z = f(x, y), clutter, and their exact volume.

The truth volume is computed from the scene's parameters (closed forms where they exist, else a
2 mm midpoint integration of the height field), never from a rendering or a reconstruction, so
it can judge the reconstruction honestly.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from silo_agent.base.choices import SCENE_NAMES
from silo_agent.grid.bin_shape import BinShape
from silo_agent.grid.geometry import cell_fractions
from silo_agent.scan import Site
from silo_agent.sim.grains import Grain, grain

HeightField = Callable[[np.ndarray, np.ndarray], np.ndarray]

SCENES = SCENE_NAMES
PAPER_PILE_M3 = 1.68  # the paper's reference pile


@dataclass(frozen=True)
class Box:
    """Axis-aligned clutter (beam, ceiling slab) in the silo frame."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


@dataclass(frozen=True)
class PileTruth:
    """One pile of a multi-pile scene, for judging pile detection."""

    apex: tuple[float, float, float]
    radius_m: float
    volume_m3: float  # the part of the surface this pile is the highest cone of
    centroid: tuple[float, float, float]  # centroid of that volume

    def to_json(self) -> dict[str, Any]:
        return {
            "apex": list(self.apex),
            "radius_m": self.radius_m,
            "volume_m3": self.volume_m3,
            "centroid": list(self.centroid),
        }


@dataclass(frozen=True)
class Scene:
    name: str
    grain: Grain
    site: Site
    height: HeightField  # surface over `extent`, walls included (outside the region)
    extent: tuple[float, float, float, float]  # xmin, xmax, ymin, ymax of the height field
    outer_z: float | None  # open floor level beyond `extent`; None: nothing beyond (walled bay)
    volume_m3: float  # exact grain volume above floor_z inside site.region
    target: tuple[float, float, float]  # where the cameras aim
    layout: str  # default camera layout: "paper" or "wall"
    wall_half_m: float  # half side of the square the wall cameras hang on
    wall_camera_z: float
    clutter: tuple[Box, ...] = ()
    piles: tuple[PileTruth, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)  # shape parameters, for tests and docs
    bin: BinShape | None = None  # a bin's wall, roof and bottom, built into the world
    surface_factor: float = 1.0  # depth noise over the D455's ideal-target figure
    max_depth_m: float = 6.0  # farthest depth the camera reports
    mesh_step_m: float = 0.01  # height-field mesh step

    def truth(self) -> dict[str, Any]:
        """What `scan.json` carries as `truth`."""
        out: dict[str, Any] = {
            "volume_m3": self.volume_m3,
            "scene": self.name,
            "grain": self.grain.name,
            "mass_t": self.volume_m3 * self.grain.density_t_m3,
        }
        if self.piles:
            out["piles"] = [p.to_json() for p in self.piles]
        if self.bin is not None:
            out |= self.bin_truth(self.volume_m3)
        return out

    def bin_truth(self, volume_m3: float) -> dict[str, Any]:
        """A bin's truth beside the volume: the highest and lowest grain, fill and headspace."""
        assert self.bin is not None
        top, low, mean = (
            self.params["grain_max_z"],
            self.params["grain_min_z"],
            self.params["grain_mean_z"],
        )
        return {
            "capacity_m3": self.params["capacity_m3"],
            "fill_ratio": volume_m3 / self.params["capacity_m3"],
            "level_max_m": top - self.site.floor_z,
            "level_min_m": low - self.site.floor_z,
            "level_mean_m": mean - self.site.floor_z,
            "headspace_m": self.bin.reference_z - top,
            "headspace_mean_m": self.bin.reference_z - mean,
        }


# ---------------------------------------------------------------- shapes


def cone_height(
    x: np.ndarray, y: np.ndarray, centre: tuple[float, float], radius: float, slope: float
) -> np.ndarray:
    """Height above the base of a cone at the angle of repose (0 outside its footprint)."""
    return np.maximum(0.0, slope * (radius - np.hypot(x - centre[0], y - centre[1])))


def segment_distance(
    x: np.ndarray, y: np.ndarray, a: tuple[float, float], b: tuple[float, float]
) -> np.ndarray:
    """Distance from points to the segment a-b."""
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    t = np.clip(((x - ax) * dx + (y - ay) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
    return np.hypot(x - (ax + t * dx), y - (ay + t * dy))


def square(half: float) -> np.ndarray:
    return np.array([[-half, -half], [half, -half], [half, half], [-half, half]], dtype=float)


def numeric_volume(
    height: HeightField, region: np.ndarray, floor_z: float, step: float = 0.002
) -> float:
    """Midpoint integral of max(height - floor_z, 0) over `region` (cells weighted by the
    fraction inside); a check on the closed forms and the truth where none exists."""
    total, _ = _integrate(height, region, floor_z, step, ())
    return total


def _integrate(
    height: HeightField,
    region: np.ndarray,
    floor_z: float,
    step: float,
    cones: tuple[tuple[tuple[float, float], float, float], ...],
) -> tuple[float, list[tuple[float, np.ndarray]]]:
    """Total volume, and per cone (centre, radius, slope) the volume and volume-weighted centroid
    of the cells where that cone is the highest, row band by row band to bound memory."""
    xmin, ymin = region.min(axis=0)
    xmax, ymax = region.max(axis=0)
    cols = int(np.ceil((xmax - xmin) / step))
    rows = int(np.ceil((ymax - ymin) / step))
    xc = xmin + (np.arange(cols) + 0.5) * step
    total = 0.0
    per_cone = np.zeros((len(cones), 4))  # volume, moments x, y, z
    band = max(1, 2_000_000 // cols)
    for r0 in range(0, rows, band):
        r1 = min(rows, r0 + band)
        origin = (float(xmin), float(ymin + r0 * step))
        weight = cell_fractions(region, origin, step, (r1 - r0, cols)) * step * step
        yc = ymin + (np.arange(r0, r1) + 0.5) * step
        gx, gy = np.meshgrid(xc, yc)
        column = np.maximum(height(gx, gy) - floor_z, 0.0) * weight
        total += float(column.sum())
        if cones:
            stack = np.stack([cone_height(gx, gy, c, r, s) for c, r, s in cones])
            owner = np.argmax(stack, axis=0)
            top = stack.max(axis=0)
            for k in range(len(cones)):
                mine = np.where(owner == k, top, 0.0) * weight
                per_cone[k] += [
                    mine.sum(),
                    (mine * gx).sum(),
                    (mine * gy).sum(),
                    (mine * (floor_z + top / 2)).sum(),
                ]
    piles = [(float(v[0]), v[1:] / v[0]) for v in per_cone]
    return total, piles


# ---------------------------------------------------------------- the library

PAPER_REGION_HALF = 2.2  # example config: the paper's 5 m camera square, 0.3 m inside it
PAPER_EXTENT = (-2.7, 2.7, -2.7, 2.7)


def _paper_site(g: Grain, ceiling_z: float = 1.5) -> Site:
    return Site(
        region=square(PAPER_REGION_HALF),
        floor_z=0.0,
        ceiling_z=ceiling_z,
        bulk_density_t_m3=g.density_t_m3,
    )


def cone_scene(g: Grain) -> Scene:
    """The paper's experiment: one pile of ~1.68 m³ on the floor, the 5 m square around it."""
    radius = float((3 * PAPER_PILE_M3 / (np.pi * g.slope)) ** (1 / 3))
    peak = g.slope * radius
    return Scene(
        name="cone",
        grain=g,
        site=_paper_site(g),
        height=lambda x, y: cone_height(x, y, (0.0, 0.0), radius, g.slope),
        extent=PAPER_EXTENT,
        outer_z=0.0,
        volume_m3=float(np.pi * radius**2 * peak / 3),
        target=(0.0, 0.0, peak / 2),
        layout="paper",
        wall_half_m=2.5,
        wall_camera_z=2.5,
        params={"centre": (0.0, 0.0), "radius": radius, "height": peak},
    )


PILES = (((-0.7, -0.5), 1.0), ((0.6, -0.3), 0.9), ((0.1, 0.8), 0.8), ((1.3, 1.1), 0.5))


def piles_scene(g: Grain) -> Scene:
    """Several overlapping piles (the surface is the highest cone): a bay filled from spouts."""
    cones = tuple((c, r, g.slope) for c, r in PILES)

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.max(np.stack([cone_height(x, y, c, r, s) for c, r, s in cones]), axis=0)

    site = _paper_site(g)
    total, per_pile = _integrate(height, site.region, site.floor_z, 0.002, cones)
    piles = tuple(
        PileTruth(
            apex=(c[0], c[1], r * g.slope),
            radius_m=r,
            volume_m3=v,
            centroid=(float(m[0]), float(m[1]), float(m[2])),
        )
        for (c, r), (v, m) in zip(PILES, per_pile, strict=True)
    )
    peak = max(r for _, r in PILES) * g.slope
    return Scene(
        name="piles",
        grain=g,
        site=site,
        height=height,
        extent=PAPER_EXTENT,
        outer_z=0.0,
        volume_m3=total,
        target=(0.0, 0.0, peak / 2),
        layout="paper",
        wall_half_m=2.5,
        wall_camera_z=2.5,
        piles=piles,
        params={"cones": PILES},
    )


RIDGE = ((-1.1, -0.4), (1.1, 0.4), 0.9)  # spine ends, half width


def ridge_scene(g: Grain) -> Scene:
    """A windrow: a prism at the angle of repose along a spine, with half-cone ends."""
    a, b, half = RIDGE
    length = float(np.hypot(b[0] - a[0], b[1] - a[1]))
    peak = g.slope * half
    return Scene(
        name="ridge",
        grain=g,
        site=_paper_site(g),
        height=lambda x, y: np.maximum(0.0, g.slope * (half - segment_distance(x, y, a, b))),
        extent=PAPER_EXTENT,
        outer_z=0.0,
        volume_m3=g.slope * (length * half**2 + np.pi * half**3 / 3),
        target=(0.0, 0.0, peak / 2),
        layout="paper",
        wall_half_m=2.5,
        wall_camera_z=2.5,
        params={"a": a, "b": b, "half_width": half, "length": length, "height": peak},
    )


BAY_HALF = 3.0
BAY_EXTENT = (-3.1, 3.1, -3.1, 3.1)  # the walls stand just outside the region


def _bay(level: HeightField, wall_top: float) -> HeightField:
    """Grain surface inside the bay, a wall up to `wall_top` outside it."""

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        inside = (np.abs(x) <= BAY_HALF + 1e-9) & (np.abs(y) <= BAY_HALF + 1e-9)
        return np.where(inside, level(x, y), wall_top)

    return height


CRATER = ((0.4, -0.3), 1.1, 1.2)  # funnel centre, funnel radius, grain level


def crater_scene(g: Grain) -> Scene:
    """A flat grain surface with the funnel an unloading outlet draws into it."""
    centre, radius, level = CRATER
    depth = g.slope * radius
    site = Site(
        region=square(BAY_HALF), floor_z=0.0, ceiling_z=2.8, bulk_density_t_m3=g.density_t_m3
    )
    return Scene(
        name="crater",
        grain=g,
        site=site,
        height=_bay(lambda x, y: level - cone_height(x, y, centre, radius, g.slope), 3.0),
        extent=BAY_EXTENT,
        outer_z=None,
        volume_m3=level * (2 * BAY_HALF) ** 2 - np.pi * radius**2 * depth / 3,
        target=(centre[0], centre[1], level - depth),
        layout="wall",
        wall_half_m=BAY_HALF,
        wall_camera_z=2.6,
        params={
            "centre": centre,
            "radius": radius,
            "level": level,
            "depth": depth,
            "area": (2 * BAY_HALF) ** 2,
        },
    )


def flat_scene(g: Grain) -> Scene:
    """The crater's bay before the outlet opened: flat grain at the crater's level. With
    `crater` in a scan sequence it is a funnel opening and being filled again."""
    centre, _radius, level = CRATER
    site = Site(
        region=square(BAY_HALF), floor_z=0.0, ceiling_z=2.8, bulk_density_t_m3=g.density_t_m3
    )
    return Scene(
        name="flat",
        grain=g,
        site=site,
        height=_bay(lambda x, y: np.full(np.broadcast(x, y).shape, level), 3.0),
        extent=BAY_EXTENT,
        outer_z=None,
        volume_m3=level * (2 * BAY_HALF) ** 2,
        target=(centre[0], centre[1], level),
        layout="wall",
        wall_half_m=BAY_HALF,
        wall_camera_z=2.6,
        params={"level": level, "area": (2 * BAY_HALF) ** 2},
    )


FULL = (1.6, 1.2, 3.2)  # grain level, filling cone radius, roof


def full_scene(g: Grain) -> Scene:
    """A bay filled close to the roof: beams and ceiling in view, cropped by ceiling_z."""
    level, radius, roof = FULL
    peak = level + g.slope * radius
    site = Site(
        region=square(BAY_HALF), floor_z=0.0, ceiling_z=2.5, bulk_density_t_m3=g.density_t_m3
    )
    beam_bottom = 2.75
    clutter = (
        Box((-3.6, -3.6, roof), (3.6, 3.6, roof + 0.1)),
        Box((-BAY_HALF, -1.6, beam_bottom), (BAY_HALF, -1.4, roof)),
        Box((-BAY_HALF, 1.4, beam_bottom), (BAY_HALF, 1.6, roof)),
        Box((-0.1, -BAY_HALF, beam_bottom + 0.1), (0.1, BAY_HALF, roof)),
    )
    return Scene(
        name="full",
        grain=g,
        site=site,
        height=_bay(lambda x, y: level + cone_height(x, y, (0.0, 0.0), radius, g.slope), roof),
        extent=BAY_EXTENT,
        outer_z=None,
        volume_m3=level * (2 * BAY_HALF) ** 2 + np.pi * radius**2 * (peak - level) / 3,
        target=(0.0, 0.0, level),
        layout="wall",
        wall_half_m=BAY_HALF,
        wall_camera_z=2.6,
        clutter=clutter,
        params={
            "level": level,
            "radius": radius,
            "peak": peak,
            "roof": roof,
            "area": (2 * BAY_HALF) ** 2,
            "beam_bottom": beam_bottom,
        },
    )


# An empty bay and a pile in it, for calibrating a walled installation: the floor and the walls
# in view of every wall camera. Both scenes place the cameras identically (same target, same
# wall layout), so a rig rendered in one is the same rig in the other. The region stops
# BAY_MARGIN_M short of the walls: a wall 6 m from a camera is seen with ~7 cm of depth noise
# along the ray, which scatters wall points up to ~0.2 m into the bay, and the fill spreads
# them; with the region 0.1 m inside the walls, the empty bay seen by A1 and A5 with their
# true poses read 0.50 m³ (30 % of the pile), 0.3 m inside 0.04 m³ (floor noise).
BAY_MARGIN_M = 0.3
BAY_WALL_TOP = 3.0
BAY_CEILING_Z = 2.8
BAY_CAMERA_Z = 2.6
BAY_TARGET = (0.0, 0.0, 0.0)  # the wall cameras aim at the middle of the bay's floor


def _bay_site(g: Grain) -> Site:
    return Site(
        region=square(BAY_HALF - BAY_MARGIN_M),
        floor_z=0.0,
        ceiling_z=BAY_CEILING_Z,
        bulk_density_t_m3=g.density_t_m3,
    )


def empty_scene(g: Grain) -> Scene:
    """The walled bay with nothing in it: floor at z = 0, walls up to BAY_WALL_TOP outside the
    region, volume 0. What a walled installation is calibrated on before it is filled."""
    return Scene(
        name="empty",
        grain=g,
        site=_bay_site(g),
        height=_bay(lambda x, y: np.zeros(np.broadcast(x, y).shape), BAY_WALL_TOP),
        extent=BAY_EXTENT,
        outer_z=None,
        volume_m3=0.0,
        target=BAY_TARGET,
        layout="wall",
        wall_half_m=BAY_HALF,
        wall_camera_z=BAY_CAMERA_Z,
        params={"wall_top": BAY_WALL_TOP, "region_half": BAY_HALF - BAY_MARGIN_M},
    )


def bay_cone_scene(g: Grain) -> Scene:
    """The paper's pile (~1.68 m³, a cone at the angle of repose) in the middle of the empty
    bay: 1.5 m of floor around it, every wall camera sees it, the floor and the walls."""
    radius = float((3 * PAPER_PILE_M3 / (np.pi * g.slope)) ** (1 / 3))
    peak = g.slope * radius
    return Scene(
        name="bay-cone",
        grain=g,
        site=_bay_site(g),
        height=_bay(lambda x, y: cone_height(x, y, (0.0, 0.0), radius, g.slope), BAY_WALL_TOP),
        extent=BAY_EXTENT,
        outer_z=None,
        volume_m3=float(np.pi * radius**2 * peak / 3),
        target=BAY_TARGET,
        layout="wall",
        wall_half_m=BAY_HALF,
        wall_camera_z=BAY_CAMERA_Z,
        params={
            "centre": (0.0, 0.0),
            "radius": radius,
            "height": peak,
            "wall_top": BAY_WALL_TOP,
            "region_half": BAY_HALF - BAY_MARGIN_M,
        },
    )


# ---------------------------------------------------------------- round bins

# A round steel bin: wall and conical roof (30 deg) in the world, eave cameras looking down and
# inward (layout "eave"), D455 noise at 2.5 times the ideal-target figure (~2 % at 4 m, the
# datasheet's bound for real surfaces), depth reported out to 20 m. The region is the wall.
BIN_SURFACE_FACTOR = 2.5
BIN_MAX_DEPTH_M = 20.0
BIN_RADIAL_SAMPLES = 400_000  # midpoints of the radial truth integral (error ~1e-9 relative)

Profile = Callable[[np.ndarray, np.ndarray], np.ndarray]


def heap_surface(level: float, radius: float, slope: float) -> Profile:
    """Centre-fill heap: grain `level` at the wall, a cone at the angle of repose over it."""
    return lambda x, y: level + np.maximum(0.0, slope * (radius - np.hypot(x, y)))


def crater_surface(level: float, radius: float, slope: float) -> Profile:
    """Draw-down crater: an inverted cone at the angle of repose over the centre outlet."""
    return lambda x, y: np.minimum(level, level - slope * (radius - np.hypot(x, y)))


def side_draw_surface(level: float, radius: float, slope: float, outlet: np.ndarray) -> Profile:
    """Side-draw: an inverted half-cone at the angle of repose against the wall outlet."""
    return lambda x, y: np.minimum(
        level, level - slope * (radius - np.hypot(x - outlet[0], y - outlet[1]))
    )


def radial_volume(shape: BinShape, surface: Profile) -> float:
    """Exact-to-rounding grain volume of an axisymmetric surface over the bin's bottom:
    integral of 2 pi r max(surface - bottom, 0) dr, midpoints of 400,000 rings."""
    r = (np.arange(BIN_RADIAL_SAMPLES) + 0.5) * (shape.radius_m / BIN_RADIAL_SAMPLES)
    zero = np.zeros_like(r)
    column = np.maximum(surface(r, zero) - shape.bottom(r, zero), 0.0)
    return float(np.sum(2 * np.pi * r * column) * shape.radius_m / BIN_RADIAL_SAMPLES)


def side_draw_volume(shape: BinShape, level: float, radius: float, slope: float) -> float:
    """A flat-bottom bin at `level` less the half-cone a wall outlet draws: around the outlet,
    the ring at distance d lies inside the wall over an angle 2 acos(d / 2R)."""
    big = shape.radius_m
    d = (np.arange(BIN_RADIAL_SAMPLES) + 0.5) * (radius / BIN_RADIAL_SAMPLES)
    drop = np.minimum(slope * (radius - d), level - shape.floor_z)
    arc = 2 * np.arccos(np.clip(d / (2 * big), -1, 1))
    removed = float(np.sum(drop * arc * d) * radius / BIN_RADIAL_SAMPLES)
    return np.pi * big * big * (level - shape.floor_z) - removed


def radial_extremes(
    shape: BinShape, surface: Profile, samples: int = 20_001
) -> tuple[float, float, float]:
    """Highest, lowest and area-weighted mean height of the grain surface where grain stands
    (bare floor or hopper steel is not grain)."""
    r = np.linspace(0.0, shape.radius_m, samples)
    zero = np.zeros_like(r)
    z = surface(r, zero)
    grain = z > shape.bottom(r, zero)
    weight = r * np.gradient(r) * grain
    top, low = float(z[grain].max()), float(z[grain].min())
    return top, low, float(np.sum(z * weight) / np.sum(weight))


def capacity_m3(shape: BinShape) -> float:
    """Volume from the bottom (hopper included) up to the eave, inside the wall."""
    return np.pi * shape.radius_m**2 * (shape.eave_z - shape.floor_z) + shape.hopper_volume_m3()


def _bin_scene(
    name: str,
    g: Grain,
    shape: BinShape,
    surface: Profile,
    volume_m3: float,
    extremes: tuple[float, float, float],
    params: dict[str, Any],
) -> Scene:
    big = shape.radius_m
    reach = big + 0.2
    cx, cy = shape.centre
    top, low, mean = extremes
    site = Site(
        region=shape.wall_polygon(),
        floor_z=shape.floor_z,
        ceiling_z=None,
        bulk_density_t_m3=g.density_t_m3,
        bin=shape,
    )

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.maximum(surface(x - cx, y - cy), shape.bottom(x, y))

    return Scene(
        name=name,
        grain=g,
        site=site,
        height=height,
        extent=(cx - reach, cx + reach, cy - reach, cy + reach),
        outer_z=None,
        volume_m3=volume_m3,
        target=(cx, cy, (top + low) / 2),
        layout="eave",
        wall_half_m=big,
        wall_camera_z=shape.eave_z - EAVE_DROP_M,
        params=params
        | {
            "diameter_m": shape.diameter_m,
            "eave_z": shape.eave_z,
            "capacity_m3": capacity_m3(shape),
            "grain_max_z": top,
            "grain_min_z": low,
            "grain_mean_z": mean,
        },
        bin=shape,
        surface_factor=BIN_SURFACE_FACTOR,
        max_depth_m=BIN_MAX_DEPTH_M,
        mesh_step_m=max(0.01, 2 * big / 500),
    )


EAVE_DROP_M = 0.3  # eave cameras hang this far under the eave


def bin_scene(
    g: Grain,
    *,
    name: str = "bin",
    diameter_m: float = 10.0,
    eave_m: float = 7.0,
    surface: str = "heap",
    level_m: float = 1.2,
    feature_radius_m: float = 3.0,
    hopper_angle_deg: float | None = None,
    outlet_diameter_m: float = 0.4,
    side_outlet_deg: float = 0.0,
) -> Scene:
    """A round bin of `diameter_m` with the eave `eave_m` above the floor plane (z = 0).

    `surface`: "heap" (grain at `level_m` by the wall, a centre-fill cone of `feature_radius_m`
    at the angle of repose on it), "crater" (grain at `level_m`, a draw-down cone of that
    radius over the centre outlet), "side" (a half-cone drawn at the wall at
    `side_outlet_deg`, flat floor only) or "level". A `hopper_angle_deg` puts a conical hopper
    (that slope from the horizontal, down to an outlet of `outlet_diameter_m`) under the floor
    plane; `level_m` may then be negative: the grain stands inside the hopper.
    """
    radius = diameter_m / 2
    if hopper_angle_deg is None:
        shape = BinShape(floor_z=0.0, eave_z=eave_m, diameter_m=diameter_m)
    else:
        depth = (radius - outlet_diameter_m / 2) * float(np.tan(np.radians(hopper_angle_deg)))
        shape = BinShape(
            floor_z=0.0,
            eave_z=eave_m,
            diameter_m=diameter_m,
            floor="hopper",
            hopper_depth_m=depth,
            outlet_diameter_m=outlet_diameter_m,
        )
    slope = g.slope
    params: dict[str, Any] = {"surface": surface, "level": level_m, "radius": feature_radius_m}
    if surface == "side":
        if shape.floor != "flat":
            raise ValueError("the side-draw scene has a flat floor")
        angle = np.radians(side_outlet_deg)
        outlet = radius * np.array([np.cos(angle), np.sin(angle)])
        profile = side_draw_surface(level_m, feature_radius_m, slope, outlet)
        volume = side_draw_volume(shape, level_m, feature_radius_m, slope)
        bottom = max(level_m - slope * feature_radius_m, shape.floor_z)
        # the mean over the disc, from the volume: the floor is flat and fully covered
        extremes = (level_m, bottom, shape.floor_z + volume / (np.pi * radius**2))
        params["outlet"] = tuple(outlet)
    else:
        if surface == "heap":
            profile = heap_surface(level_m, feature_radius_m, slope)
        elif surface == "crater":
            profile = crater_surface(level_m, feature_radius_m, slope)
        elif surface == "level":
            profile = heap_surface(level_m, 0.0, slope)
        else:
            raise ValueError(f"unknown bin surface {surface!r}")
        volume = radial_volume(shape, profile)
        extremes = radial_extremes(shape, profile)
    if hopper_angle_deg is not None:
        params |= {"hopper_angle_deg": hopper_angle_deg, "hopper_depth_m": shape.hopper_depth_m}
    return _bin_scene(name, g, shape, profile, volume, extremes, params)


_BUILDERS: dict[str, Callable[[Grain], Scene]] = {
    "cone": cone_scene,
    "piles": piles_scene,
    "ridge": ridge_scene,
    "crater": crater_scene,
    "full": full_scene,
    "flat": flat_scene,
    "empty": empty_scene,
    "bay-cone": bay_cone_scene,
    # the 10 m bin, walls 7 m: grain 0.9-2.7 m
    "bin-heap": lambda g: bin_scene(g, name="bin-heap", level_m=1.2, feature_radius_m=3.0),
    "bin-crater": lambda g: bin_scene(
        g, name="bin-crater", surface="crater", level_m=2.4, feature_radius_m=3.0
    ),
    "bin-side": lambda g: bin_scene(
        g, name="bin-side", surface="side", level_m=2.0, feature_radius_m=4.0
    ),
    # an 8 m hopper bin (45 deg cone, 0.4 m outlet, 3.8 m deep), eave 6 m above the floor plane
    "hopper-heap": lambda g: bin_scene(
        g,
        name="hopper-heap",
        diameter_m=8.0,
        eave_m=6.0,
        level_m=1.0,
        feature_radius_m=2.5,
        hopper_angle_deg=45.0,
    ),
    # the same bin drawn down: a crater inside the hopper, the cone's steel bare above it
    "hopper-low": lambda g: bin_scene(
        g,
        name="hopper-low",
        diameter_m=8.0,
        eave_m=6.0,
        surface="crater",
        level_m=-2.6 + g.slope * 3.0,
        feature_radius_m=3.0,
        hopper_angle_deg=45.0,
    ),
    # a larger bin: 18 m across, eave 12 m, a 3.5 m deep fill with a heap
    "bin-18": lambda g: bin_scene(
        g, name="bin-18", diameter_m=18.0, eave_m=12.0, level_m=3.5, feature_radius_m=6.0
    ),
}


@lru_cache(maxsize=8)
def make_scene(name: str, grain_name: str = "wheat") -> Scene:
    """The named scene for a grain; a ValueError names the known scenes."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    return _BUILDERS[name](grain(grain_name))
