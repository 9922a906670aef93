"""The `silo-scan/1` directory (docs/scan-format.md): types, reader, writer, PLY I/O.

A reader rejects a bad directory with a `ScanError` naming the file and the problem.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO, Literal, cast

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from silo_agent.base.atomic import publish_directory
from silo_agent.base.choices import DEFAULT_MAX_DEPTH_M, DEFAULT_MIN_DEPTH_M
from silo_agent.base.files import FileProblem, open_regular, read_regular
from silo_agent.base.limits import (
    MAX_CLOUD_POINTS,
    MAX_COORDINATE_M,
    MAX_MANIFEST_BYTES,
    MAX_PLY_HEADER_BYTES,
    MAX_SCAN_POINTS,
)
from silo_agent.config import describe_validation_error
from silo_agent.grid.bin_shape import BinShape
from silo_agent.grid.geometry import check_polygon, gravity_angle_deg, rigid_transform_problem

FORMAT = "silo-scan/1"
FORMAT_WITH_BIN = "silo-scan/2"  # adds site.bin; a scan without one is still written as /1
MANIFEST = "scan.json"


class ScanError(Exception):
    """A scan directory that does not follow silo-scan/1; the message names file and problem."""


# ---------------------------------------------------------------- types


@dataclass(frozen=True)
class Site:
    region: np.ndarray  # (V, 2) polygon in the silo frame
    floor_z: float
    ceiling_z: float | None = None
    base: Literal["floor", "boundary"] = "floor"
    bulk_density_t_m3: float | None = None
    bin: BinShape | None = None  # the known wall, eave and bottom (silo-scan/2)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"region": self.region.tolist(), "floor_z": self.floor_z}
        if self.ceiling_z is not None:
            out["ceiling_z"] = self.ceiling_z
        out["base"] = self.base
        if self.bulk_density_t_m3 is not None:
            out["bulk_density_t_m3"] = self.bulk_density_t_m3
        if self.bin is not None:
            out["bin"] = self.bin.to_json()
        return out


@dataclass
class CameraCloud:
    """One camera's raw cloud, in its own optical frame, with its pose in the silo."""

    serial: str
    points: np.ndarray  # (N, 3) float32, camera frame, metres
    extrinsic: np.ndarray  # (4, 4) camera -> silo
    intrinsics: dict[str, Any] | None = None
    colors: np.ndarray | None = None  # (N, 3) uint8
    extra: dict[str, Any] = field(default_factory=dict)  # firmware, gravity, frames, ...
    not_measurements: int = 0  # points of the cloud file dropped when read (`measured_only`)

    def points_in_silo(self, rows: slice | None = None) -> np.ndarray:
        """(N, 3) float32 points in the silo frame (of the points in `rows`, default all: each
        point's the same either way).

        Written column by column: a (N, 3) @ (3, 3) product goes through BLAS with an inner
        dimension of 3 and is about 4x slower than nine fused multiply-adds over the columns.
        """
        rotation = self.extrinsic[:3, :3].astype(np.float32)
        translation = self.extrinsic[:3, 3].astype(np.float32)
        points = self.points if rows is None else self.points[rows]
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        out = np.empty((len(points), 3), dtype=np.float32)
        for axis in range(3):
            r = rotation[axis]
            column = out[:, axis]
            np.multiply(x, r[0], out=column)
            column += y * r[1]
            column += z * r[2]
            column += translation[axis]
        return out


@dataclass
class Scan:
    scan_id: str
    captured_at: str
    silo_id: str
    site: Site
    cameras: list[CameraCloud]
    reconstruction: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)  # truth, result, version, ...


def depth_range_of(camera: CameraCloud) -> tuple[float, float]:
    """(near, far) depth limits of the camera's sensor model: its manifest's `depth_range_m`
    (what its capture's threshold filter kept), else the D455's defaults."""
    value = camera.extra.get("depth_range_m")
    if value is None:
        return DEFAULT_MIN_DEPTH_M, DEFAULT_MAX_DEPTH_M
    return float(value[0]), float(value[1])


