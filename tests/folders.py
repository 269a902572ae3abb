"""The test folders, on sys.path. Tests import the helpers here (meshes.py,
reference.py, bvh_check.py, cli_helpers.py) and a few of each other's scenes and
renderers (test_accel's cornell_box, test_integrators' render, ...) by module name,
from whichever folder of tests/ they live in: conftest.py calls :func:`on_path` before
pytest imports a test, and a test that starts a fresh Python hands it :data:`FOLDERS`."""

import sys
from pathlib import Path

#: tests/ itself.
TESTS = Path(__file__).resolve().parent

#: tests/ and each folder under it that holds tests (one per package they mirror).
FOLDERS = [str(TESTS)] + sorted({str(p.parent) for p in TESTS.rglob("test_*.py")} - {str(TESTS)})


def on_path():
    """Every folder of :data:`FOLDERS` on ``sys.path`` (those already there kept)."""
    sys.path[:0] = [folder for folder in FOLDERS if folder not in sys.path]
