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

Live maps (`P/heightmap/live`) set flag bit 2 (FLAG_LIVE) and append, after the version-2
extension (a live map has no counted layer: C = 0):

    4      sequence (uint32), +1 per live map of the agent, wrapping at 2**32
    4      metadata length M (uint32)
    M      metadata, UTF-8 JSON object (time, session, robots, rate)
    1      layer count L (uint8), then per layer:
    1        name length N (uint8)
    N        name, UTF-8 ("changed": since the previous live map, "held": the robot's footprint
             plus margin, whose cells keep their last good value)
    4        blob length B (uint32)
    B        zlib(numpy.packbits(layer, bitorder="big")), row-major, 1 = set

`decode_heightmap` reads the height map of either kind; `decode_live_heightmap` the rest too.

Heights and counted heights are rounded to the millimetre, so a decoded value is within
0.5 mm of the published one; unknown cells decode to NaN.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from silo_agent.grid.heightmap import HeightMap

MAGIC = b"SLHM"
VERSION = 2
VERSIONS = (1, 2)  # what the decoder reads
ENCODING_UINT16_MM = 1
FILTER_ROW_DELTA = 1
FLAG_ROW0_MIN_Y = 1
FLAG_ORIGIN_OUTER_CORNER = 2
FLAG_LIVE = 4
LIVE_HEADER = struct.Struct("<II")
UNKNOWN = 0xFFFF
FRAME_ID = "silo"
HEADER = struct.Struct("<4sBBBBIIddddHHHIII")
EXTENSION = struct.Struct("<dddddHI")  # version 2, after the inside layer
MAX_RANGE_M = (UNKNOWN - 1) / 1000.0


class HeightMapFormatError(ValueError):
    """Bytes that are not a height map this decoder understands."""


def _codes(values: np.ndarray, what: str, level: int = 9) -> tuple[float, bytes]:
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
    return offset, zlib.compress(filtered.astype("<u2").tobytes(), level)


def _values(blob: bytes, offset: float, unknown: int, rows: int, cols: int) -> np.ndarray:
    filtered = np.frombuffer(blob, dtype="<u2").reshape(rows, cols)
    codes = np.cumsum(filtered, axis=1, dtype=np.uint16)
    return np.where(codes == unknown, np.nan, offset + codes / 1000.0)


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def encode_heightmap(
    hm: HeightMap, scan_id: str, frame_id: str = FRAME_ID, flags: int = 0, level: int = 9
) -> bytes:
    """Encode a height map; raises ValueError if its heights span more than 65.534 m.
    `level` is zlib's: 9 for a retained map sent once, lower for live maps sent twice a
    second."""
    rows, cols = hm.shape
    z_offset, heights_blob = _codes(hm.heights, "heights", level)
    observed_blob = zlib.compress(
        np.packbits(np.asarray(hm.observed, dtype=bool).ravel(), bitorder="big").tobytes(), level
    )
    inside = np.clip(np.rint(np.asarray(hm.inside, dtype=np.float64) * 255.0), 0, 255)
    inside_blob = zlib.compress(inside.astype(np.uint8).tobytes(), level)
    counted_offset, counted_blob = 0.0, b""
    if hm.counted is not None:
        counted_offset, counted_blob = _codes(hm.counted, "counted heights", level)
    base = hm.base or (None, None, None)
    frame = frame_id.encode()
    scan = scan_id.encode()
    captured = (hm.captured_at or "").encode()
    header = HEADER.pack(
        MAGIC,
        VERSION,
        ENCODING_UINT16_MM,
        FILTER_ROW_DELTA,
        FLAG_ROW0_MIN_Y | FLAG_ORIGIN_OUTER_CORNER | flags,
        rows,
        cols,
        float(hm.step),
        float(hm.origin[0]),
        float(hm.origin[1]),
        z_offset,
        UNKNOWN,
        len(frame),
        len(scan),
        len(heights_blob),
        len(observed_blob),
        len(inside_blob),
    )
    extension = EXTENSION.pack(
        _or_nan(hm.floor_z),
        *(_or_nan(v) for v in base),
        counted_offset,
        len(captured),
        len(counted_blob),
    )
    return b"".join(
        [
            header,
            frame,
            scan,
            heights_blob,
            observed_blob,
            inside_blob,
            extension,
            captured,
            counted_blob,
        ]
    )


def _known(value: float) -> float | None:
    return None if math.isnan(value) else value


LIVE_LEVEL = 1  # zlib level of live maps: 2 a second, on one core, made and sent


def _packed(mask: np.ndarray) -> bytes:
    return zlib.compress(
        np.packbits(np.asarray(mask, dtype=bool).ravel(), bitorder="big").tobytes(), LIVE_LEVEL
    )