def rows_where(array: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """`array[keep]` of a 2-D array's rows, each row copied as one opaque item: 6x faster than
    the boolean index on (N, 3) float32 points (2.6 against 15.5 ms for a 1280x720 cloud), and
    without the index array `np.compress` makes. The same bytes either way."""
    rows = np.ascontiguousarray(array)
    flat = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
    return flat[keep].view(rows.dtype).reshape(-1, rows.shape[1])


def measured_only(camera: CameraCloud) -> CameraCloud:
    """`camera` without the points that are not measurements, counted in `not_measurements`.

    Exporters write "no return" as (0, 0, 0) or NaN, and a depth past the sensor's range is
    noise, not surface: a raw export with 243,517 origin points read 6 % high at 5 mm. Kept:
    finite points in front of the camera (z > 0) within its depth range (z along the axis,
    as the D455 measures it and its threshold filter cuts)."""
    near, far = depth_range_of(camera)
    points = camera.points
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    # column by column and in place: np.isfinite(points).all(axis=1) reduces along rows of
    # three, 13x slower (36 ms against 2.7 ms a 1280x720 cloud on the bench VM)
    keep = z > 0.0
    keep &= z >= near
    keep &= z <= far
    for column in (x, y, z):
        keep &= np.isfinite(column)
    dropped = len(points) - int(np.count_nonzero(keep))
    if dropped == 0:
        return camera
    colors = rows_where(camera.colors, keep) if camera.colors is not None else None
    return replace(
        camera,
        points=rows_where(points, keep),
        colors=colors,
        not_measurements=camera.not_measurements + dropped,
    )


def with_extrinsics(
    cameras: Sequence[CameraCloud], poses: Mapping[str, np.ndarray]
) -> list[CameraCloud]:
    """The clouds with their extrinsics replaced (cameras missing from `poses` unchanged)."""
    return [
        replace(c, extrinsic=np.asarray(poses.get(c.serial, c.extrinsic), dtype=float))
        for c in cameras
    ]


# ---------------------------------------------------------------- manifest schema


def gravity_of(camera: CameraCloud) -> np.ndarray | None:
    """The camera's IMU gravity vector (`gravity` in scan.json: down, camera axes), if any."""
    value = camera.extra.get("gravity")
    if value is None:
        return None
    vector = np.asarray(value, dtype=float)
    if vector.shape != (3,) or not np.all(np.isfinite(vector)) or np.linalg.norm(vector) < 1e-6:
        return None
    return vector


def gravity_angles(cameras: Sequence[CameraCloud]) -> dict[str, float]:
    """Per camera: degrees between its measured gravity and the vertical its extrinsic claims."""
    out = {}
    for camera in cameras:
        gravity = gravity_of(camera)
        if gravity is not None:
            out[camera.serial] = gravity_angle_deg(gravity, camera.extrinsic)
    return out


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False)


class _Intrinsics(_Open):
    # an image and a focal length: a zero (a camera that failed to report them) divided by
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    ppx: float
    ppy: float


class _Camera(_Open):
    serial: str = Field(min_length=1)
    cloud: str
    extrinsic: list[list[float]]
    intrinsics: _Intrinsics | None = None
    depth_range_m: tuple[float, float] | None = None

    @field_validator("depth_range_m")
    @classmethod
    def _near_below_far(cls, value: tuple[float, float] | None) -> tuple[float, float] | None:
        if value is not None and not 0.0 <= value[0] < value[1]:
            raise ValueError(f"must be [near, far] with 0 <= near < far, got {list(value)}")
        return value

    @field_validator("cloud")
    @classmethod
    def _plain_name(cls, name: str) -> str:
        if not name or "/" in name or "\\" in name or name in (".", "..") or ".." in name:
            raise ValueError(f"must be a plain file name inside the scan directory, got {name!r}")
        if "\x00" in name:  # no file can have it: the open would fail as a ValueError
            raise ValueError(f"must not contain a NUL character, got {name!r}")
        return name

    @field_validator("extrinsic")
    @classmethod
    def _rigid(cls, rows: list[list[float]]) -> list[list[float]]:
        if len(rows) != 4 or any(len(r) != 4 for r in rows):
            raise ValueError("must be a 4x4 matrix (4 rows of 4 numbers)")
        problem = rigid_transform_problem(np.asarray(rows, dtype=float))
        if problem:
            raise ValueError(f"not a rigid transform: {problem}")
        return rows


class _Bin(_Open):
    eave_z: float
    floor: Literal["flat", "hopper", "sloped"] = "flat"
    centre: tuple[float, float] = (0.0, 0.0)
    diameter_m: float | None = None
    wall: list[tuple[float, float]] | None = None
    hopper_depth_m: float = 0.0
    outlet_diameter_m: float = 0.0
    floor_slope_deg: float = 0.0
    floor_downhill_deg: float = 0.0
    roof_pitch_deg: float = 30.0
    headspace_from: Literal["eave", "roof"] = "eave"


