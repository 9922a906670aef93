"""structlog set-up: a human console on a terminal, one JSON object per line otherwise."""

from __future__ import annotations

import logging
import sys

import structlog


def _stderr_logger(*_args: object) -> structlog.PrintLogger:
    return structlog.PrintLogger(sys.stderr)


class _StderrHandler(logging.StreamHandler):
    """A handler writing to whatever sys.stderr is at each record (as `_stderr_logger`)."""

    @property
    def stream(self) -> object:
        return sys.stderr

    @stream.setter
    def stream(self, _value: object) -> None:
        pass


def configure_logging(level: str = "info", json_output: bool | None = None) -> None:
    """Log to stderr; `json_output=None` picks JSON unless stderr is a TTY. The libraries'
    standard-library records (uvicorn's "Exception in ASGI application", apscheduler's,
    paho's), warnings and above, go the same way, one line each: they had reached stderr as
    plain multi-line tracebacks among the JSON lines."""
    if json_output is None:
        json_output = not sys.stderr.isatty()
    renderer = (
        structlog.processors.JSONRenderer()
        if json_output
        else structlog.dev.ConsoleRenderer(colors=sys.stderr.isatty())
    )
    stamped: list[structlog.typing.Processor] = [
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    handler = _StderrHandler()
    handler.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            foreign_pre_chain=[structlog.stdlib.add_logger_name, *stamped],
            processors=[
                structlog.stdlib.ProcessorFormatter.remove_processors_meta,
                structlog.processors.format_exc_info,
                renderer,
            ],
        )
    )
    root = logging.getLogger()
    root.handlers = [h for h in root.handlers if not isinstance(h, _StderrHandler)] + [handler]
    root.setLevel(logging.WARNING)
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            *stamped,
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
