#!/usr/bin/env bash
# Set up everything hlbvh needs on a fresh Debian machine, idempotently, then run a job.
#   bash run.sh main    a short animated render, hlbvh and native, plus their comparison
#   bash run.sh test    the test suite
#   bash run.sh setup   only the set-up
set -euo pipefail
cd "$(dirname "$0")"
job="${1:-main}"

# ---- A libLLVM that Dr.Jit 1.5 accepts (Debian 12's LLVM 15 crashes it) ----
if ! ls /usr/lib/*/libLLVM*.so.19* /usr/lib/*/libLLVM-19.so >/dev/null 2>&1 \
   && [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19
  else
    echo "run.sh: Dr.Jit needs libLLVM 16 or newer: run 'apt-get install libllvm19' as root," \
         "or set DRJIT_LIBLLVM_PATH to such a libLLVM.so" >&2
    exit 1
  fi
fi

# ---- Headless Chromium for the report test (HTML pages must show their images) ----
if [ "$job" = test ] && ! command -v chromium >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium \
      || echo "run.sh: chromium could not be installed; the browser test will be skipped" >&2
  fi
fi

# ---- The virtual environment and the package ----
PY="${PYTHON:-python3}"
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.hlbvh-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ setup.py -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[test]"
  touch "$stamp"
fi

case "$job" in
  setup) .venv/bin/hlbvh doctor ;;
  main)  .venv/bin/hlbvh compare world --frames 0:12 --resolution 480x270 --spp 4 \
           --blur-frame 6 --shutter 0.5 --sub-frames 4 --out out/main ;;
  test)  .venv/bin/python -m pytest -q -m "slow or not slow" tests ;;
  *) echo "run.sh: unknown job '$job' (expected main, test or setup)" >&2; exit 2 ;;
esac
