"""What every command shares: the one-line failure, loading the config on first use, logging
and the argument types. Imports nothing heavy: `process --help` loads this."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from silo_agent.config import Config


def fail(message: str, status: int) -> int:
    """`silo-agent: <message>` on stderr; `status` back for the command to return."""
    print(f"silo-agent: {message}", file=sys.stderr)
    return status


def load_config(path: Path, service: bool = False) -> Config:
    """The validated config file; pydantic and the config models load here, on first use,
    not at start-up (about 0.1 s that `process` without --config and `--help` never pay)."""
    from silo_agent.config import load_config as load

    return load(path, service=service)


# numpy's tools for developers and its compatibility modules, which nothing the agent runs uses
NUMPY_UNUSED = ("testing", "f2py", "ctypeslib", "polynomial", "ma", "char", "rec", "strings")


def numpy_unused_lazily() -> None:
    """Make numpy's modules in NUMPY_UNUSED load on first use, not at start-up. scipy's
    array-API layer (every scipy subpackage imports it) looks up each of numpy's names at its
    import, which loads them all: numpy.testing (unittest, difflib, subprocess) and numpy.f2py
    (its Fortran parser) among them, about 0.06 s of a one-off `process` for modules it never
    reads. Stand-ins that load themselves on their first attribute access
    (importlib.util.LazyLoader) take their place in sys.modules and on numpy; any code that
    does use one gets the real module then. Modules already imported are left alone."""
    import importlib.util

    import numpy

    for name in NUMPY_UNUSED:
        full = f"numpy.{name}"
        if full in sys.modules:
            continue
        spec = importlib.util.find_spec(full)
        if spec is None or spec.loader is None:
            continue
        loader = importlib.util.LazyLoader(spec.loader)
        spec.loader = loader
        module = importlib.util.module_from_spec(spec)
        sys.modules[full] = module
        loader.exec_module(module)
        setattr(numpy, name, module)


def output_directory_problem(path: Path) -> str | None:
    """Why a command could not make (or write into) the directory `path`, in one line naming
    it; None if it can (`files.writable_directory_problem`, the check `run` makes)."""
    from silo_agent.base.files import writable_directory_problem

    problem = writable_directory_problem(path)
    return None if problem is None else f"{path}: cannot write there: {problem}"


def configure_logging(args: argparse.Namespace) -> None:
    """structlog set up for the command's --log-level (structlog loads here, not at start)."""
    from silo_agent.base.log import configure_logging as configure

    configure(args.log_level)


def seconds(text: str) -> float:
    """A duration > 0, in seconds."""
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"want a duration in seconds > 0, got {text!r}")
    return value


def wait_seconds(text: str) -> float:
    """A wait >= 0 in seconds, finite (0: do not wait)."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"want a wait in seconds >= 0, got {text!r}")
    return value


def positive(text: str) -> int:
    """A whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"want a whole number >= 1, got {text!r}")
    return value


def non_negative(text: str) -> int:
    """A whole number >= 0 (a seed)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"want a whole number >= 0, got {text!r}")
    return value


def grid_step(text: str) -> float:
    """A grid step in metres, within the bounds a config's `reconstruction.grid_step_m` takes
    (config/reconstruction.py: the one home of them)."""
    from pydantic import ValidationError

    from silo_agent.config.reconstruction import ReconstructionConfig

    try:
        return ReconstructionConfig.model_validate({"grid_step_m": text}).grid_step_m
    except ValidationError as exc:
        reason = exc.errors()[0]["msg"]
        message = f"want a grid step in metres ({reason}), got {text!r}"
        raise argparse.ArgumentTypeError(message) from None


def views(text: str) -> list[str]:
    """Distinct camera positions, e.g. `A1,A5` (sim.layouts.VIEWS)."""
    from silo_agent.sim.layouts import VIEWS  # at parse time, for `simulate` only

    chosen = [v.strip().upper() for v in text.split(",") if v.strip()]
    unknown = [v for v in chosen if v not in VIEWS]
    if not chosen or unknown or len(set(chosen)) != len(chosen):
        raise argparse.ArgumentTypeError(f"want distinct views among {', '.join(VIEWS)}")
    return chosen


def calib_error(text: str) -> tuple[float, float]:
    """`DEG,M`: how far simulated poses are off the written extrinsics."""
    try:
        degrees, metres = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("want DEG,M, e.g. 0.5,0.01") from None
    if not (0 <= degrees < float("inf") and 0 <= metres < float("inf")):
        raise argparse.ArgumentTypeError(f"DEG and M must be finite and >= 0, got {text!r}")
    return degrees, metres


def resolution(text: str) -> tuple[int, int]:
    """`WIDTHxHEIGHT` of a simulated depth image."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError("want WIDTHxHEIGHT, e.g. 1280x720") from None
    from silo_agent.base.d455 import MAX_HEIGHT_PX, MAX_WIDTH_PX, MIN_IMAGE_PX

    if not (MIN_IMAGE_PX <= width <= MAX_WIDTH_PX and MIN_IMAGE_PX <= height <= MAX_HEIGHT_PX):
        raise argparse.ArgumentTypeError(
            f"want {MIN_IMAGE_PX}-{MAX_WIDTH_PX} x {MIN_IMAGE_PX}-{MAX_HEIGHT_PX} pixels"
        )
    return width, height
