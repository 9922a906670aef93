"""Binary wire format of `P/heightmap` ("SLHM" version 2), small enough to retain on a broker.

Everything a robot needs to place a cell, and to integrate the published volume from the map,
is in the message, so nobody has to guess the origin, the row order, the base or what
"unknown" looks like (the usual complaints about grid maps).

Layout, little-endian. Version 2 is version 1 (offsets 0 to the end of the inside layer are
unchanged) followed by an extension, so a version-1 decoder that ignores trailing bytes still
reads a version-2 map:

    offset size  field
    0      4     magic b"SLHM"
    4      1     version = 2 (1: no extension)
    5      1     height encoding: 1 = uint16 millimetres above z_offset_m
    6      1     filter: 1 = per-row horizontal difference modulo 2**16 (undo with a cumsum)
    7      1     flags: bit 0 = row 0 is the minimum-y row, bit 1 = origin is the outer corner
    8      4     rows (uint32), cells along +y
    12     4     cols (uint32), cells along +x
    16     8     step_m (float64), cell size
    24     8     origin_x_m (float64), silo-frame x of the outer (min x, min y) corner of cell [0,0]
    32     8     origin_y_m (float64)
    40     8     z_offset_m (float64), silo-frame z of height code 0
    48     2     unknown code (uint16) = 65535: no surface (outside the region)
    50     2     frame id length F (uint16)
    52     2     scan id length S (uint16)
    54     4     heights blob length H (uint32)
    58     4     observed blob length O (uint32)
    62     4     inside blob length I (uint32)
    66     F     frame id, UTF-8 ("silo": the silo frame, z up, metres)
           S     scan id, UTF-8
           H     zlib(uint16[rows, cols] after the filter), row-major
           O     zlib(numpy.packbits(observed, bitorder="big")), row-major, 1 = measured,
                 0 = filled by interpolation or unknown
           I     zlib(uint8[rows, cols] round(inside * 255)): fraction of the cell inside the region
    E = 66+F+S+H+O+I, the version-2 extension:
    E      8     floor_z_m (float64), silo-frame z of the floor (level = z - floor_z); NaN unknown
    E+8    24    base_a, base_b, base_c (float64): the volume's base, z = a*x + b*y + c; NaN unknown
    E+32   8     counted_offset_m (float64): value of counted code 0
    E+40   2     captured_at length T (uint16)
    E+42   4     counted blob length C (uint32); 0 = no counted layer
    E+46   T     captured_at, UTF-8 RFC 3339 (when the scan was taken)
           C     zlib(uint16[rows, cols] after the filter), row-major: per cell, millimetres
                 above counted_offset_m of the height above the base that the published volume
                 counts; volume_m3 = step**2 * sum(counted * inside)

Heights and counted heights are rounded to the millimetre, so a decoded value is within
0.5 mm of the published one; unknown cells decode to NaN.
"""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np

from silo_agent.heightmap import HeightMap

MAGIC = b"SLHM"
VERSION = 2
VERSIONS = (1, 2)  # what the decoder reads
ENCODING_UINT16_MM = 1
FILTER_ROW_DELTA = 1
FLAG_ROW0_MIN_Y = 1
FLAG_ORIGIN_OUTER_CORNER = 2
UNKNOWN = 0xFFFF
FRAME_ID = "silo"
HEADER = struct.Struct("<4sBBBBIIddddHHHIII")
EXTENSION = struct.Struct("<dddddHI")  # version 2, after the inside layer
MAX_RANGE_M = (UNKNOWN - 1) / 1000.0


class HeightMapFormatError(ValueError):
    """Bytes that are not a height map this decoder understands."""


def _codes(values: np.ndarray, what: str) -> tuple[float, bytes]:
    """(offset, zlib blob) of values in millimetres above the offset, row-delta filtered."""
    values = np.asarray(values, dtype=np.float64)
    known = np.isfinite(values)
    if known.any():
        offset = math.floor(float(values[known].min()) * 1000.0) / 1000.0
        span = float(values[known].max()) - offset
        if span > MAX_RANGE_M:
            raise ValueError(f"{what} span {span:.3f} m, the format holds {MAX_RANGE_M} m")
    else:
        offset = 0.0
    codes = np.full(values.shape, UNKNOWN, dtype=np.uint16)
    codes[known] = np.rint((values[known] - offset) * 1000.0).astype(np.uint16)
    filtered = codes.copy()
    filtered[:, 1:] = codes[:, 1:] - codes[:, :-1]  # uint16 arithmetic wraps: modulo 2**16
    return offset, zlib.compress(filtered.astype("<u2").tobytes(), 9)


