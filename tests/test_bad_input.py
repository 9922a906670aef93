"""Every bad scan directory and config gives one clear line naming the file, never a traceback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.support.cli import run_cli

MANIFEST = "scan.json"
INTRINSICS = {"width": 424, "height": 240, "fx": 300.0, "fy": 300.0, "ppx": 212.0, "ppy": 120.0}


def _edit_manifest(scan_dir: Path, change) -> None:
    path = scan_dir / MANIFEST
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _first_cloud(scan_dir: Path) -> Path:
    return scan_dir / json.loads((scan_dir / MANIFEST).read_text())["cameras"][0]["cloud"]


def _assert_clear_failure(result, *fragments: str) -> None:
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    assert result.stdout == ""


def _set(path: list, value):
    def change(data):
        target = data
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value

    return change


def _delete(path: list):
    def change(data):
        target = data
        for key in path[:-1]:
            target = target[key]
        del target[path[-1]]

    return change


@pytest.mark.parametrize(
    ("change", "fragments"),
    [
        (_delete(["scan_id"]), ["scan.json", "scan_id", "required"]),
        (_delete(["site", "floor_z"]), ["site.floor_z", "required"]),
        (_set(["site", "floor_z"], "low"), ["site.floor_z"]),
        (_set(["format"], "silo-scan/9"), ["format"]),
        (_set(["captured_at"], "yesterday"), ["captured_at", "RFC 3339"]),
        (_set(["cameras", 0, "extrinsic", 0, 0], 2.0), ["cameras.0.extrinsic", "rigid"]),
        (_set(["cameras", 0, "extrinsic", 1], [0, 1, 0]), ["cameras.0.extrinsic", "4x4"]),
        (_set(["cameras", 0, "extrinsic", 3], [0, 0, 0.5, 1]), ["last row"]),
        (_set(["cameras", 0, "cloud"], "../cam0.ply"), ["cameras.0.cloud", "plain file name"]),
        (_set(["cameras", 0, "cloud"], "sub/cam0.ply"), ["cameras.0.cloud", "plain file name"]),
        (_set(["site", "region"], [[0, 0], [1, 0]]), ["site.region", "at least 3"]),
        (
            _set(["site", "region"], [[0, 0], [1, 1], [1, 0], [0, 1]]),
            ["site.region", "self-intersecting"],
        ),
        (_set(["cameras"], []), ["cameras"]),
        (
            _set(["cameras", 0, "intrinsics"], {**INTRINSICS, "fx": 0}),
            ["intrinsics.fx", "greater than 0"],
        ),
        (
            _set(["cameras", 0, "intrinsics"], {**INTRINSICS, "width": -5}),
            ["intrinsics.width", "greater than 0"],
        ),
    ],
)
def test_bad_manifest_is_named(scan_dir: Path, change, fragments) -> None:
    _edit_manifest(scan_dir, change)
    _assert_clear_failure(run_cli("process", str(scan_dir), "--json"), *fragments)


def test_non_finite_extrinsic(scan_dir: Path) -> None:
    text = (scan_dir / MANIFEST).read_text()
    data = json.loads(text)
    data["cameras"][0]["extrinsic"][0][3] = 1e400  # json.dumps writes Infinity
    (scan_dir / MANIFEST).write_text(json.dumps(data))
    _assert_clear_failure(run_cli("process", str(scan_dir)), "extrinsic")


def test_manifest_not_json(scan_dir: Path) -> None:
    (scan_dir / MANIFEST).write_text("{not json")
    _assert_clear_failure(run_cli("process", str(scan_dir)), "scan.json", "not valid JSON")


def test_missing_directory(tmp_path: Path) -> None:
    _assert_clear_failure(run_cli("process", str(tmp_path / "nope")), "nope", "not a directory")
    # a scan directory that is not there, to the commands that also take a scan id: a bad scan
    # directory (65), as for process; it had been a configuration error (78)
    nope = str(tmp_path / "nope")
    for command in (("report", nope, "--out", str(tmp_path / "r.html")), ("replay", nope)):
        result = run_cli(*command)
        _assert_clear_failure(result, nope, "no such scan directory", "needs --config")
        assert result.returncode == 65


def test_output_whose_reader_went_away_ends_quietly(scan_dir: Path) -> None:
    """`process ... | head -1`: the reader closes the pipe; the command ends with 141 (as one
    killed by SIGPIPE) and no traceback (it had printed a BrokenPipeError traceback)."""
    import os
    import subprocess
    import sys

    read, write = os.pipe()
    os.close(read)  # the reader has gone before the first line is written
    try:
        done = subprocess.run(
            [sys.executable, "-m", "silo_agent", "process", str(scan_dir), "--json"],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
        )
    finally:
        os.close(write)
    assert done.returncode == 141 and done.stderr == ""


def test_missing_cloud_file(scan_dir: Path) -> None:
    cloud = _first_cloud(scan_dir)
    cloud.unlink()
    _assert_clear_failure(run_cli("process", str(scan_dir)), cloud.name, "cannot read")


def test_truncated_cloud(scan_dir: Path) -> None:
    cloud = _first_cloud(scan_dir)
    data = cloud.read_bytes()
    cloud.write_bytes(data[: len(data) - 7])
    _assert_clear_failure(run_cli("process", str(scan_dir)), cloud.name, "header says")


def test_header_lies_about_count(scan_dir: Path) -> None:
    cloud = _first_cloud(scan_dir)
    data = cloud.read_bytes()
    header_end = data.index(b"end_header\n")
    header = data[:header_end].decode()
    count = int(header.split("element vertex ")[1].split()[0])
    header = header.replace(f"element vertex {count}", f"element vertex {count + 10}")
    cloud.write_bytes(header.encode() + data[header_end:])
    _assert_clear_failure(run_cli("process", str(scan_dir)), cloud.name, str(count + 10))


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        (b"garbage", "not a PLY"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n0 0 0\n",
            "binary_little_endian",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty double x\n"
            b"property double y\nproperty double z\nend_header\n" + bytes(24),
            "float x",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n",
            "empty",
        ),
    ],
)
def test_malformed_cloud(scan_dir: Path, body: bytes, fragment: str) -> None:
    cloud = _first_cloud(scan_dir)
    cloud.write_bytes(body)
    _assert_clear_failure(run_cli("process", str(scan_dir)), cloud.name, fragment)


# ---------------------------------------------------------------- configuration

GOOD = """
[silo]
id = "silo-1"
region = [[-2, -2], [2, -2], [2, 2], [-2, 2]]
floor_z = 0.0

