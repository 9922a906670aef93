"""Each default and each exit status has one home: the outbox bounds, the alarms' fallbacks and
the command line's defaults follow config.py, and exit statuses are defined only in
silo_agent/base/exits.py. Changed at the source, a value must change everywhere."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import silo_agent

ROOT = Path(silo_agent.__file__).parent

# config.py's defaults changed before the modules that use them are imported
FOLLOW_THE_CONFIG = """
import inspect, json
from silo_agent import config

fields = {
    config.MqttConfig: {"outbox_max_messages": 7, "outbox_max_bytes": 8000,
                        "outbox_max_age_days": 2.0},
    config.CameraConfig: {"gravity_tolerance_deg": 9.0},
    config.SiloConfig: {"floor_z": -1.5},
}
for model, values in fields.items():
    for name, value in values.items():
        model.model_fields[name].default = value
# the flags' defaults live in choices.py, which config.py's fields are built from (checked below)
from silo_agent.base import choices
choices.DEFAULT_GRID_STEP_M, choices.DEFAULT_GRAIN = 0.05, "corn"

from silo_agent.analysis.alarms import Inputs
from silo_agent.cli import build_parser
from silo_agent.analysis.drift import DriftMonitor, drift_step
from silo_agent.telemetry.outbox import OutboxLimits

limits = OutboxLimits()
args = build_parser().parse_args(["simulate", "--scene", "cone", "--views", "A1", "--out", "x"])
print(json.dumps({
    "outbox": [limits.max_messages, limits.max_bytes, limits.max_age_s],
    "drift_step": inspect.signature(drift_step).parameters["gravity_tolerance_deg"].default,
    "monitor": inspect.signature(DriftMonitor).parameters["gravity_tolerance_deg"].default,
    "floor_z": Inputs.__dataclass_fields__["floor_z"].default,
    "grid_step": args.grid_step,
    "grain": args.grain,
}))
"""


def test_defaults_follow_config_py() -> None:
    done = subprocess.run(
        [sys.executable, "-c", FOLLOW_THE_CONFIG], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == {
        "outbox": [7, 8000, 2.0 * 86400],
        "drift_step": 9.0,
        "monitor": 9.0,
        "floor_z": -1.5,
        "grid_step": 0.05,
        "grain": "corn",
    }


def test_config_fields_take_the_shared_choices() -> None:
    from silo_agent import config
    from silo_agent.base import choices

    reconstruction, simulation = config.ReconstructionConfig(), config.SimulationConfig()
    assert reconstruction.method == choices.DEFAULT_METHOD
    assert reconstruction.grid_step_m == choices.DEFAULT_GRID_STEP_M
    assert (simulation.grain, simulation.layout) == (choices.DEFAULT_GRAIN, choices.DEFAULT_LAYOUT)
    fields = config.ReconstructionConfig.model_fields, config.SimulationConfig.model_fields
    assert fields[0]["method"].annotation is choices.Method
    assert (fields[1]["grain"].annotation, fields[1]["layout"].annotation) == (
        choices.Grain,
        choices.Layout,
    )


def test_exit_statuses_are_defined_only_in_exits() -> None:
    status_names = {"OK", "FAILURE", "USAGE", "DATA_ERROR", "CONFIG_ERROR", "INTERRUPTED"}
    defined = []
    for path in sorted(ROOT.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Assign):
                names = [t.id for t in node.targets if isinstance(t, ast.Name)]
                defined += [
                    f"{path.relative_to(ROOT)}: {n}"
                    for n in names
                    if n.startswith("EX_") or n in status_names
                ]
    assert defined and all(d.startswith("base/exits.py:") for d in defined), defined
