"""The daemon's modules do not load the offline calibration tool (ICP, pose graph, config
editing): drift monitoring and gravity angles live on the runtime side."""

from __future__ import annotations

import subprocess
import sys

import pytest


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
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]", f"{module} loads {done.stdout.strip()}"


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
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[]", "numpy.testing._private.utils"]


_SCIPY_DOCS = (
    "import sys\n"
    "from silo_agent.cli.common import scipy_docs_unparsed\n"
    "if sys.argv[1] == 'unparsed':\n"
    "    scipy_docs_unparsed()\n"
    "import numpy as np\n"
    "from scipy import ndimage\n"
    "doc = ndimage.uniform_filter1d.__doc__ or ''\n"
    "print('Array API Standard Support' in doc, 'Calculate a 1-D uniform filter' in doc)\n"
    "print(ndimage.uniform_filter1d(np.arange(10.0), 3, mode='constant').tolist())\n"
)


def test_process_leaves_scipy_docstrings_unparsed() -> None:
    """`process` has scipy skip the docstring parse its array-API decorator makes at import
    (`scipy_docs_unparsed`): the docstrings stay as written, without the appended table,
    and the functions compute what they do otherwise."""
    runs = {
        how: subprocess.run(
            [sys.executable, "-c", _SCIPY_DOCS, how], capture_output=True, text=True, timeout=120
        )
        for how in ("unparsed", "parsed")
    }
    for done in runs.values():
        assert done.returncode == 0, done.stderr
    unparsed, parsed = (runs[how].stdout.splitlines() for how in ("unparsed", "parsed"))
    if parsed[0] == "False True":
        pytest.skip("this scipy appends no array-API table to its docstrings")
    assert parsed[0] == "True True"
    assert unparsed[0] == "False True"
    assert unparsed[1] == parsed[1]


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
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        "['silo_agent.config.base', 'silo_agent.config.calibration', "
        "'silo_agent.config.detection', 'silo_agent.config.reconstruction']",
        "True",
        "silo_agent.config.root silo_agent.config.base",
        "module 'silo_agent.config' has no attribute 'NoSuchName'",
    ]


_PLUGINS = (
    "import os, sys\n"
    "os.environ.pop('PYDANTIC_DISABLE_PLUGINS', None)\n"
    "if sys.argv[1] != 'on':\n"
    "    os.environ['PYDANTIC_DISABLE_PLUGINS'] = sys.argv[1]\n"
    "from silo_agent.cli.common import pydantic_plugins_unlooked\n"
    "pydantic_plugins_unlooked()\n"
    "from pydantic import BaseModel\n"
    "class Model(BaseModel):\n"
    "    x: int\n"
    "print(Model.model_validate({'x': 2}).x, 'importlib.metadata' in sys.modules)\n"
    "from pydantic.plugin._loader import get_plugins\n"
    "print(list(get_plugins()))\n"
    "from pydantic.plugin import _loader\n"
    "print(_loader.PYDANTIC_ENTRY_POINT_GROUP, 'importlib.metadata' in sys.modules)\n"
)


@pytest.mark.parametrize(
    ("plugins", "metadata_at_first_model"), [("__all__", False), ("1", False), ("on", True)]
)
def test_pydantic_plugins_off_load_no_package_metadata(plugins, metadata_at_first_model) -> None:
    """With pydantic's plugins off (`process` turns them off), its plugin loader stays a
    stand-in and importlib.metadata (the email package with it) is not imported: models
    validate and no plugin is found. Anything else read of the loader gets the real one; with
    plugins on, the real loader runs from the first model."""
    done = subprocess.run(
        [sys.executable, "-c", _PLUGINS, plugins], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        f"2 {metadata_at_first_model}",
        "[]",
        "pydantic True",
    ]