[[cameras]]
serial = "A"
source = "realsense"
extrinsic = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
"""


@pytest.mark.parametrize(
    ("edit", "fragments"),
    [
        (lambda t: t.replace('id = "silo-1"', 'id = "silo 1"'), ["silo.id", "pattern"]),
        (lambda t: t + "\n[mqtt]\nprot = 1\n", ["mqtt.prot", "unknown key"]),
        (lambda t: t.replace("floor_z = 0.0", 'floor_z = "zero"'), ["silo.floor_z"]),
        (
            lambda t: t.replace("[[0, 0, 0, 1]]", "[[0, 0, 0, 1]]").replace(
                "[[1, 0, 0, 0]", "[[2, 0, 0, 0]"
            ),
            ["cameras.0", "orthonormal"],
        ),
        (
            lambda t: t.replace(
                "region = [[-2, -2], [2, -2], [2, 2], [-2, 2]]",
                "region = [[0, 0], [1, 1], [1, 0], [0, 1]]",
            ),
            ["silo.region", "self-intersecting"],
        ),
        (
            lambda t: t.replace('source = "realsense"', 'source = "playback"'),
            ["cameras.0", "playback = FILE"],
        ),
        (lambda t: t.replace("[silo]", "[silo\n"), ["not valid TOML"]),
    ],
)
def test_bad_config_names_file_and_key(tmp_path: Path, edit, fragments) -> None:
    path = tmp_path / "agent.toml"
    path.write_text(edit(GOOD))
    result = run_cli("check-config", str(path))
    assert result.returncode == 78
    assert "Traceback" not in result.stderr
    assert str(path) in result.stderr
    for fragment in fragments:
        assert fragment in result.stderr


def test_example_config_is_valid() -> None:
    example = Path(__file__).parents[1] / "config" / "silo-agent.example.toml"
    result = run_cli("check-config", str(example))
    assert result.returncode == 0, result.stderr


def test_process_rejects_bad_config_before_reading_scan(tmp_path: Path) -> None:
    path = tmp_path / "agent.toml"
    path.write_text(GOOD.replace("floor_z = 0.0", "floor_z = 0.0\nceiling_z = -1.0"))
    result = run_cli("process", str(tmp_path / "missing-scan"), "--config", str(path))
    assert result.returncode == 78
    assert "ceiling_z" in result.stderr


@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        (["simulate", "--seed", "-1"], ["--seed", "whole number >= 0", "'-1'"]),
        (["simulate", "--grid-step", "-1"], ["--grid-step", "greater than 0.001"]),
        (["simulate", "--grid-step", "nan"], ["--grid-step", "finite"]),
        (["simulate", "--calib-error", "nan,0"], ["--calib-error", "finite"]),
        (["process", "SCAN", "--grid-step", "5"], ["--grid-step", "less than or equal to 1"]),
        (["flush", "--config", "C", "--timeout", "inf"], ["--timeout", "wait in seconds"]),
        (["flush", "--config", "C", "--linger", "-1"], ["--linger", "wait in seconds"]),
    ],
)
def test_out_of_range_arguments_are_usage_errors(tmp_path: Path, args, fragments) -> None:
    """Numbers a command cannot use are refused by the argument they came in, exit 2, before
    anything is read or written (a negative grid step was written into a simulated scan that
    `process` then refused; an infinite --timeout waited for ever)."""
    if args[0] == "simulate":
        args = ["simulate", "--scene", "cone", "--views", "A1", "--out", "OUT", *args[1:]]
    args = [str(tmp_path / "out") if a == "OUT" else a for a in args]
    result = run_cli(*args)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    for fragment in fragments:
        assert fragment in last, last
    assert not (tmp_path / "out").exists()


def test_simulated_cameras_that_see_nothing_write_no_scan(tmp_path: Path) -> None:
    """A calibration error so large the camera looks away from the scene would give it an
    empty cloud, which no scan reader accepts: refused, naming the camera."""
    out = tmp_path / "scan"
    result = run_cli(
        *("simulate", "--scene", "cone", "--views", "A1,A5", "--out", str(out)),
        *("--calib-error", "0,1000000", "--resolution", "64x48"),
    )
    assert result.returncode == 2
    _assert_clear_failure(result, "sim-A1", "sim-A5", "see nothing of the scene")
    assert not out.exists()


@pytest.mark.parametrize("command", ["simulate", "simulate --record", "record", "scan"])
def test_an_output_path_through_a_file_is_one_line(tmp_path: Path, command: str) -> None:
    """An output directory that cannot be made (a part of its path is a file) is one line
    naming it, exit 1, before anything is captured, rendered or written."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    target = blocker / "out"
    demo = Path(__file__).resolve().parent.parent / "config"
    args = {
        "simulate": ["simulate", "--scene", "cone", "--views", "A1", "--out", str(target)],
        "simulate --record": [
            *("simulate", "--scene", "cone", "--views", "A1"),
            *("--out", str(tmp_path / "scan"), "--record", str(target)),
        ],
        "record": ["record", "--config", str(demo / "silo-agent.example.toml")],
        "scan": ["scan", "--config", str(demo / "demo.toml")],
    }[command]
    if command in ("record", "scan"):
        args += ["--out", str(target)]
    result = run_cli(*args)
    assert result.returncode == 1
    named = target.parent if command == "simulate" else target  # the scan's parent is made
    _assert_clear_failure(result, str(named), "cannot write there")
    assert not (tmp_path / "scan").exists()


