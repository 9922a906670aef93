"""structlog set-up: a human console on a terminal, one JSON object per line otherwise."""

from __future__ import annotations

import logging
import sys

import structlog


def _stderr_logger(*_args: object) -> structlog.PrintLogger:
    return structlog.PrintLogger(sys.stderr)


def configure_logging(level: str = "info", json_output: bool | None = None) -> None:
    """Log to stderr; `json_output=None` picks JSON unless stderr is a TTY."""
    if json_output is None:
        json_output = not sys.stderr.isatty()
    renderer = (
        structlog.processors.JSONRenderer()
        if json_output
        else structlog.dev.ConsoleRenderer(colors=sys.stderr.isatty())
    )
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            structlog.processors.format_exc_info,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(
            logging.getLevelNamesMapping()[level.upper()]
        ),
        # Resolve sys.stderr at each call: a stream fixed here may be closed or
        # swapped later (pytest capture, daemonisers), killing whoever logs next.
        logger_factory=_stderr_logger,
        cache_logger_on_first_use=False,
    )