def _values(blob: bytes, offset: float, unknown: int, rows: int, cols: int) -> np.ndarray:
    filtered = np.frombuffer(blob, dtype="<u2").reshape(rows, cols)
    codes = np.cumsum(filtered, axis=1, dtype=np.uint16)
    return np.where(codes == unknown, np.nan, offset + codes / 1000.0)


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def encode_heightmap(hm: HeightMap, scan_id: str, frame_id: str = FRAME_ID) -> bytes:
    """Encode a height map; raises ValueError if its heights span more than 65.534 m."""
    rows, cols = hm.shape
    z_offset, heights_blob = _codes(hm.heights, "heights")
    observed_blob = zlib.compress(
        np.packbits(np.asarray(hm.observed, dtype=bool).ravel(), bitorder="big").tobytes(), 9
    )
    inside = np.clip(np.rint(np.asarray(hm.inside, dtype=np.float64) * 255.0), 0, 255)
    inside_blob = zlib.compress(inside.astype(np.uint8).tobytes(), 9)
    counted_offset, counted_blob = 0.0, b""
    if hm.counted is not None:
        counted_offset, counted_blob = _codes(hm.counted, "counted heights")
    base = hm.base or (None, None, None)
    frame = frame_id.encode()
    scan = scan_id.encode()
    captured = (hm.captured_at or "").encode()
    header = HEADER.pack(
        MAGIC, VERSION, ENCODING_UINT16_MM, FILTER_ROW_DELTA,
        FLAG_ROW0_MIN_Y | FLAG_ORIGIN_OUTER_CORNER, rows, cols, float(hm.step),
        float(hm.origin[0]), float(hm.origin[1]), z_offset, UNKNOWN, len(frame), len(scan),
        len(heights_blob), len(observed_blob), len(inside_blob),
    )  # fmt: skip
    extension = EXTENSION.pack(
        _or_nan(hm.floor_z), *(_or_nan(v) for v in base), counted_offset, len(captured),
        len(counted_blob),
    )  # fmt: skip
    return b"".join([header, frame, scan, heights_blob, observed_blob, inside_blob, extension,
                     captured, counted_blob])  # fmt: skip


def _known(value: float) -> float | None:
    return None if math.isnan(value) else value


def decode_heightmap_with_ids(data: bytes) -> tuple[HeightMap, str, str]:
    """Decode version 1 or 2 to (height map, scan id, frame id); what version 1 lacks (floor,
    base, counted heights, capture time) is None."""
    if len(data) < HEADER.size or data[:4] != MAGIC:
        raise HeightMapFormatError("not an SLHM height map (bad magic or too short)")
    (
        _magic, version, encoding, filt, flags, rows, cols, step, ox, oy, z_offset,
        unknown, f_len, s_len, h_len, o_len, i_len,
    ) = HEADER.unpack_from(data)  # fmt: skip
    if version not in VERSIONS or encoding != ENCODING_UINT16_MM or filt != FILTER_ROW_DELTA:
        raise HeightMapFormatError(
            f"unsupported SLHM version {version} / encoding {encoding} / filter {filt}"
        )
    if flags != FLAG_ROW0_MIN_Y | FLAG_ORIGIN_OUTER_CORNER:
        raise HeightMapFormatError(f"unsupported SLHM flags {flags:#x}")
    pos = HEADER.size
    frame = data[pos : pos + f_len].decode()
    pos += f_len
    scan_id = data[pos : pos + s_len].decode()
    pos += s_len
    blobs = []
    for length in (h_len, o_len, i_len):
        blobs.append(data[pos : pos + length])
        pos += length
    floor_z = base = captured_at = None
    counted_offset, counted_blob = 0.0, b""
    if version >= 2:
        if len(data) < pos + EXTENSION.size:
            raise HeightMapFormatError("length mismatch: the version 2 extension is cut short")
        floor, a, b, c, counted_offset, t_len, c_len = EXTENSION.unpack_from(data, pos)
        pos += EXTENSION.size
        floor_z = _known(floor)
        base = None if math.isnan(c) else (a, b, c)
        captured_at = data[pos : pos + t_len].decode() or None
        pos += t_len
        counted_blob = data[pos : pos + c_len]
        pos += c_len
    if pos != len(data):
        raise HeightMapFormatError(f"length mismatch: header says {pos} bytes, got {len(data)}")
    try:
        raw = [zlib.decompress(b) for b in blobs]
        counted_raw = zlib.decompress(counted_blob) if counted_blob else None
    except zlib.error as exc:
        raise HeightMapFormatError(f"corrupt compressed layer: {exc}") from None
    n = rows * cols
    if (len(raw[0]) != 2 * n or len(raw[1]) != (n + 7) // 8 or len(raw[2]) != n
            or (counted_raw is not None and len(counted_raw) != 2 * n)):  # fmt: skip
        raise HeightMapFormatError("layer sizes do not match rows x cols")
    observed = np.unpackbits(np.frombuffer(raw[1], dtype=np.uint8), count=n, bitorder="big")
    counted = None
    if counted_raw is not None:
        counted = _values(counted_raw, counted_offset, unknown, rows, cols)
    hm = HeightMap(
        origin=(ox, oy),
        step=step,
        heights=_values(raw[0], z_offset, unknown, rows, cols),
        observed=observed.reshape(rows, cols).astype(bool),
        inside=np.frombuffer(raw[2], dtype=np.uint8).reshape(rows, cols) / 255.0,
        floor_z=floor_z,
        base=base,
        counted=counted,
        captured_at=captured_at,
    )
    return hm, scan_id, frame


def decode_heightmap(data: bytes) -> HeightMap:
    """Decode `P/heightmap` bytes to a HeightMap (heights to the millimetre, NaN unknown)."""
    return decode_heightmap_with_ids(data)[0]
