"""The choices and defaults that both the config file and the command-line flags offer, in a
module with no imports beyond `typing`, so that `silo-agent --help` and `process` can name them
without loading pydantic. `config.py` builds its fields from these; the flags read them."""

from typing import Literal, get_args

Method = Literal["bicm", "rectangle", "alpha", "poisson", "hull"]
Grain = Literal["wheat", "corn", "soybeans", "rice"]
Layout = Literal["paper", "wall", "eave"]

METHODS: tuple[str, ...] = get_args(Method)
GRAINS: tuple[str, ...] = get_args(Grain)
LAYOUTS: tuple[str, ...] = get_args(Layout)

DEFAULT_METHOD: Method = "bicm"
DEFAULT_GRID_STEP_M = 0.02
DEFAULT_GRAIN: Grain = "wheat"
DEFAULT_LAYOUT: Layout = "paper"

# Angle of repose (degrees) per grain: the steepest a free grain surface stands, which shapes
# the simulator's piles and bounds the reconstruction's fill of unseen cells. design.md's
# ranges (wheat 25-27, rice 30-40: the middle of the range).
REPOSE_DEG: dict[str, float] = {"wheat": 26.0, "corn": 23.0, "soybeans": 25.0, "rice": 35.0}

# The D455 sensor model's depth range (metres along the optical axis): the capture's threshold
# filter, and what a scan reader keeps of a cloud whose manifest does not give its own range.
DEFAULT_MIN_DEPTH_M = 0.3
DEFAULT_MAX_DEPTH_M = 10.0

# The simulator's camera positions (the paper's A1-A8: midpoints A1 A3 A5 A7, corners A2 A4 A6
# A8, counter-clockwise from the middle of the -y side); a sim camera's `view` names one.
VIEW_NAMES: tuple[str, ...] = ("A1", "A2", "A3", "A4", "A5", "A6", "A7", "A8")

# The simulator's scene library (sim/scenes.py builds each; the bin scenes are round bins), each
# with the camera layouts that place all of A1-A8 in it, whatever the grain: a paper camera
# stands 1 m over the floor, under the grain of the deeper scenes, and the eave layout needs a
# round bin. The config refuses any other layout before a capture fails on it, the simulator
# refuses it too, and tests/test_sim_layouts.py renders every scene and layout against this.
SCENE_LAYOUTS: dict[str, tuple[Layout, ...]] = {
    "cone": ("paper", "wall"),
    "piles": ("paper", "wall"),
    "ridge": ("paper", "wall"),
    "crater": ("wall",),
    "full": ("wall",),
    "flat": ("wall",),
    "empty": ("paper", "wall"),
    "bay-cone": ("paper", "wall"),
    "bin-heap": ("wall", "eave"),
    "bin-crater": ("wall", "eave"),
    "bin-side": ("wall", "eave"),
    "hopper-heap": ("wall", "eave"),
    "hopper-low": ("paper", "wall", "eave"),
    "bin-18": ("wall", "eave"),
}
SCENE_NAMES: tuple[str, ...] = tuple(SCENE_LAYOUTS)

# The site each scene stands on: the `site` its scans carry (region, floor_z, ceiling_z, base,
# bin) and the building around it, where the layouts hang the cameras. A `[simulation]
# sequence` is one silo whose grain changes scan after scan, its cameras kept where its first
# scene places them, so all its scenes are of one site: the config refuses a sequence that
# mixes sites (its later scenes were rendered from the first site's camera places).
# tests/test_sim_layouts.py checks this table against the scenes' own sites.
SCENE_SITES: dict[str, str] = {
    "cone": "open floor",
    "piles": "open floor",
    "ridge": "open floor",
    "crater": "6 m bay, region wall to wall",
    "flat": "6 m bay, region wall to wall",
    "full": "6 m bay under a roof",
    "empty": "6 m bay, region 0.3 m inside the walls",
    "bay-cone": "6 m bay, region 0.3 m inside the walls",
    "bin-heap": "10 m bin",
    "bin-crater": "10 m bin",
    "bin-side": "10 m bin",
    "hopper-heap": "8 m hopper bin",
    "hopper-low": "8 m hopper bin",
    "bin-18": "18 m bin",
}


def layout_misfit(scene: str, layout: str) -> str | None:
    """Why `layout` cannot place the cameras in the library scene `scene`, or None when it can.
    A scene outside the library (the moving robot's bay) is left to the simulator's geometry."""
    fits = SCENE_LAYOUTS.get(scene)
    if fits is None or layout in fits:
        return None
    return f"layout {layout!r} does not fit scene {scene!r} (it fits {', '.join(fits)})"


def site_misfit(first: str, scene: str) -> str | None:
    """Why library scene `scene` cannot follow `first` in a sequence (another site), or None."""
    if SCENE_SITES[scene] == SCENE_SITES[first]:
        return None
    return (
        f"scene {scene!r} ({SCENE_SITES[scene]}) is not of the site of the sequence's first "
        f"scene {first!r} ({SCENE_SITES[first]}): a sequence is one silo whose grain changes, "
        "its cameras where its first scene places them"
    )
