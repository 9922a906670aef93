"""`silo-agent process` over many scan directories in one process, and a lean start."""

from __future__ import annotations

import json
import os
import pty
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.level import level_scan
from silo_agent.scan import Scan, write_scan
from tests.support.cli import run_cli

STEP = "0.05"  # coarse: these tests are about the batch, not the surface


@pytest.fixture
def two_scans(tmp_path: Path, cone_scan_4: Scan, cone_scan_2: Scan) -> list[Path]:
    return [
        write_scan(replace(cone_scan_4, scan_id="four"), tmp_path / "a-four"),
        write_scan(replace(cone_scan_2, scan_id="two"), tmp_path / "c-two"),
    ]


def _lines(stdout: str) -> list[dict]:
    return [json.loads(line) for line in stdout.splitlines()]


def _without_timings(results: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "timings_s"} for r in results]


def test_a_bad_directory_in_the_middle_fails_alone(tmp_path, two_scans: list[Path]) -> None:
    bad = tmp_path / "b-broken"
    bad.mkdir()
    (bad / "scan.json").write_text("{not json")
    done = run_cli(
        "process", str(two_scans[0]), str(bad), str(two_scans[1]), "--json", "--grid-step", STEP
    )
    assert done.returncode == 65, done.stderr
    results = _lines(done.stdout)
    assert [r["scan_dir"] for r in results] == [str(two_scans[0]), str(two_scans[1])]
    assert [r["scan_id"] for r in results] == ["four", "two"]
    errors = done.stderr.splitlines()
    assert "Traceback" not in done.stderr
    assert len(errors) == 2, done.stderr
    assert str(bad / "scan.json") in errors[0] and "not valid JSON" in errors[0]
    assert errors[1] == "silo-agent: 2 of 3 scans processed, 1 failed"


def test_each_json_line_is_the_scans_own_result(
    two_scans: list[Path], cone_scan_4: Scan, cone_scan_2: Scan
) -> None:
    done = run_cli("process", *map(str, two_scans), "--json", "--grid-step", STEP)
    assert done.returncode == 0, done.stderr
    results = _lines(done.stdout)
    settings = ReconstructionConfig(grid_step_m=float(STEP))
    for result, scan in zip(results, [cone_scan_4, cone_scan_2], strict=True):
        leveled, _, _ = level_scan(scan, CalibrationConfig())  # the default outside bins
        assert result["volume_m3"] == reconstruct(leveled, settings).volume_m3
    assert done.stderr.splitlines() == ["silo-agent: 2 of 2 scans processed"]


def test_a_directory_of_scans_is_processed_scan_by_scan(tmp_path, two_scans) -> None:
    (tmp_path / "alarm-state.json").write_text("{}")  # what else lives in an audit cache
    (tmp_path / ".c-two.tmp").mkdir()  # a scan being written
    done = run_cli("process", str(tmp_path), "--json", "--grid-step", STEP)
    assert done.returncode == 0, done.stderr
    assert [r["scan_dir"] for r in _lines(done.stdout)] == [str(d) for d in two_scans]


def test_jobs_give_the_same_results_in_the_same_order(two_scans: list[Path]) -> None:
    args = ["process", *map(str, two_scans), *map(str, two_scans), "--json", "--grid-step", STEP]
    one = run_cli(*args)
    two = run_cli(*args, "--jobs", "2")
    assert one.returncode == two.returncode == 0, two.stderr
    assert len(_lines(two.stdout)) == 4
    assert _without_timings(_lines(two.stdout)) == _without_timings(_lines(one.stdout))


def test_a_bad_config_stops_before_any_scan(tmp_path, two_scans: list[Path]) -> None:
    config = tmp_path / "agent.toml"
    config.write_text("[silo]\nid = 'bad id with spaces'\n")
    done = run_cli("process", *map(str, two_scans), "--config", str(config), "--json")
    assert done.returncode == 78
    assert done.stdout == ""
    assert str(config) in done.stderr


def _stderr_on_a_terminal(*args: str) -> tuple[int, str]:
    """Run the CLI with stderr on a pseudo-terminal; (status, what the terminal showed)."""
    leader, follower = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "silo_agent", *args], stdout=subprocess.DEVNULL, stderr=follower
    )
    os.close(follower)
    shown = b""
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # EIO: the child closed the terminal
            break
        if not chunk:
            break
        shown += chunk
    os.close(leader)
    return proc.wait(timeout=120), shown.decode()


def test_a_progress_bar_on_a_terminal_only(tmp_path, two_scans: list[Path]) -> None:
    dirs = [str(two_scans[0])] * 5
    status, shown = _stderr_on_a_terminal("process", *dirs, "--grid-step", STEP)
    assert status == 0, shown
    assert "] 5/5 a-four" in shown and "] 1/5 a-four" in shown
    piped = run_cli("process", *dirs, "--grid-step", STEP)
    assert "/5 " not in piped.stderr and "\r" not in piped.stderr
    status, shown = _stderr_on_a_terminal("process", *dirs[:2], "--grid-step", STEP)
    assert "/2 " not in shown  # two scans: no bar


HEAVY = [
    "structlog",
    "asyncio",
    "open3d",
    "sklearn",
    "onnxruntime",
    "pyrealsense2",
    "paho",
    "apscheduler",
    "silo_agent.telemetry",
    "silo_agent.capture",
    "silo_agent.calibrate",
    "silo_agent.sim",
    "silo_agent.base.log",
]


