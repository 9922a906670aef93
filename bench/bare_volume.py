"""The least a Python process can do for a scan's 2.5D volume: what CloudCompare's `-VOLUME`
computes, in numpy, with nothing of the agent's method. bench/floor.py times it as a whole
process against CloudCompare and `silo-agent process`.

Usage: python bench/bare_volume.py STEP SCAN_DIR [SCAN_DIR ...]

For each scan: reads the manifest and each camera's PLY (x, y, z float32 only, as the
simulator writes them) straight into an array, moves the points into the silo frame, keeps
those under the ceiling and in the region's box, takes each cell's mean height, fills the
empty cells from the nearest measured one (scipy's distance transform) and sums over the cells
inside the region (a bin's circle, or an axis-aligned rectangle). No wall test, no noise
handling, no trust, no clustering, no membrane: it reads a wall as grain, as CloudCompare does.
Prints one JSON line a scan: its directory, volume and cells with a point. Its heap is set up
as `process` sets up its own (silo_agent/base/heap.py: freed blocks reused, no huge-page
advice), so neither pays page faults the other does not.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from silo_agent.base.heap import keep_freed_memory, small_pages

small_pages()  # before numpy is imported
keep_freed_memory()

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

END_HEADER = b"end_header\n"


def read_points(directory: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """(every camera's points in the silo frame, float32 (N, 3); the manifest's site): each
    PLY's body read straight into its array."""
    manifest = json.loads((directory / "scan.json").read_text())
    clouds = []
    for camera in manifest["cameras"]:
        path = directory / camera["cloud"]
        with path.open("rb") as f:
            head = f.read(4096)
        end = head.index(END_HEADER)
        header = head[:end].decode("ascii")
        if header.count("property") != 3 or "property float z" not in header:
            raise SystemExit(f"{camera['cloud']}: only x, y, z float32 PLYs are read here")
        points = np.fromfile(path, np.float32, offset=end + len(END_HEADER)).reshape(-1, 3)
        pose = np.asarray(camera["extrinsic"], np.float32)
        clouds.append(points @ pose[:3, :3].T + pose[:3, 3])
    return np.concatenate(clouds), manifest["site"]


def _bounds(site: dict[str, Any]) -> tuple[float, float, float, float, float | None]:
    """(x0, y0, x1, y1, radius): a bin's circle's box and radius, or the rectangle's, None."""
    shape = site.get("bin")
    if shape and shape.get("diameter_m"):
        (cx, cy), radius = shape["centre"], shape["diameter_m"] / 2
        return cx - radius, cy - radius, cx + radius, cy + radius, radius
    region = np.asarray(site["region"], dtype=np.float64)
    x0, y0 = region.min(axis=0)
    x1, y1 = region.max(axis=0)
    on_box = np.isin(region[:, 0], (x0, x1)) & np.isin(region[:, 1], (y0, y1))
    if len(region) != 4 or not np.all(on_box):
        raise SystemExit("the region must be a bin's circle or an axis-aligned rectangle")
    return float(x0), float(y0), float(x1), float(y1), None


def cell_means(
    points: np.ndarray, site: dict[str, Any], step: float
) -> tuple[np.ndarray, np.ndarray]:
    """(each cell's mean height, NaN where no point fell; the cells whose centre is inside).
    Points are cropped to the region's box and under the ceiling; the circle is a test on the
    cells, not on every point."""
    x0, y0, x1, y1, radius = _bounds(site)
    cols, rows = int(np.ceil((x1 - x0) / step)), int(np.ceil((y1 - y0) / step))
    col = points[:, 0] - np.float32(x0)
    col *= np.float32(1 / step)
    row = points[:, 1] - np.float32(y0)
    row *= np.float32(1 / step)
    z = points[:, 2]
    keep = (col >= 0) & (col < cols) & (row >= 0) & (row < rows) & np.isfinite(z)
    if site.get("ceiling_z") is not None:
        keep &= z < site["ceiling_z"]
    cell = row[keep].astype(np.intp)
    cell *= cols
    cell += col[keep].astype(np.intp)
    count = np.bincount(cell, minlength=rows * cols)
    total = np.bincount(cell, z[keep], rows * cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = (total / count).reshape(rows, cols)
    xs = x0 + (np.arange(cols) + 0.5) * step
    ys = y0 + (np.arange(rows) + 0.5) * step
    inside = (xs[None, :] <= x1) & (ys[:, None] <= y1)
    if radius is not None:
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        inside = (xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2 < radius * radius
    return height, inside


def bare_volume(directory: Path, step: float) -> tuple[float, int]:
    """(the scan's volume above its floor, its cells with a point)."""
    points, site = read_points(directory)
    height, inside = cell_means(points, site, step)
    nearest = ndimage.distance_transform_edt(
        np.isnan(height), return_distances=False, return_indices=True
    )
    filled = height[tuple(nearest)]
    volume = float(np.sum(filled[inside] - site["floor_z"]) * step * step)
    return volume, int(np.count_nonzero(np.isfinite(height)))


def main() -> None:
    if len(sys.argv) < 3 or sys.argv[1].startswith("-"):  # no argparse: a bare process
        sys.exit(__doc__.split("\n\n")[1])
    step = float(sys.argv[1])
    for directory in map(Path, sys.argv[2:]):
        volume, cells = bare_volume(directory, step)
        print(json.dumps({"scan_dir": str(directory), "volume_m3": volume, "cells": cells}))


if __name__ == "__main__":
    main()
