"""mypy holds the package and the benchmarks to their annotations: `make test` runs it before
the suite, its settings silence only the libraries that have no types, and the Sparkplug
module protoc generated is checked through the stub protoc made from the same schema."""

from __future__ import annotations

import re
import subprocess
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# no inline types, no stub package
UNTYPED_LIBRARIES = {"pyrealsense2", "onnxruntime", "apscheduler", "pyamg", "threadpoolctl"}


def _make_test(tmp_path: Path, failing: str | None = None) -> tuple[int, list[str]]:
    """`make test` with stand-ins for the venv's tools that log how they were called;
    `failing` (ruff, mypy or python) exits 1. Returns make's status and the calls in order."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    calls = tmp_path / "calls"
    for tool in ("ruff", "mypy", "python"):
        script = venv / "bin" / tool
        status = 1 if tool == failing else 0
        script.write_text(f'#!/bin/sh\necho "{tool} $*" >> {calls}\nexit {status}\n')
        script.chmod(0o755)
    stamp = venv / ".installed"
    stamp.touch()
    run = subprocess.run(
        ["make", "-s", "-C", str(ROOT), "test", f"VENV={venv}", f"STAMP={stamp}"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    logged = [c.strip() for c in calls.read_text().splitlines()] if calls.exists() else []
    return run.returncode, logged


def test_make_test_runs_lint_format_and_types_before_the_suite(tmp_path: Path) -> None:
    status, calls = _make_test(tmp_path)
    assert status == 0
    assert calls == [
        "ruff check silo_agent tests bench",
        "ruff format --check silo_agent tests bench",
        "mypy",
        "python -m pytest -q -n 2 --dist loadfile",
    ]


@pytest.mark.parametrize("failing", ["ruff", "mypy"])
def test_a_lint_format_or_type_error_stops_make_test_before_the_suite(
    tmp_path: Path, failing: str
) -> None:
    status, calls = _make_test(tmp_path, failing)
    assert status != 0
    assert calls and calls[-1].startswith(failing)
    assert not any(c.startswith("python") for c in calls)


def test_mypy_checks_the_package_and_silences_only_untyped_libraries() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    mypy = project["tool"]["mypy"]
    assert {"silo_agent", "bench"} <= set(mypy["files"])
    assert mypy["exclude"] == [r"_pb2\.py$"]  # generated code only
    assert "ignore_missing_imports" not in mypy  # not for every library at once
    silenced = {
        module.split(".")[0]
        for override in mypy.get("overrides", [])
        if override.get("ignore_missing_imports")
        for module in override["module"]
    }
    assert silenced == UNTYPED_LIBRARIES
    test_extra = " ".join(project["project"]["optional-dependencies"]["test"])
    for package in ("mypy", "scipy-stubs", "types-protobuf"):
        assert package in test_extra, f"{package} is not installed by make test"


def test_the_sparkplug_stub_declares_what_the_schema_does() -> None:
    telemetry = ROOT / "silo_agent" / "telemetry"
    schema = (telemetry / "sparkplug_b.proto").read_text(encoding="utf-8")
    stub = (telemetry / "sparkplug_b_pb2.pyi").read_text(encoding="utf-8")
    schema = re.sub(r"//[^\n]*", "", schema)
    types = set(re.findall(r"\b(?:message|enum)\s+(\w+)", schema))
    fields = set(re.findall(r"\b(\w+)\s*=\s*\d+\s*;", schema))  # fields and enum values
    assert {"Payload", "Metric", "MetaData", "DataType"} <= types
    assert {"int_value", "boolean_value", "string_value", "Boolean"} <= fields
    declared_types = set(re.findall(r"^\s*class (\w+)\(", stub, re.MULTILINE))
    declared_names = set(re.findall(r"^\s*(\w+): ", stub, re.MULTILINE))
    assert types - declared_types == set(), "regenerate the stub with --pyi_out"
    assert fields - declared_names == set(), "regenerate the stub with --pyi_out"