def _imported(code: str) -> set[str]:
    done = subprocess.run(
        [sys.executable, "-c", code + "\nimport sys\nprint(*sys.modules)"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return set(done.stdout.split())


def test_process_imports_only_what_its_path_needs(scan_dir: Path) -> None:
    loaded = _imported(
        "from silo_agent.cli import main\n"
        f"assert main(['process', {str(scan_dir)!r}, '--json']) == 0"
    )
    assert {"silo_agent.reconstruct", "silo_agent.detect"} <= loaded  # it did the work
    assert loaded.isdisjoint(HEAVY), sorted(loaded & set(HEAVY))


def test_process_help_imports_no_numeric_library() -> None:
    loaded = _imported(
        "from silo_agent.cli import main\n"
        "try:\n    main(['process', '--help'])\nexcept SystemExit:\n    pass"
    )
    heavy = {"numpy", "scipy", "pydantic", "importlib.metadata", *HEAVY}
    assert loaded.isdisjoint(heavy), sorted(loaded & heavy)


def test_process_builds_only_the_settings_models_it_validates(scan_dir: Path) -> None:
    """pydantic builds a model's validator when first used (defer_build): `process` validates
    the scan's reconstruction, detection and calibration settings, never the daemon's config."""
    code = (
        "import contextlib, io\n"
        "from silo_agent.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    assert main(['process', {str(scan_dir)!r}, '--json']) == 0\n"
        "import silo_agent.config as c\n"
        "names = ['Config', 'MqttConfig', 'LiveConfig', 'ReconstructionConfig',"
        " 'DetectionConfig', 'CalibrationConfig']\n"
        "print(*(getattr(c, n).__pydantic_complete__ for n in names))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False", "False", "False", "True", "True", "True"]


@pytest.mark.parametrize(("preset", "expected"), [(None, "__all__"), ("", ""), ("1", "1")])
def test_pydantic_plugins_are_off_unless_the_environment_says(
    scan_dir: Path, preset: str | None, expected: str
) -> None:
    """Scanning every installed package for pydantic plugins costs each `process` ~0.02 s;
    the agent turns it off, and an explicit setting (even empty: plugins on) wins."""
    code = (
        "import contextlib, io, os\n"
        "from silo_agent.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    assert main(['process', {str(scan_dir)!r}, '--json']) == 0\n"
        "print(repr(os.environ.get('PYDANTIC_DISABLE_PLUGINS')))"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYDANTIC_DISABLE_PLUGINS"}
    if preset is not None:
        env["PYDANTIC_DISABLE_PLUGINS"] = preset
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == repr(expected)


def _raw_points_alive_at_the_clustering(
    monkeypatch: pytest.MonkeyPatch, directory: Path, release_points: bool
) -> tuple[list[bool], dict]:
    """`process_directory` of `directory`: whether any raw cloud's points were still alive each
    time the clustering's segments were built (the last time: the reconstruction's peak), and
    the summary."""
    import weakref

    import silo_agent.reconstruct as reconstruct_module
    from silo_agent.scan import read_scan
    from silo_agent.service import scan_path

    raw: list[weakref.ref] = []
    alive: list[bool] = []

    def reading(path: Path) -> Scan:
        scan = read_scan(path)
        raw.extend(weakref.ref(c.points) for c in scan.cameras)
        return scan

    segments = reconstruct_module.height_segments

    def watched(*args, **kwargs):
        alive.append(any(ref() is not None for ref in raw))
        return segments(*args, **kwargs)

    monkeypatch.setattr(scan_path, "read_scan", reading)
    monkeypatch.setattr(reconstruct_module, "height_segments", watched)
    _scan, _result, summary = scan_path.process_directory(directory, release_points=release_points)
    monkeypatch.undo()
    return alive, {k: v for k, v in summary.to_json().items() if k != "timings_s"}


@pytest.mark.parametrize("scene", ["cone", "bin-heap"])
def test_process_lets_go_of_the_raw_clouds_before_the_clustering(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, scene: str
) -> None:
    """`process` (batch.outcome_of) reads nothing of the raw clouds after the reconstruction:
    they go once fused (a bin: once its wall is dropped), before the peak, and the summary is
    the same as with them kept."""
    from silo_agent.sim.scenes import make_scene
    from silo_agent.sim.simulate import simulate

    scan = simulate(make_scene(scene), ["A1", "A5"], seed=0, resolution=(424, 240))
    directory = write_scan(replace(scan, reconstruction={"grid_step_m": 0.05}), tmp_path / "s")
    kept_alive, kept = _raw_points_alive_at_the_clustering(monkeypatch, directory, False)
    let_go, released = _raw_points_alive_at_the_clustering(monkeypatch, directory, True)
    # a bin's first pass (the wall step) clusters too, on the raw clouds: the last is the peak
    assert kept_alive[-1] and not let_go[-1]
    assert released == kept


def test_scan_directories_may_follow_the_options(two_scans: list[Path]) -> None:
    """`process a --json b`: argparse takes one run of positionals, and the second directory
    was an "unrecognized argument"; an unknown option still is."""
    first, second = map(str, two_scans)
    done = run_cli("process", first, "--json", "--grid-step", STEP, second)
    assert done.returncode == 0, done.stderr
    assert [r["scan_dir"] for r in _lines(done.stdout)] == [first, second]
    bad = run_cli("process", first, "--jsn", second)
    assert bad.returncode == 2 and "unrecognized arguments: --jsn" in bad.stderr
