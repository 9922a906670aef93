"""Writing a calibration back into the site's config file: only the cameras' extrinsics
change, every comment and all other text stay (tomlkit keeps the document's layout), the
result is read back before anything is written, and the old file is kept as a backup."""

from __future__ import annotations

import shutil
import tomllib
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import tomlkit
from tomlkit.exceptions import TOMLKitError
from tomlkit.items import AbstractTable, Item

from silo_agent.base.atomic import write_atomic
from silo_agent.calibrate.errors import CalibrationError
from silo_agent.config import ConfigError, parse_config
from silo_agent.grid.geometry import euler_from_rotation


def _number(value: float) -> str:
    text = f"{value:.9f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _matrix_text(matrix: np.ndarray, indent: str) -> str:
    """A 4x4 matrix as a TOML array, one row a line, rows aligned under the first."""
    rows = [f"[{', '.join(_number(v) for v in row)}]" for row in matrix]
    return "[" + (",\n" + indent + " " * len("extrinsic = [")).join(rows) + "]"


def _vector_text(values: tuple[float, ...]) -> str:
    return f"[{', '.join(_number(v) for v in values)}]"


def _set(table: AbstractTable, key: str, value_text: str) -> None:
    """Set `table[key]` to the TOML value `value_text`, written as given; an existing key keeps
    its place, indent and trailing comment, a new one goes at the end of the table."""
    new: Item = tomlkit.parse(f"{key} = {value_text}\n")[key]
    old = table.get(key)
    if isinstance(old, Item):
        new.trivia.indent = old.trivia.indent
        new.trivia.comment_ws = old.trivia.comment_ws
        new.trivia.comment = old.trivia.comment
        new.trivia.trail = old.trivia.trail
        table[key] = new
    else:
        table.add(key, new)


def rewrite_config_text(text: str, poses: Mapping[str, np.ndarray]) -> str:
    """`text` with the extrinsics of the cameras in `poses` replaced, nothing else touched.

    Each camera keeps its form: a 4x4 `extrinsic` is rewritten as a matrix, a `rotate_deg` /
    `translate_m` pair in the paper's form; a camera with neither (a sim camera placed by its
    `view`) gets an `extrinsic`. Comments stay, trailing ones too.
    """
    document = tomlkit.parse(text)
    cameras = document.get("cameras", [])
    done = set()
    for table in cameras if isinstance(cameras, list) else []:
        serial = str(table.get("serial", "")) if isinstance(table, AbstractTable) else ""
        if serial not in poses:
            continue
        pose = np.asarray(poses[serial], dtype=np.float64)
        done.add(serial)
        if "extrinsic" not in table and ("rotate_deg" in table or "translate_m" in table):
            _set(table, "rotate_deg", _vector_text(euler_from_rotation(pose[:3, :3])))
            _set(table, "translate_m", _vector_text(tuple(pose[:3, 3])))
        else:
            anchor = table.get("extrinsic", table.get("serial"))
            _set(table, "extrinsic", _matrix_text(pose, anchor.trivia.indent))
    missing = sorted(set(poses) - done)
    if missing:
        raise CalibrationError(f"no [[cameras]] table with serial {', '.join(missing)}")
    return tomlkit.dumps(document)


def write_calibrated_config(path: Path, poses: Mapping[str, np.ndarray]) -> Path:
    """Rewrite the config file at `path` with the new extrinsics; keep the old one as a backup
    (`<name>.<UTC time>.bak`, beside the file a symlink names). The new text is validated
    before anything is written, and is written atomically. Returns the backup's path."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        new = rewrite_config_text(text, poses)
        config = parse_config(tomllib.loads(new), f"{path} (rewritten)")
    except (tomllib.TOMLDecodeError, TOMLKitError) as exc:
        raise CalibrationError(
            f"{path}: the rewritten file is not valid TOML ({exc}); nothing written"
        ) from None
    for camera in config.cameras:
        if camera.serial in poses:
            got = camera.extrinsic_matrix()
            if got is None or not np.allclose(got, poses[camera.serial], atol=1e-6):
                raise CalibrationError(
                    f"{path}: the rewritten extrinsic of {camera.serial} does "
                    "not read back; nothing written"
                )
    target = path.resolve()  # a symlinked config: the file it names is rewritten, the link kept
    backup = target.with_name(f"{target.name}.{datetime.now(UTC):%Y%m%dT%H%M%S%fZ}.bak")
    shutil.copy2(target, backup)
    write_atomic(target, new.encode("utf-8"), keep_access=True)
    return backup
