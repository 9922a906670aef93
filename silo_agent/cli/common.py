"""What every command shares: the one-line failure, loading the config on first use, logging
and the argument types. Imports nothing heavy: `process --help` loads this."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import types
from pathlib import Path
from typing import TYPE_CHECKING, Any

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


PLUGINS_OFF = ("__all__", "1", "true")  # PYDANTIC_DISABLE_PLUGINS values that turn them all off


def _no_plugins() -> tuple[()]:
    return ()


class _PluginLoaderStandIn(types.ModuleType):
    """pydantic.plugin._loader while pydantic's plugins are off (`pydantic_plugins_unlooked`):
    its `get_plugins` answers none, as the real one does then; any other use, or plugins
    turned on, loads the real module in its place and reads from it."""

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):  # the import system's questions (`__path__`): a plain module's
            raise AttributeError(name)
        if name == "get_plugins" and os.environ.get("PYDANTIC_DISABLE_PLUGINS") in PLUGINS_OFF:
            return _no_plugins
        if sys.modules.get(self.__name__) is self:
            del sys.modules[self.__name__]
        return getattr(importlib.import_module(self.__name__), name)


def pydantic_plugins_unlooked() -> None:
    """Spare pydantic's plugin loader while its plugins are off (PYDANTIC_DISABLE_PLUGINS, which
    `process` sets): the loader imports importlib.metadata at its top (and with it the email
    package, to parse metadata) when the first model is validated, and then returns no plugins
    without reading it. A stand-in (`_PluginLoaderStandIn`) takes its place in sys.modules
    until something needs the real one: importing importlib.metadata after numpy and
    pydantic, one core under load, 12 fresh processes, 0.021-0.024 s of CPU."""
    name = "pydantic.plugin._loader"
    if os.environ.get("PYDANTIC_DISABLE_PLUGINS") in PLUGINS_OFF and name not in sys.modules:
        sys.modules[name] = _PluginLoaderStandIn(name)


class _UnparsedDoc(dict[str, list[str]]):
    """Stands in for scipy's numpydoc parser where `scipy_docs_unparsed` says: the docstring
    read back as it was, the note appended to it dropped."""

    def __init__(self, function: object) -> None:
        super().__init__(Notes=[])
        self.doc = getattr(function, "__doc__", None) or ""

    def __str__(self) -> str:
        return "\n" + self.doc  # the decorator drops the first line (a signature) of this


def scipy_docs_unparsed() -> None:
    """Keep scipy from parsing docstrings at import. scipy's `xp_capabilities` decorator
    (scipy._lib._array_api, scipy 1.15 on) parses the numpydoc docstring of every function it
    marks, as scipy.ndimage, scipy.special and scipy.sparse.linalg are imported, to append a
    table of array backends to it: 172 parses, most of those imports' Python time. With its
    parser (`FunctionDoc` in that module) replaced by `_UnparsedDoc`, the functions are the
    same and only their docstrings lack the table, which the agent never reads: importing
    numpy, scipy.ndimage and scipy.sparse.linalg, one core, 10 alternated fresh processes,
    CPU 0.258-0.408 -> 0.219-0.342 s. Nothing is done where scipy has no such parser (older
    scipy) or scipy.ndimage is loaded already (too late to matter)."""
    if "scipy.ndimage" in sys.modules:
        return
    try:
        from scipy._lib import _array_api
    except ImportError:
        return
    if hasattr(_array_api, "FunctionDoc") and hasattr(_array_api, "xp_capabilities"):
        _array_api.FunctionDoc = _UnparsedDoc  # type: ignore[attr-defined,unused-ignore]


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


def positive(text: str) -> int:
    """A whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"want a whole number >= 1, got {text!r}")
    return value


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
    if degrees < 0 or metres < 0:
        raise argparse.ArgumentTypeError("DEG and M must be >= 0")
    return degrees, metres


def resolution(text: str) -> tuple[int, int]:
    """`WIDTHxHEIGHT` of a simulated depth image."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError("want WIDTHxHEIGHT, e.g. 1280x720") from None
    if not (16 <= width <= 1280 and 16 <= height <= 800):
        raise argparse.ArgumentTypeError("want 16-1280 x 16-800 pixels")
    return width, height
