"""A damaged audit cache or scan directory through the real CLI: `replay`, `report`, `scans`,
`process` and `calibrate --scan` exit 65 with one line naming the file and the problem (no
traceback), `scans list` marks a damaged entry and lists the others, and `scans export` to a
path it cannot write is one line with nothing half-written.

One scan is taken once per module with `silo-agent scan` (two simulated cameras, 5 cm grid);
each test damages its own copy of that audit cache."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from silo_agent.cli import main
from tests.support.agent import SILO, write_config

PORT = 9  # nothing listens: no test here reaches a broker


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An audit cache (`scans/`) holding one scan made by `silo-agent scan`, with its result."""
    workdir = tmp_path_factory.mktemp("pristine")
    config = write_config(workdir / "agent.toml", PORT, workdir)
    assert main(["scan", "--config", str(config)]) == 0
    return workdir / "scans"


@pytest.fixture
def cache(tmp_path: Path, pristine: Path, capsys: pytest.CaptureFixture) -> tuple[Path, Path]:
    """(config, scan directory) of this test's own copy of the pristine cache."""
    shutil.copytree(pristine, tmp_path / "scans")
    config = write_config(tmp_path / "agent.toml", PORT, tmp_path)
    (scan,) = (tmp_path / "scans").iterdir()
    capsys.readouterr()
    return config, scan


def one_line(capsys: pytest.CaptureFixture, argv: list[str], status: int, *says: str) -> str:
    """Run the CLI: `status`, and one stderr line naming what `says` names."""
    assert main(argv) == status
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("silo-agent: "), err
    for fragment in says:
        assert fragment in err[0], err[0]
    return err[0]


def edit_json(path: Path, change: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def replace_with_directory(path: Path) -> None:
    path.unlink()
    path.mkdir()


# ---------------------------------------------------------------- scans export


def test_export_where_it_cannot_write_is_one_line_and_leaves_nothing(
    tmp_path: Path, cache: tuple[Path, Path], capsys: pytest.CaptureFixture
) -> None:
    config, scan = cache
    argv = ["scans", "export", scan.name, "--config", str(config), "--out"]
    missing = tmp_path / "no-such-directory" / "x.tar.gz"
    one_line(capsys, [*argv, str(missing)], 1, str(missing), "No such file or directory")
    taken = tmp_path / "out"
    taken.mkdir()
    one_line(capsys, [*argv, str(taken)], 1, str(taken), "Is a directory")
    assert list(taken.iterdir()) == []
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert main([*argv, str(tmp_path / "ok.tar.gz")]) == 0  # the same export, where it can
    assert (tmp_path / "ok.tar.gz").stat().st_size > 0


# ---------------------------------------------------------------- result.json, inputs.json


@pytest.mark.parametrize(
    ("damage", "says"),
    [
        (lambda p: p.write_text(""), "empty"),
        (lambda p: p.write_bytes(b"\xff\xfe\x00junk"), "not UTF-8"),
        (lambda p: p.write_text("[]"), "must be a JSON object"),
        (lambda p: p.write_text('{"previous_piles": [{"x": 1}]}'), "previous_piles"),
    ],
    ids=["empty", "junk-bytes", "list", "pile-without-id"],
)
def test_replay_names_a_damaged_inputs_json(
    cache: tuple[Path, Path], capsys: pytest.CaptureFixture, damage, says: str
) -> None:
    config, scan = cache
    damage(scan / "inputs.json")
    argv = ["replay", scan.name, "--config", str(config)]
    one_line(capsys, argv, 65, f"{scan / 'inputs.json'}: ", says)


@pytest.mark.parametrize(
    ("damage", "says"),
    [
        (lambda p: p.write_text(""), "empty"),
        (lambda p: p.write_text("junk"), "not valid JSON"),
        (lambda p: p.write_text("[]"), "must be a JSON object"),
        (lambda p: p.write_text('"x"'), "must be a JSON object"),
        (replace_with_directory, "not a regular file (a directory)"),
    ],
    ids=["empty", "junk", "list", "string", "directory"],
)
def test_replay_names_a_damaged_result_json(
    cache: tuple[Path, Path], capsys: pytest.CaptureFixture, damage, says: str
) -> None:
    config, scan = cache
    damage(scan / "result.json")
    argv = ["replay", scan.name, "--config", str(config)]
    one_line(capsys, argv, 65, f"{scan / 'result.json'}: ", says)


@pytest.mark.parametrize("text", ["", "junk"])
def test_scans_show_names_a_damaged_result_json(
    cache: tuple[Path, Path], capsys: pytest.CaptureFixture, text: str
) -> None:
    config, scan = cache
    (scan / "result.json").write_text(text)
    argv = ["scans", "show", scan.name, "--config", str(config)]
    one_line(capsys, argv, 65, f"{scan / 'result.json'}: ")


def test_scans_list_marks_a_damaged_entry_and_lists_the_others(
    cache: tuple[Path, Path], capsys: pytest.CaptureFixture
) -> None:
    config, scan = cache
    ids = [f"{SILO}-20260101T00000{k}Z" for k in range(3)]
    for scan_id in ids:
        shutil.copytree(scan, scan.parent / scan_id)
    damaged = scan.parent / ids[1] / "result.json"
    damaged.write_text("[]")
    assert main(["scans", "list", "--config", str(config)]) == 65
    captured = capsys.readouterr()
    lines = {line.split()[0]: line for line in captured.out.splitlines()}
    assert all(scan_id in lines for scan_id in [*ids, scan.name])
    assert "DAMAGED result.json" in lines[ids[1]]
    assert all("m³" in lines[scan_id] for scan_id in [ids[0], ids[2], scan.name])
    assert "4 scan(s)" in captured.out
    assert captured.err.strip().splitlines() == [
        f"silo-agent: {damaged}: must be a JSON object, got []"
    ]


@pytest.mark.parametrize(
    ("result", "says"),
    [
        ('{"volume_m3": "x", "valid": true}', "lacks 'scan_id'"),
        (None, "volume_m3"),  # the kept result with a NaN volume
    ],
    ids=["no-summary", "nan-volume"],
)
def test_report_names_a_result_that_is_no_summary(
    tmp_path: Path,
    cache: tuple[Path, Path],
    capsys: pytest.CaptureFixture,
    result: str | None,
    says: str,
) -> None:
    config, scan = cache
    path = scan / "result.json"
    if result is None:
        result = json.dumps({**json.loads(path.read_text()), "volume_m3": float("nan")})
    path.write_text(result)
    out = tmp_path / "r.html"
    argv = ["report", scan.name, "--config", str(config), "--out", str(out)]
    one_line(capsys, argv, 65, f"{path}: ", says)
    assert not out.exists()


# ---------------------------------------------------------------- scan.json


def test_a_config_snapshot_that_is_no_object_is_named(
    tmp_path: Path, cache: tuple[Path, Path], capsys: pytest.CaptureFixture
) -> None:
    config, scan = cache
    edit_json(scan / "scan.json", lambda m: m.update(config="x"))
    says = (f"{scan / 'scan.json'}: config: ", "must be a JSON object")
    one_line(capsys, ["replay", scan.name, "--config", str(config)], 65, *says)
    report = ["report", scan.name, "--config", str(config), "--out", str(tmp_path / "r.html")]
    one_line(capsys, report, 65, *says)
    one_line(capsys, ["process", str(scan)], 65, *says)


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (lambda r: r.update(method="zzz"), "method"),
        (lambda r: r.update(grid_step_m=-1), "grid_step_m"),
    ],
    ids=["method", "grid-step"],
)
def test_bad_reconstruction_settings_name_the_manifest_path(
    tmp_path: Path, cache: tuple[Path, Path], capsys: pytest.CaptureFixture, change, says: str
) -> None:
    _config, scan = cache
    directory = tmp_path / "d_x"  # not named like the scan id the manifest holds
    shutil.copytree(scan, directory)
    edit_json(directory / "scan.json", lambda m: change(m["reconstruction"]))
    prefix = f"silo-agent: {directory / 'scan.json'}: reconstruction: {says}"
    assert one_line(capsys, ["process", str(directory)], 65).startswith(prefix)


