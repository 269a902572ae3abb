"""Before pytest imports a test module: the test folders on sys.path (folders.py)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from folders import on_path  # noqa: E402

on_path()