_SCAN_KEYS = {"eave_height_m": "eave_z"}  # BinShape names the config's keys


class _Site(_Open):
    region: list[tuple[float, float]]
    floor_z: float = Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)
    ceiling_z: float | None = Field(default=None, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)
    base: Literal["floor", "boundary"] = "floor"
    bulk_density_t_m3: float | None = Field(default=None, gt=0)
    bin: _Bin | None = None

    @field_validator("region")
    @classmethod
    def _simple(cls, region: list[tuple[float, float]]) -> list[tuple[float, float]]:
        problem = check_polygon(np.asarray(region, dtype=float).reshape(-1, 2))
        if problem:
            raise ValueError(problem)
        return region

    @model_validator(mode="after")
    def _ceiling_above_floor(self) -> _Site:
        """As the config requires: a floor above the ceiling made a volume of 3e-05 m³ with
        negative levels, reported valid."""
        if self.ceiling_z is not None and self.ceiling_z <= self.floor_z:
            raise ValueError(f"ceiling_z ({self.ceiling_z}) must be above floor_z ({self.floor_z})")
        return self

    @model_validator(mode="after")
    def _bin_consistent(self) -> _Site:
        shape = self.bin_shape()
        if shape is None:
            return self
        for key, problem in shape.problems():
            raise ValueError(f"bin.{_SCAN_KEYS.get(key, key)}: {problem}")
        outside = shape.region_problem(np.asarray(self.region, dtype=float))
        if outside:
            raise ValueError(f"region: {outside}")
        return self

    def bin_shape(self) -> BinShape | None:
        if self.bin is None:
            return None
        return BinShape.from_json(self.bin.model_dump(), self.floor_z)


class _Manifest(_Open):
    format: Literal["silo-scan/1", "silo-scan/2"]
    scan_id: str = Field(pattern=r"^[A-Za-z0-9._-]+$")
    captured_at: str
    silo_id: str = Field(min_length=1)
    site: _Site
    reconstruction: dict[str, Any] = Field(default_factory=dict)
    cameras: list[_Camera] = Field(min_length=1)

    @field_validator("cameras")
    @classmethod
    def _unique_serials(cls, cameras: list[_Camera]) -> list[_Camera]:
        serials = [c.serial for c in cameras]
        dupes = sorted({s for s in serials if serials.count(s) > 1})
        if dupes:
            raise ValueError(f"camera serials must be unique, repeated: {', '.join(dupes)}")
        return cameras

    @field_validator("captured_at")
    @classmethod
    def _rfc3339(cls, value: str) -> str:
        try:
            datetime.fromisoformat(value.replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(f"must be an RFC 3339 time, got {value!r}") from None
        return value


# ---------------------------------------------------------------- PLY

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}


@contextmanager
def _open_regular(path: Path) -> Iterator[BinaryIO]:
    """`files.open_regular`, its problem a ScanError naming `path`."""
    try:
        with open_regular(path) as handle:
            yield handle
    except FileProblem as exc:
        raise ScanError(f"{path}: {exc}") from None


def json_object(path: Path, limit: int) -> dict[str, Any]:
    """The JSON object the regular file `path` holds (at most `limit` bytes): a manifest, a
    kept result; ScanError naming the file and what is wrong with it."""
    try:
        raw = read_regular(path, limit)
    except FileProblem as exc:
        raise ScanError(f"{path}: {exc}") from None
    if not raw.strip():
        raise ScanError(f"{path}: empty")
    try:
        data = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ScanError(f"{path}: not UTF-8 text at byte offset {exc.start}") from None
    except json.JSONDecodeError as exc:
        raise ScanError(f"{path}: not valid JSON: {exc}") from None
    except RecursionError:
        raise ScanError(f"{path}: JSON nested too deeply") from None
    if not isinstance(data, dict):
        raise ScanError(f"{path}: must be a JSON object, got {data!r:.40}")
    return data