@pytest.mark.parametrize("name", ["sim-A2.ply", "scan.json"])
def test_a_directory_in_place_of_a_scan_file_is_named(
    tmp_path: Path, cache: tuple[Path, Path], capsys: pytest.CaptureFixture, name: str
) -> None:
    config, scan = cache
    replace_with_directory(scan / name)
    says = (f"{scan / name}: ", "a directory")
    one_line(capsys, ["process", str(scan)], 65, *says)
    one_line(capsys, ["report", str(scan), "--out", str(tmp_path / "r.html")], 65, *says)
    one_line(capsys, ["calibrate", "--config", str(config), "--scan", str(scan)], 65, *says)


def test_reconstruction_keys_a_newer_agent_wrote_are_ignored(
    tmp_path: Path, cache: tuple[Path, Path], capsys: pytest.CaptureFixture
) -> None:
    """silo-scan/1 readers ignore keys they do not know (docs/scan-format.md): a setting a
    newer agent adds to `reconstruction` leaves the result as it was (process and replay had
    refused it as an unknown key, report and calibrate had read it)."""
    _config, scan = cache
    assert main(["process", str(scan), "--json"]) == 0
    before = json.loads(capsys.readouterr().out)
    directory = tmp_path / "newer"
    shutil.copytree(scan, directory)
    edit_json(directory / "scan.json", lambda m: m["reconstruction"].update(x_future=3))
    assert main(["process", str(directory), "--json"]) == 0
    after = json.loads(capsys.readouterr().out)
    assert after["volume_m3"] == before["volume_m3"]
    assert main(["replay", str(directory)]) == 0
    assert "identical" in capsys.readouterr().out