@pytest.mark.parametrize("kind", ["directory", "fifo", "device", "huge"])
def test_a_config_path_that_is_no_config_file_is_one_line(tmp_path: Path, kind: str) -> None:
    """check-config on what is no config file: a directory (a traceback), a FIFO (blocked
    waiting for a writer), /dev/zero (read for ever), a file past the size a scan's manifest
    holds. Exit 78 and one line, at once."""
    import os

    path = {"directory": tmp_path, "device": Path("/dev/zero")}.get(kind, tmp_path / "c.toml")
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "huge":
        path.write_bytes(b"# " + b"x" * (17 * 1024 * 1024) + b"\n")
    result = run_cli("check-config", str(path))
    assert result.returncode == 78
    fragment = "larger than" if kind == "huge" else "not a regular file"
    _assert_clear_failure(result, str(path), fragment)


def test_a_report_on_a_full_disk_leaves_the_previous_one_whole(tmp_path: Path, scan_dir) -> None:
    """report --out over an earlier report on a file system that has filled up: one line
    naming the file, exit 1, and the earlier report as it was (a truncated new one had taken
    its place)."""
    from tests.support.faults import fill, tmpfs

    with tmpfs(tmp_path / "small", "2m") as small:
        out = small / "r.html"
        assert run_cli("report", str(scan_dir), "--out", str(out)).returncode == 0
        before = out.read_bytes()
        fill(small)
        result = run_cli("report", str(scan_dir), "--out", str(out))
        assert result.returncode == 1
        _assert_clear_failure(result, f"cannot write {out}", "No space left on device")
        assert out.read_bytes() == before and before.rstrip().endswith(b"</html>")
        assert sorted(p.name for p in small.iterdir()) == ["filler", "r.html"]


