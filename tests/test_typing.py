"""mypy holds the package and the benchmarks to their annotations: `make test` runs it before
the suite, its settings silence only the libraries that have no types, and the Sparkplug
module protoc generated is checked through the stub protoc made from the same schema."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
UNTYPED_LIBRARIES = {"pyrealsense2", "onnxruntime", "apscheduler"}  # no inline types, no stubs


def _recipe(makefile: str, target: str) -> list[str]:
    """The command lines of one Makefile target."""
    lines = makefile.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"{target}:"))
    recipe = []
    for line in lines[start + 1 :]:
        if not line.startswith("\t"):
            break
        recipe.append(line.strip())
    return recipe


def test_make_test_runs_mypy_before_the_suite() -> None:
    recipe = _recipe((ROOT / "Makefile").read_text(encoding="utf-8"), "test")
    mypy = [i for i, line in enumerate(recipe) if line.split()[0].endswith("/mypy")]
    pytest = [i for i, line in enumerate(recipe) if "pytest" in line]
    assert mypy and pytest, recipe
    assert mypy[0] < pytest[0], "a type error must stop make test before the suite runs"


def test_make_test_checks_the_format_before_the_suite() -> None:
    recipe = _recipe((ROOT / "Makefile").read_text(encoding="utf-8"), "test")
    check = [i for i, line in enumerate(recipe) if "ruff format --check" in line]
    pytest = [i for i, line in enumerate(recipe) if "pytest" in line]
    assert check and pytest, recipe
    assert check[0] < pytest[0]
    for tree in ("silo_agent", "tests", "bench"):
        assert tree in recipe[check[0]].split()


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
