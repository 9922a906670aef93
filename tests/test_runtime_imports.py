"""The daemon's modules do not load the offline calibration tool (ICP, pose graph, config
editing): drift monitoring and gravity angles live on the runtime side."""

from __future__ import annotations

import subprocess
import sys

import pytest


def _python(code: str) -> str:
    """What a fresh interpreter running `code` prints (it must succeed)."""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.mark.parametrize(
    "module",
    [
        "silo_agent.service.pipeline",
        "silo_agent.service.daemon",
        "silo_agent.analysis.alarms",
        "silo_agent.analysis.drift",
    ],
)
def test_runtime_module_does_not_load_calibrate(module: str) -> None:
    code = (
        f"import sys, {module}\n"
        "print(sorted(m for m in sys.modules if m.startswith('silo_agent.calibrate')))"
    )
    stdout = _python(code)
    assert stdout.strip() == "[]", f"{module} loads {stdout.strip()}"


def test_process_leaves_numpy_developer_modules_unloaded_until_used() -> None:
    """`process` loads scipy without numpy.testing and numpy.f2py (and the standard library
    modules they pull in); a module that does use one still gets the real thing."""
    code = (
        "import sys\n"
        "from silo_agent.cli.common import numpy_unused_lazily\n"
        "numpy_unused_lazily()\n"
        "import scipy.ndimage, scipy.sparse.linalg\n"
        "print(sorted({'unittest', 'numpy.f2py.crackfortran'} & set(sys.modules)))\n"
        "import numpy.testing\n"
        "numpy.testing.assert_equal(1, 1)\n"
        "print(sys.modules['numpy.testing'].assert_equal.__module__)\n"
    )
    stdout = _python(code)
    assert stdout.split() == ["[]", "numpy.testing._private.utils"]


def test_process_path_builds_only_the_config_sections_it_validates() -> None:
    """The config package imports a section's module when one of its names is first asked
    for: the scan path (reconstruction, detection, calibration settings) loads no other
    section's models, and every public name is still there."""
    code = (
        "import sys\n"
        "import silo_agent.service.scan_path, silo_agent.analysis.scan_analysis\n"
        "print(sorted(m for m in sys.modules if m.startswith('silo_agent.config.')))\n"
        "import silo_agent.config as config\n"
        "from silo_agent.config import *\n"
        "print(all(getattr(config, n) is globals()[n] for n in config.__all__))\n"
        "print(config.Config.__module__, config.describe_validation_error.__module__)\n"
        "try:\n"
        "    config.NoSuchName\n"
        "except AttributeError as exc:\n"
        "    print(exc)\n"
    )
    stdout = _python(code)
    assert stdout.splitlines() == [
        "['silo_agent.config.base', 'silo_agent.config.calibration', "
        "'silo_agent.config.detection', 'silo_agent.config.reconstruction']",
        "True",
        "silo_agent.config.root silo_agent.config.base",
        "module 'silo_agent.config' has no attribute 'NoSuchName'",
    ]