@pytest.mark.parametrize("case", ["blocks, new --out", "blocks, --out of the user's", "inodes"])
def test_a_scan_on_a_full_disk_is_one_line_and_leaves_no_scan(tmp_path: Path, case: str) -> None:
    """`scan --out` on a file system that is full: one line naming the scan directory it could
    not write and the OS error, exit 1, and no empty --out directory it made; an --out
    directory that was there before stays, with what it held. With inodes for the raw scan but
    none for result.json the raw scan (the measurement) is kept whole, for `process` later.
    It had left the empty directory behind, its line naming neither the path nor (for the
    result) the OS error."""
    from tests.support.faults import fill, leave_inodes, tmpfs

    demo = Path(__file__).resolve().parent.parent / "config" / "demo.toml"
    size = "20m,nr_inodes=64" if case == "inodes" else "64k"
    with tmpfs(tmp_path / "small", size) as small:
        out = small / "new" / "scans"
        if case == "blocks, --out of the user's":
            out = small / "scans"
            out.mkdir()
            (out / "note.txt").write_text("the user's\n")
        before = sorted(str(p.relative_to(small)) for p in small.rglob("*"))
        if case == "inodes":  # for the raw scan: --out, its parent, staging, 4 clouds, scan.json
            leave_inodes(small, 2 + 1 + 4 + 1)
            before = sorted(p.name for p in small.iterdir())
        else:
            fill(small)
            before.append("filler")
        result = run_cli("scan", "--config", str(demo), "--out", str(out))
        assert result.returncode == 1 and result.stdout == ""
        assert "Traceback" not in result.stderr
        (line,) = [x for x in result.stderr.splitlines() if x.startswith("silo-agent:")]
        assert line == result.stderr.splitlines()[-1]
        what = "keep the result with the scan" if case == "inodes" else "write the scan"
        assert line.startswith(f"silo-agent: {out}/demo-"), line
        assert f": cannot {what}: No space left on device;" in line, line
        if case == "inodes":
            assert line.endswith("; the raw scan is kept without it"), line
            (kept,) = [p for p in out.iterdir() if p.name.startswith("demo-")]
            assert str(kept) in line and not (kept / "result.json").exists()
            assert run_cli("process", str(kept), "--json").returncode == 0  # a whole scan
        else:
            assert sorted(str(p.relative_to(small)) for p in small.rglob("*")) == sorted(before)
