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


def test04_no_llvm_on_the_system_leaves_the_choice_to_the_backends(monkeypatch):
    """No libLLVM >= 16 on the system: import goes on (a CUDA-only machine runs on its
    GPU), and check_backend() says what to install only when CUDA does not work either."""
    monkeypatch.setattr(environment, "candidates", lambda: [(15, "/usr/lib/libLLVM-15.so")])
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setitem(sys.modules, "drjit", None)
    del sys.modules["drjit"]
    assert environment.ensure_llvm() is None
    assert "DRJIT_LIBLLVM_PATH" not in os.environ


def test04b_without_llvm_or_cuda_the_check_says_what_to_install(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    _backends(monkeypatch, llvm=False, cuda=False)
    with pytest.raises(environment.LLVMNotFoundError,
                       match="no usable libLLVM and no CUDA device.*apt-get install libllvm19"):
        environment.check_backend()


def test05_doctor_reports_versions_and_runs_a_kernel():
    r = subprocess.run([sys.executable, "-m", "hlbvh.cli", "doctor"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for word in ("drjit", "mitsuba", "libLLVM", "variant", "kernel     ok"):
        assert word in r.stdout


# ---------------------------------------------------------------------------------------
# The backend check and the variant choice, with Dr.Jit's answers stubbed at the
# boundary (dr.has_backend, dr.detail.llvm_version): no CUDA device is needed to run
# the CUDA branches.
# ---------------------------------------------------------------------------------------


def _backends(monkeypatch, llvm: bool, cuda: bool, llvm_version=(19, 1, 7)):
    import drjit as dr

    available = {dr.JitBackend.LLVM: llvm, dr.JitBackend.CUDA: cuda}
    monkeypatch.setattr(dr, "has_backend", lambda backend: available[backend])
    monkeypatch.setattr(dr.detail, "llvm_version", lambda: llvm_version)


def test06_check_backend_accepts_cuda_alone(monkeypatch):
    """No LLVM backend but a CUDA one (a GPU machine without libLLVM): usable."""
    _backends(monkeypatch, llvm=False, cuda=True)
    assert environment.check_backend() is None


def test07_check_backend_refuses_an_old_llvm_even_with_cuda(monkeypatch):
    """Dr.Jit imported before hlbvh chose LLVM 15: refused, naming the version and the
    fix, whether or not a GPU exists (the LLVM backend would crash the first kernel)."""
    for cuda in (False, True):
        _backends(monkeypatch, llvm=True, cuda=cuda, llvm_version=(15, 0, 7))
        with pytest.raises(environment.LLVMNotFoundError,
                           match="Dr.Jit loaded LLVM 15.*import hlbvh before drjit"):
            environment.check_backend()
    _backends(monkeypatch, llvm=True, cuda=False, llvm_version=(environment.MIN_LLVM_MAJOR, 0, 0))
    assert environment.check_backend() is None


def test08_check_backend_without_any_backend_says_what_to_install(monkeypatch):
    _backends(monkeypatch, llvm=False, cuda=False)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/opt/llvm/libLLVM.so.18")
    with pytest.raises(environment.LLVMNotFoundError,
                       match="could not initialise its LLVM backend with "
                             "'/opt/llvm/libLLVM.so.18'.*libllvm19"):
        environment.check_backend()


# In a fresh process: Dr.Jit's backends stubbed, mi.set_variant recorded (and the LLVM
# variant set, this machine's), then ``import hlbvh`` chooses its variant.
_CHOOSE = """
import drjit as dr, mitsuba as mi
available = {{dr.JitBackend.LLVM: {llvm}, dr.JitBackend.CUDA: {cuda}}}
dr.has_backend = lambda backend: available[backend]
chosen, real = [], mi.set_variant
mi.set_variant = lambda *names: (chosen.extend(names), real("llvm_ad_rgb"))
import hlbvh
print(chosen)
"""


@pytest.mark.parametrize("llvm, cuda, expected", [
    (True, True, "cuda_ad_rgb"),     # a working GPU wins
    (False, True, "cuda_ad_rgb"),    # a GPU machine without a usable libLLVM
    (True, False, "llvm_ad_rgb"),    # the CPU
])
def test09_import_chooses_cuda_where_a_gpu_works(llvm, cuda, expected):
    r = _run(_CHOOSE.format(llvm=llvm, cuda=cuda), dict(os.environ))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == repr([expected])


def test10_import_keeps_a_variant_already_set():
    """A variant the user set before ``import hlbvh`` is kept (no set_variant call),
    even where CUDA works."""
    code = _CHOOSE.replace("import hlbvh", "real('llvm_ad_rgb'); import hlbvh")
    r = _run(code.format(llvm=True, cuda=True), dict(os.environ))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"


def test11_the_real_backends_choose_the_variant():
    """Unstubbed: ``cuda_ad_rgb`` exactly where Dr.Jit's CUDA backend works (a machine
    with a GPU runs the CUDA branch for real), ``llvm_ad_rgb`` elsewhere."""
    r = _run("import hlbvh, drjit as dr, mitsuba as mi; "
             "print(dr.has_backend(dr.JitBackend.CUDA), mi.variant())", dict(os.environ))
    assert r.returncode == 0, r.stderr
    cuda, variant = r.stdout.split()[-2:]
    assert variant == ("cuda_ad_rgb" if cuda == "True" else "llvm_ad_rgb")
