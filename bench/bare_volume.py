"""The least a Python process can do for a round bin's 2.5D volume: what CloudCompare's
`-VOLUME` computes, in numpy, with nothing of the agent's method. bench/floor.py times it as a
whole process against CloudCompare and `silo-agent process`.

Usage: python bench/bare_volume.py SCAN_DIR STEP

Reads the manifest and each camera's PLY (x, y, z float32 only, as the simulator writes them)
straight into an array, moves the points into the silo frame, keeps those inside the bin's
circle, takes each cell's mean height, fills the empty cells from the nearest measured one
(scipy's distance transform) and sums over the cells inside the circle. No wall test, no noise
handling, no trust, no clustering, no membrane: it reads the wall as grain, as CloudCompare
does. Prints one JSON line: the volume and the points kept.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

END_HEADER = b"end_header\n"


def main() -> None:
    directory, step = Path(sys.argv[1]), float(sys.argv[2])
    manifest = json.loads((directory / "scan.json").read_text())
    site = manifest["site"]
    shape = site["bin"]
    (cx, cy), radius = shape["centre"], shape["diameter_m"] / 2
    clouds = []
    for camera in manifest["cameras"]:
        body = (directory / camera["cloud"]).read_bytes()
        header = body[: body.index(END_HEADER)].decode("ascii")
        if header.count("property") != 3 or "property float z" not in header:
            raise SystemExit(f"{camera['cloud']}: only x, y, z float32 PLYs are read here")
        start = body.index(END_HEADER) + len(END_HEADER)
        points = np.frombuffer(body, np.float32, offset=start).reshape(-1, 3)
        pose = np.asarray(camera["extrinsic"], np.float32)
        clouds.append(points @ pose[:3, :3].T + pose[:3, 3])
    points = np.concatenate(clouds)
    del clouds
    x, y, z = points[:, 0] - cx, points[:, 1] - cy, points[:, 2]
    keep = (x * x + y * y < radius * radius) & np.isfinite(z)
    x, y, z = x[keep], y[keep], z[keep]
    side = int(np.ceil(2 * radius / step))
    col = np.clip(((x + radius) / step).astype(np.intp), 0, side - 1)
    row = np.clip(((y + radius) / step).astype(np.intp), 0, side - 1)
    cell = row * side + col
    count = np.bincount(cell, minlength=side * side)
    total = np.bincount(cell, z, side * side)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = (total / count).reshape(side, side)  # NaN where no point fell
    nearest = ndimage.distance_transform_edt(
        np.isnan(height), return_distances=False, return_indices=True
    )
    height = height[tuple(nearest)]
    centres = -radius + (np.arange(side) + 0.5) * step
    inside = centres[None, :] ** 2 + centres[:, None] ** 2 < radius * radius
    volume = float(np.sum(height[inside] - site["floor_z"]) * step * step)
    print(json.dumps({"volume_m3": volume, "points": len(z)}))


if __name__ == "__main__":
    main()