def _ply_header(path: Path, header: list[str]) -> tuple[int, list[tuple[str, str]]]:
    """(vertex count, [(property, dtype)]) of a PLY header's lines."""
    count: int | None = None
    props: list[tuple[str, str]] = []
    in_vertex, fmt = False, None
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = " ".join(words[1:])
        elif words[0] == "element":
            if len(words) != 3:
                raise ScanError(f"{path}: bad element line '{line}' (want 'element vertex N')")
            if words[1] != "vertex" or count is not None:
                raise ScanError(f"{path}: only one 'element vertex' is supported, got '{line}'")
            try:
                count = int(words[2])
            except ValueError:
                raise ScanError(f"{path}: bad element line '{line}'") from None
            in_vertex = True
        elif words[0] == "property" and in_vertex:
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise ScanError(f"{path}: unsupported property '{line}'")
            if any(name == words[2] for name, _ in props):
                raise ScanError(f"{path}: property '{words[2]}' is repeated")
            props.append((words[2], _PLY_TYPES[words[1]]))
    if fmt != "binary_little_endian 1.0":
        raise ScanError(f"{path}: format must be 'binary_little_endian 1.0', got {fmt!r}")
    if count is None or count < 0:
        raise ScanError(f"{path}: no 'element vertex N' in the header")
    if count > MAX_CLOUD_POINTS:
        raise ScanError(
            f"{path}: {count:,} points, more than the limit of {MAX_CLOUD_POINTS:,} per cloud"
        )
    if [p for p, _ in props[:3]] != ["x", "y", "z"] or any(t != "<f4" for _, t in props[:3]):
        raise ScanError(f"{path}: the first properties must be 'float x', 'float y', 'float z'")
    return count, props


@dataclass(frozen=True)
class PlyLayout:
    """Where a PLY cloud's vertices are and how they are laid out, from its header alone."""

    path: Path
    count: int
    dtype: np.dtype
    body_offset: int


def ply_layout(path: Path) -> PlyLayout:
    """Read and check a binary little-endian PLY's header, and that the file is as long as it
    announces: a wrong or endless file costs no more than the header, and a scan's clouds can
    all be measured against the limits before any of them is read."""
    with _open_regular(path) as handle:
        try:
            start = handle.read(MAX_PLY_HEADER_BYTES)
            size = os.fstat(handle.fileno()).st_size
        except OSError as exc:
            raise ScanError(f"{path}: cannot read: {exc.strerror or exc}") from None
    end = start.find(b"end_header\n")
    if not start.startswith(b"ply\n") or end < 0:
        raise ScanError(
            f"{path}: not a PLY file (no 'ply' magic or no 'end_header' in the "
            f"first {MAX_PLY_HEADER_BYTES // 1024} KiB)"
        )
    header = start[:end].decode("ascii", errors="replace").splitlines()
    count, props = _ply_header(path, header)
    dtype = np.dtype(props)
    expected = count * dtype.itemsize
    body_offset = end + len(b"end_header\n")
    if size - body_offset != expected:
        raise ScanError(
            f"{path}: header says {count} points ({expected} bytes) but the body has "
            f"{size - body_offset} bytes"
        )
    if count == 0:
        raise ScanError(f"{path}: the cloud is empty (0 points)")
    return PlyLayout(path, count, dtype, body_offset)


