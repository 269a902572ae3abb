"""The package finds a libLLVM Dr.Jit accepts, and says what to install when none."""

import os
import subprocess
import sys

import pytest

from hlbvh import environment


def test01_llvm_major_is_read_from_library_names():
    assert environment.llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert environment.llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM-15.so") == 15
    assert environment.llvm_major("/usr/lib/llvm-18/lib/libLLVM.so") == 18


def test02_a_usable_llvm_is_found_here():
    path = environment.find_libllvm()
    assert path is not None and environment.llvm_major(path) >= environment.MIN_LLVM_MAJOR


def _run(code, env):
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)


def test03_a_missing_user_path_fails_with_an_install_hint():
    env = dict(os.environ, DRJIT_LIBLLVM_PATH="/nonexistent/libLLVM.so")
    r = _run("import hlbvh", env)
    assert r.returncode != 0
    assert "libllvm19" in r.stderr and "DRJIT_LIBLLVM_PATH" in r.stderr


def test04_no_llvm_on_the_system_fails_with_one_clear_sentence(monkeypatch):
    monkeypatch.setattr(environment, "candidates", lambda: [(15, "/usr/lib/libLLVM-15.so")])
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setitem(sys.modules, "drjit", None)
    del sys.modules["drjit"]
    with pytest.raises(environment.LLVMNotFoundError, match="apt-get install libllvm19"):
        environment.ensure_llvm()


def test05_doctor_reports_versions_and_runs_a_kernel():
    r = subprocess.run([sys.executable, "-m", "hlbvh.cli", "doctor"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for word in ("drjit", "mitsuba", "libLLVM", "variant", "kernel     ok"):
        assert word in r.stdout
