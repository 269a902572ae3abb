"""A regular install, as a user gets it: the wheel built from the checkout holds every
sub-package (found by setup.py, not listed by hand), and once installed into a folder
of its own it imports, runs ``hlbvh doctor`` and renders a frame from a working
directory outside the checkout, without the editable install standing in for it."""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The sub-packages a user imports: each folder of the repository, and plugin's own.
SUB_PACKAGES = ("accel", "render", "cli", "integrators", "kernels", "scenes", "comparison")

#: What is never part of the sources the wheel is built from.
NOT_SOURCES = shutil.ignore_patterns(".git", ".venv", "out", "build", "*.egg-info",
                                     "__pycache__", ".pytest_cache", ".hypothesis")


def _run(argv, cwd, env=None):
    """``argv`` run in ``cwd``; its stdout (the test fails with stderr on an error)."""
    done = subprocess.run([str(a) for a in argv], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, (argv, done.stdout[-2000:], done.stderr[-4000:])
    return done.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(wheel, target)``: the wheel built from a copy of the checkout's sources (the
    build leaves its build/ and egg-info there, not in the shared checkout), and the
    folder it is installed into."""
    base = tmp_path_factory.mktemp("packaging")
    sources = base / "sources"
    shutil.copytree(ROOT, sources, ignore=NOT_SOURCES, symlinks=True)
    wheels, target = base / "wheels", base / "target"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
          "-q", "-w", wheels, "."], cwd=sources)
    (wheel,) = wheels.glob("hlbvh-*.whl")
    _run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", target,
          wheel], cwd=base)
    return wheel, target


def _user_env(target: Path) -> dict:
    """The environment of a user whose ``hlbvh`` is the one installed in ``target``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    env["PYTHONPATH"] = str(target)
    return env


def test01_the_wheel_holds_every_sub_package(installed):
    wheel, _ = installed
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "hlbvh/__init__.py" in names
    for sub in SUB_PACKAGES:
        assert f"hlbvh/{sub}/__init__.py" in names, sub
    assert not any(name.startswith(("tests/", "plugin/")) for name in names)


def test02_the_installed_package_imports_runs_doctor_and_renders(installed, tmp_path):
    """From a folder outside the checkout: ``hlbvh`` is the installed one (not the
    editable install's), ``python -m hlbvh.cli doctor`` and the ``hlbvh`` script's
    render of one small frame succeed, and the frame's files are written."""
    _, target = installed
    away = tmp_path / "elsewhere"
    away.mkdir()
    env = _user_env(target)
    found = _run([sys.executable, "-c",
                  "import hlbvh, hlbvh.kernels, hlbvh.accel, hlbvh.render, hlbvh.cli, "
                  "hlbvh.integrators, hlbvh.scenes, hlbvh.comparison\n"
                  "for m in (hlbvh, hlbvh.kernels, hlbvh.accel, hlbvh.scenes):\n"
                  "    print(m.__file__)"], cwd=away, env=env).split()
    assert len(found) == 4
    for path in found:
        assert Path(path).resolve().is_relative_to(target.resolve()), path
    assert "mitsuba" in _run([sys.executable, "-m", "hlbvh.cli", "doctor"], cwd=away,
                             env=env).lower()
    out = tmp_path / "frames"
    _run([target / "bin" / "hlbvh", "render", "cloth", "--triangles", 200, "--frames", 1,
          "--resolution", 16, "--spp", 1, "--out", out], cwd=away, env=env)
    for name in ("frame_0000.exr", "frame_0000.png", "stats.csv"):
        assert (out / name).is_file(), sorted(p.name for p in out.iterdir())
