"""`P/heightmap` as a robot reads it: decoded with the documentation's own numpy decoder (not the
package's), the volume integrated from the map agrees with the published volume, the header
says where the floor and the base are and when the scan was taken, and the grid_map recipe puts
every cell where grid_map's convention says it is."""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from silo_agent.analysis.scan_analysis import analyse
from silo_agent.config import DetectionConfig, ReconstructionConfig
from silo_agent.sim import make_scene, simulate
from silo_agent.telemetry.heightmap_codec import HEADER, decode_heightmap, encode_heightmap

ROOT = Path(__file__).resolve().parents[1]
MM = 0.0005  # a layer value is rounded to the millimetre


def documented_decoder() -> dict:
    """The `# SLHM decoder` block of the user documentation, executed as a user would."""
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    blocks = [
        m.group(1)
        for page in pages
        if page.is_file()
        for m in re.finditer(r"```python\n(# SLHM decoder.*?)```", page.read_text(), re.S)
    ]
    assert len(blocks) == 1, "the documentation has exactly one SLHM decoder"
    namespace: dict = {}
    exec(compile(blocks[0], "documented SLHM decoder", "exec"), namespace)
    return namespace


@pytest.fixture(scope="module")
def published():
    """A real result of the engine: a cone seen from two walls, 5 cm grid (the membrane fill,
    whose volume the comparisons with the naive integrals below were worked out on)."""
    scene = make_scene("cone", "wheat")
    scan = simulate(scene, ["A1", "A5"], 0, (0.0, 0.0), 0.05)
    settings = ReconstructionConfig.model_validate(scan.reconstruction | {"fill": "membrane"})
    result = analyse(scan, settings, DetectionConfig()).reconstruction
    return scan, result, encode_heightmap(result.heightmap, scan.scan_id)


def test_volume_integrated_from_the_decoded_map_is_the_published_volume(published) -> None:
    scan, result, blob = published
    doc = documented_decoder()
    m = doc["decode"](blob)
    assert blob[4] == 2 and m["scan_id"] == scan.scan_id and m["frame"] == "silo"
    assert m["captured_at"] == scan.captured_at
    assert m["floor_z"] == scan.site.floor_z
    assert m["base"] == (0.0, 0.0, scan.site.floor_z)  # base = "floor"

    volume = doc["volume_m3"](m)
    # Only rounding separates them: counted to the millimetre (uniform error, variance
    # 1 mm²/12) and inside to 1/255 (variance (1/255)²/12), independent cell to cell, so the
    # sum's error has sigma = step² sqrt(sum(inside² mm²/12 + counted² /(12 x 255²))); allow 6.
    counted, inside = np.nan_to_num(m["counted"]), m["inside"]
    sigma = m["step"] ** 2 * float(
        np.sqrt(np.sum(inside**2 * 1e-6 / 12 + counted**2 / (12 * 255**2)))
    )
    assert abs(volume - result.volume_m3) <= 6 * sigma
    assert 6 * sigma < 5e-4 * result.volume_m3  # tight: the old 0.2 % gap would not pass
    bound = 6 * sigma

    # why the layer is needed: neither naive integral of the surface is the published volume
    # (the clip at the base counts the floor's noise; the volume's correction of it, reading
    # the default depth noise factor 2.5 on this ideal-noise scene, takes a little more than
    # that off, bounded by min(smooth, 0) a cell: under the signed sum here)
    above = np.nan_to_num(m["z"] - m["floor_z"])
    clipped = m["step"] ** 2 * float(np.sum(np.maximum(above, 0.0) * inside))
    signed = m["step"] ** 2 * float(np.sum(above * inside))
    assert clipped - result.volume_m3 > 3 * bound and abs(result.volume_m3 - signed) > bound


def test_grid_map_recipe_puts_every_cell_where_grid_map_looks(published) -> None:
    """grid_map: position = map centre; cell (i, j) centre = position + length/2 -
    (index + 0.5) * resolution on each axis (x along i, y along j)."""
    _scan, result, blob = published
    doc = documented_decoder()
    m = doc["decode"](blob)
    data, position, length = doc["to_grid_map"](m["z"], m)
    assert data.shape == (m["cols"], m["rows"])  # grid_map size = (cells along x, along y)
    i, j = np.meshgrid(np.arange(data.shape[0]), np.arange(data.shape[1]), indexing="ij")
    x = position[0] + length[0] / 2 - (i + 0.5) * m["step"]
    y = position[1] + length[1] / 2 - (j + 0.5) * m["step"]
    hm = result.heightmap
    expected = np.array([hm.height_at(a, b) for a, b in zip(x.ravel(), y.ravel(), strict=True)])
    got = data.ravel()
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    known = ~np.isnan(expected)
    assert np.max(np.abs(got[known] - expected[known])) <= MM + 1e-6  # float32 heights
    # the max-x, max-y corner cell is grid_map's index (0, 0)
    assert np.array_equal(data[0, 0], m["z"][-1, -1], equal_nan=True)


def test_version_1_maps_still_decode_and_version_2_extends_version_1(published) -> None:
    """A version-1 map (no extension) decodes, the extension's fields None; a version-1
    reader that ignores trailing bytes reads a version-2 map's heights unchanged."""
    _scan, result, blob = published
    fields = list(HEADER.unpack_from(blob))
    end = HEADER.size + sum(fields[12:17])  # frame, scan id and the three layers
    fields[1] = 1
    v1 = HEADER.pack(*fields) + blob[HEADER.size : end]
    old = decode_heightmap(v1)
    assert old.counted is None and old.floor_z is None and old.captured_at is None
    new = decode_heightmap(blob)
    np.testing.assert_array_equal(old.heights, new.heights)
    np.testing.assert_array_equal(old.inside, new.inside)
    # the version-1 reading of the heights layer, at the offsets version 1 documented
    rows, cols = struct.unpack_from("<II", blob, 8)
    z0, unknown, nf, ns, nh = struct.unpack_from("<dHHHI", blob, 40)
    pos = 66 + nf + ns
    codes = np.cumsum(
        np.frombuffer(zlib.decompress(blob[pos : pos + nh]), "<u2").reshape(rows, cols),
        axis=1,
        dtype=np.uint16,
    )
    np.testing.assert_array_equal(
        np.where(codes == unknown, np.nan, z0 + codes / 1000.0), new.heights
    )
    assert new.counted is not None and new.captured_at == result.heightmap.captured_at