def read_ply(path: Path | PlyLayout) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a binary little-endian PLY cloud: (points (N,3) float32, colours (N,3) uint8 | None).

    The body is read straight into the array the engine uses when the file holds x, y, z
    alone (one copy, no bytes object in between); with more properties, into a record array
    whose coordinates are then gathered. Points come back as stored, NaN and all: `read_scan`
    drops those that are not measurements (`measured_only`)."""
    layout = path if isinstance(path, PlyLayout) else ply_layout(path)
    xyz_only = layout.dtype.itemsize == 12
    shape = (layout.count, 3) if xyz_only else (layout.count,)
    data: np.ndarray[Any, np.dtype[Any]] = np.empty(shape, np.float32 if xyz_only else layout.dtype)
    with _open_regular(layout.path) as handle:
        try:
            handle.seek(layout.body_offset)
            got = cast(io.BufferedReader, handle).readinto(data.data.cast("B"))
        except OSError as exc:
            raise ScanError(f"{layout.path}: cannot read: {exc.strerror or exc}") from None
    if got != data.nbytes:
        raise ScanError(f"{layout.path}: changed while it was read ({got} of {data.nbytes} bytes)")
    points = data if xyz_only else np.stack([data["x"], data["y"], data["z"]], axis=1)
    names = data.dtype.names or ()
    colors = None
    if all(c in names for c in ("red", "green", "blue")):
        colors = np.stack([data["red"], data["green"], data["blue"]], axis=1).astype(np.uint8)
    return points, colors


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write a binary little-endian PLY with float x y z (and uchar colours)."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(len(points), dtype=fields)
    data["x"], data["y"], data["z"] = points[:, 0], points[:, 1], points[:, 2]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += ["property float x", "property float y", "property float z"]
    if colors is not None:
        data["red"], data["green"], data["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with open(path, "wb") as out:
        out.write(("\n".join(header) + "\n").encode("ascii"))
        out.write(data.tobytes())


# ---------------------------------------------------------------- directory


def read_manifest(directory: Path) -> dict[str, Any]:
    """The raw manifest JSON, validated against silo-scan/1."""
    path = directory / MANIFEST
    if not directory.is_dir():
        raise ScanError(f"{directory}: not a directory")
    if not path.exists():
        raise ScanError(f"{path}: missing (not a silo-scan/1 directory)")
    data = json_object(path, MAX_MANIFEST_BYTES)
    try:
        _Manifest.model_validate(data)
    except ValidationError as exc:
        raise ScanError(describe_validation_error(exc, str(path)).splitlines()[0]) from None
    return data


def read_scan(directory: str | Path) -> Scan:
    """Read and check a whole scan directory."""
    directory = Path(directory)
    data = read_manifest(directory)
    manifest = _Manifest.model_validate(data)
    site = Site(
        region=np.asarray(manifest.site.region, dtype=float),
        floor_z=manifest.site.floor_z,
        ceiling_z=manifest.site.ceiling_z,
        base=manifest.site.base,
        bulk_density_t_m3=manifest.site.bulk_density_t_m3,
        bin=manifest.site.bin_shape(),
    )
    layouts = [ply_layout(directory / camera.cloud) for camera in manifest.cameras]
    total = 0
    for layout in layouts:  # every header first: refused before any cloud is read
        total += layout.count
        if total > MAX_SCAN_POINTS:
            raise ScanError(
                f"{directory}: more than the limit of {MAX_SCAN_POINTS:,} points in "
                f"all clouds together (at {layout.path.name})"
            )
    cameras = []
    known = {"serial", "cloud", "extrinsic", "intrinsics"}
    for raw_camera, camera, layout in zip(data["cameras"], manifest.cameras, layouts, strict=True):
        points, colors = read_ply(layout)
        cloud = CameraCloud(
            serial=camera.serial,
            points=points,
            extrinsic=np.asarray(camera.extrinsic, dtype=float),
            intrinsics=raw_camera.get("intrinsics"),
            colors=colors,
            extra={k: v for k, v in raw_camera.items() if k not in known},
        )
        cameras.append(measured_only(cloud))
    top = {"format", "scan_id", "captured_at", "silo_id", "site", "reconstruction", "cameras"}
    return Scan(
        scan_id=manifest.scan_id,
        captured_at=manifest.captured_at,
        silo_id=manifest.silo_id,
        site=site,
        cameras=cameras,
        reconstruction=dict(manifest.reconstruction),
        extra={k: v for k, v in data.items() if k not in top},
    )


def manifest_of(scan: Scan) -> dict[str, Any]:
    cameras = []
    for camera in scan.cameras:
        entry: dict[str, Any] = {
            "serial": camera.serial,
            "cloud": f"{camera.serial}.ply",
            "extrinsic": np.asarray(camera.extrinsic, dtype=float).tolist(),
        }
        if camera.intrinsics is not None:
            entry["intrinsics"] = camera.intrinsics
        entry.update(camera.extra)
        cameras.append(entry)
    return {
        "format": FORMAT if scan.site.bin is None else FORMAT_WITH_BIN,
        "scan_id": scan.scan_id,
        "captured_at": scan.captured_at,
        "silo_id": scan.silo_id,
        "site": scan.site.to_json(),
        "reconstruction": scan.reconstruction,
        "cameras": cameras,
        **scan.extra,
    }


def write_scan(scan: Scan, directory: str | Path) -> Path:
    """Write `scan` as a new silo-scan/1 directory, atomically (staging, fsync, rename, fsync)."""
    directory = Path(directory)
    if directory.exists():
        raise ScanError(f"{directory}: already exists; scans are never overwritten")
    directory.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{directory.name}.", dir=directory.parent))
    try:
        for camera in scan.cameras:
            write_ply(staging / f"{camera.serial}.ply", camera.points, camera.colors)
        (staging / MANIFEST).write_text(json.dumps(manifest_of(scan), indent=2) + "\n")
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    publish_directory(staging, directory)
    return directory
