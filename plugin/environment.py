"""Find a libLLVM that Dr.Jit's LLVM backend accepts, before ``drjit`` is imported.

Dr.Jit loads ``libLLVM`` at run time. Debian 12's default LLVM 15 crashes Dr.Jit 1.5 at
the first real kernel ("Cannot select: fminimum"); LLVM 16 and newer work (Debian's
``libllvm19`` is the tested one). This module picks the newest suitable library it can
find and exports it through ``DRJIT_LIBLLVM_PATH``, unless the user already set that
variable, which is always respected.

It also keeps Ctrl-C while the ``hlbvh`` command starts (importing Dr.Jit and Mitsuba
takes a while) from ending in a traceback out of an import: see
:func:`exit_quietly_on_interrupt`.
"""

from __future__ import annotations

import glob
import os
import re
import signal
import sys
import threading

#: Oldest LLVM major version known to work with Dr.Jit 1.5.
MIN_LLVM_MAJOR = 16

INSTALL_HINT = (
    "install Debian's libllvm19 (`apt-get install libllvm19`) or point "
    "DRJIT_LIBLLVM_PATH at a libLLVM.so of version 16 or newer "
    "(LLVM 15, Debian 12's default, crashes Dr.Jit 1.5)"
)

_SEARCH_PATTERNS = (
    "/usr/lib/*/libLLVM*.so*",
    "/usr/lib/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
)


class LLVMNotFoundError(ImportError):
    """No libLLVM usable by Dr.Jit was found."""


def llvm_major(path: str) -> int | None:
    """The LLVM major version encoded in a library file name, or None."""
    name = os.path.basename(path)
    m = re.search(r"libLLVM[-.]?(\d+)", name) or re.search(r"llvm-(\d+)", path)
    if m is None:
        m = re.search(r"\.so\.(\d+)", name)
    return int(m.group(1)) if m else None


def candidates() -> list[tuple[int, str]]:
    """Every libLLVM on the usual system paths, as (major version, path), newest first."""
    found = {}
    for pattern in _SEARCH_PATTERNS:
        for path in glob.glob(pattern):
            major = llvm_major(path)
            if major is not None and os.path.isfile(path):
                found.setdefault(os.path.realpath(path), (major, path))
    return sorted(found.values(), key=lambda mp: (-mp[0], mp[1]))


def find_libllvm() -> str | None:
    """The path of the newest libLLVM of version >= MIN_LLVM_MAJOR, or None."""
    for major, path in candidates():
        if major >= MIN_LLVM_MAJOR:
            return path
    return None


def ensure_llvm() -> str | None:
    """Export DRJIT_LIBLLVM_PATH before drjit loads; return the path in use.

    Returns None when no suitable library exists: a machine with a GPU and no libLLVM
    runs on Dr.Jit's CUDA backend alone, and :func:`check_backend` (after Dr.Jit is
    imported) raises LLVMNotFoundError with the install hint only when neither backend
    works. A DRJIT_LIBLLVM_PATH the user set is always respected, and refused when it
    names no file.
    """
    user = os.environ.get("DRJIT_LIBLLVM_PATH")
    if user:
        if not os.path.isfile(user):
            raise LLVMNotFoundError(
                f"DRJIT_LIBLLVM_PATH={user!r} does not exist: {INSTALL_HINT}."
            )
        return user
    if "drjit" in sys.modules:
        return None  # too late to choose; check_backend() tells whether it works
    path = find_libllvm()
    if path is None:
        return None  # CUDA may still work: check_backend() decides
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def check_backend() -> None:
    """Fail with one clear sentence when neither the LLVM nor the CUDA backend works."""
    import drjit as dr

    if dr.has_backend(dr.JitBackend.LLVM):
        major = dr.detail.llvm_version()[0]
        if major < MIN_LLVM_MAJOR:
            # Dr.Jit was imported before hlbvh and chose an LLVM that crashes it.
            raise LLVMNotFoundError(
                f"Dr.Jit loaded LLVM {major}, which crashes Dr.Jit 1.5: import hlbvh before "
                f"drjit/mitsuba, or {INSTALL_HINT}."
            )
        return
    if dr.has_backend(dr.JitBackend.CUDA):
        return
    chosen = os.environ.get("DRJIT_LIBLLVM_PATH")
    if chosen is None:
        raise LLVMNotFoundError(
            f"hlbvh found no usable libLLVM and no CUDA device: {INSTALL_HINT}."
        )
    raise LLVMNotFoundError(
        f"Dr.Jit could not initialise its LLVM backend with {chosen!r} and found no "
        f"CUDA device: {INSTALL_HINT}."
    )


def exit_quietly_on_interrupt() -> None:
    """While the ``hlbvh`` command starts, make Ctrl-C end it with one line and exit
    status 130 instead of a ``KeyboardInterrupt`` traceback out of whichever import it
    lands in; :func:`end_of_start_up` gives Ctrl-C back to Python once the command
    line is parsed. Only the ``hlbvh`` console script is affected (its ``__main__`` is
    a file named ``hlbvh``), and only where Python's own handler is in place: a program
    that imports hlbvh keeps its Ctrl-C."""
    main = sys.modules.get("__main__")
    if (os.path.basename(getattr(main, "__file__", None) or "") == "hlbvh"
            and threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
        signal.signal(signal.SIGINT, _interrupted_while_starting)


def end_of_start_up() -> None:
    """Python's Ctrl-C handler back in place of :func:`exit_quietly_on_interrupt`'s."""
    if signal.getsignal(signal.SIGINT) is _interrupted_while_starting:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _interrupted_while_starting(signum, frame):
    print("hlbvh: interrupted", file=sys.stderr)
    raise SystemExit(130)


exit_quietly_on_interrupt()
