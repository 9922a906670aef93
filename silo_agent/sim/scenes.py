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

from silo_agent.grid.geometry import cell_fractions
from silo_agent.scan import Site
from silo_agent.sim.grains import Grain, grain

HeightField = Callable[[np.ndarray, np.ndarray], np.ndarray]

SCENES = ("cone", "piles", "ridge", "crater", "full", "flat", "empty", "bay-cone")
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
        return out


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


_BUILDERS: dict[str, Callable[[Grain], Scene]] = {
    "cone": cone_scene,
    "piles": piles_scene,
    "ridge": ridge_scene,
    "crater": crater_scene,
    "full": full_scene,
    "flat": flat_scene,
    "empty": empty_scene,
    "bay-cone": bay_cone_scene,
}


@lru_cache(maxsize=8)
def make_scene(name: str, grain_name: str = "wheat") -> Scene:
    """The named scene for a grain; a ValueError names the known scenes."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENES)}")
    return _BUILDERS[name](grain(grain_name))
