"""`silo-agent process`: scan directories processed offline (service/batch.py). Lean: what
this imports at the top is what every `process` needs anyway."""

from __future__ import annotations

import argparse

from silo_agent.cli.common import configure_logging, load_config, numpy_unused_lazily
from silo_agent.service import batch


def process(args: argparse.Namespace) -> int:
    numpy_unused_lazily()  # before scipy loads, which would load them all
    config = load_config(args.config) if args.config else None
    if config is not None and config.detection.onnx is not None:
        configure_logging(args)  # the ONNX detector logs; nothing else on this path does
    options = batch.Options(config, args.grid_step, args.method, args.json)
    return batch.run(args.scan_dirs, options, args.jobs)