def encode_live_heightmap(
    hm: HeightMap, session_id: str, sequence: int, meta: dict, layers: dict[str, np.ndarray]
) -> bytes:
    """A live map: the SLHM height map with FLAG_LIVE, then sequence, metadata and bit layers."""
    parts = [encode_heightmap(hm, session_id, flags=FLAG_LIVE, level=LIVE_LEVEL)]
    text = json.dumps(meta, separators=(",", ":")).encode()
    parts.append(LIVE_HEADER.pack(sequence % 2**32, len(text)) + text + bytes([len(layers)]))
    for name, mask in layers.items():
        if np.shape(mask) != hm.shape:
            raise ValueError(f"layer {name!r} is {np.shape(mask)}, the map {hm.shape}")
        blob, label = _packed(mask), name.encode()
        parts.append(bytes([len(label)]) + label + struct.pack("<I", len(blob)) + blob)
    return b"".join(parts)


@dataclass(frozen=True)
class LiveHeightMap:
    """A decoded `P/heightmap/live` message."""

    heightmap: HeightMap
    session_id: str
    sequence: int
    meta: dict
    layers: dict[str, np.ndarray]


def decode_live_heightmap(data: bytes) -> LiveHeightMap:
    """Decode a live map; HeightMapFormatError if it is not one or is cut short."""
    hm, session_id, _frame, end = _decode(data)
    if not HEADER.unpack_from(data)[4] & FLAG_LIVE:
        raise HeightMapFormatError("not a live height map (flag bit 2 clear)")
    try:
        sequence, meta_len = LIVE_HEADER.unpack_from(data, end)
        pos = end + LIVE_HEADER.size
        meta = json.loads(data[pos : pos + meta_len])
        pos += meta_len
        count = data[pos]
        pos += 1
        layers = {}
        for _ in range(count):
            n = data[pos]
            name = data[pos + 1 : pos + 1 + n].decode()
            (size,) = struct.unpack_from("<I", data, pos + 1 + n)
            pos += 5 + n
            bits = np.unpackbits(
                np.frombuffer(zlib.decompress(data[pos : pos + size]), np.uint8),
                count=hm.heights.size,
                bitorder="big",
            )
            layers[name] = bits.reshape(hm.shape).astype(bool)
            pos += size
    except (struct.error, IndexError, ValueError, zlib.error) as exc:
        raise HeightMapFormatError(f"corrupt live map extension: {exc}") from None
    if pos != len(data):
        raise HeightMapFormatError(f"length mismatch: live map ends at {pos}, got {len(data)}")
    return LiveHeightMap(hm, session_id, sequence, meta, layers)


def decode_heightmap_with_ids(data: bytes) -> tuple[HeightMap, str, str]:
    """Decode version 1 or 2 to (height map, scan id, frame id); what version 1 lacks (floor,
    base, counted heights, capture time) is None. A live map's extension is not read."""
    hm, scan_id, frame, end = _decode(data)
    if end != len(data) and not HEADER.unpack_from(data)[4] & FLAG_LIVE:
        raise HeightMapFormatError(f"length mismatch: header says {end} bytes, got {len(data)}")
    return hm, scan_id, frame


def _decode(data: bytes) -> tuple[HeightMap, str, str, int]:
    """(height map, scan id, frame id, offset where the SLHM part ends)."""
    if len(data) < HEADER.size or data[:4] != MAGIC:
        raise HeightMapFormatError("not an SLHM height map (bad magic or too short)")
    (
        _magic,
        version,
        encoding,
        filt,
        flags,
        rows,
        cols,
        step,
        ox,
        oy,
        z_offset,
        unknown,
        f_len,
        s_len,
        h_len,
        o_len,
        i_len,
    ) = HEADER.unpack_from(data)
    if version not in VERSIONS or encoding != ENCODING_UINT16_MM or filt != FILTER_ROW_DELTA:
        raise HeightMapFormatError(
            f"unsupported SLHM version {version} / encoding {encoding} / filter {filt}"
        )
    if flags & ~FLAG_LIVE != FLAG_ROW0_MIN_Y | FLAG_ORIGIN_OUTER_CORNER:
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
    if pos > len(data):
        raise HeightMapFormatError(f"length mismatch: header says {pos} bytes, got {len(data)}")
    try:
        raw = [zlib.decompress(b) for b in blobs]
        counted_raw = zlib.decompress(counted_blob) if counted_blob else None
    except zlib.error as exc:
        raise HeightMapFormatError(f"corrupt compressed layer: {exc}") from None
    n = rows * cols
    if (
        len(raw[0]) != 2 * n
        or len(raw[1]) != (n + 7) // 8
        or len(raw[2]) != n
        or (counted_raw is not None and len(counted_raw) != 2 * n)
    ):
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
    return hm, scan_id, frame, pos


def decode_heightmap(data: bytes) -> HeightMap:
    """Decode `P/heightmap` bytes to a HeightMap (heights to the millimetre, NaN unknown)."""
    return decode_heightmap_with_ids(data)[0]
