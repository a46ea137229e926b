#!/usr/bin/env bash
# Run the whole test suite, after ruff's lint and format check. Installs everything (service,
# datagen, training, test extras) into .venv on first use. Extra arguments go to pytest, e.g. -k service.
#
# torch: on a machine without an NVIDIA GPU the CPU-only build is installed from torch's CPU
# wheel index (no NVIDIA CUDA wheels). If that index cannot be reached within a few seconds,
# torch comes from the default index instead (a note says so). VGQ_TORCH chooses:
#   VGQ_TORCH=auto  (default) CPU build without an NVIDIA GPU, default index with one
#   VGQ_TORCH=cpu   always the CPU build (falls back to the default index if unreachable)
#   VGQ_TORCH=default  the default index (PyPI's Linux build pulls the CUDA libraries)
set -euo pipefail
cd "$(dirname "$0")/.."
CPU_INDEX=${VGQ_TORCH_CPU_INDEX:-https://download.pytorch.org/whl/cpu}
REACH_TIMEOUT_S=${VGQ_TORCH_INDEX_TIMEOUT_S:-5}

torch_pin() {  # the torch version the train extra pins (pyproject.toml), e.g. 2.13.0
  sed -n 's/^ *"torch==\([^"]*\)".*/\1/p' pyproject.toml | head -1
}

has_nvidia_gpu() {
  command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1
}

index_reachable() {  # $1 answers within REACH_TIMEOUT_S seconds
  .venv/bin/python - "$1" "$REACH_TIMEOUT_S" <<'EOF' >/dev/null 2>&1
import sys
import urllib.request

urllib.request.urlopen(sys.argv[1].rstrip("/") + "/torch/", timeout=float(sys.argv[2])).close()
EOF
}

install_torch() {
  local choice=${VGQ_TORCH:-auto} pin
  pin=$(torch_pin)
  case "$choice" in
    auto) if has_nvidia_gpu; then choice=default; else choice=cpu; fi ;;
    cpu|default) ;;
    *) echo "VGQ_TORCH must be auto, cpu or default, got '$choice'" >&2; exit 2 ;;
  esac
  if [ "$choice" = cpu ]; then
    if index_reachable "$CPU_INDEX"; then
      echo "installing CPU-only torch $pin from $CPU_INDEX (no NVIDIA GPU found or VGQ_TORCH=cpu;" \
           "VGQ_TORCH=default for the default index)"
      .venv/bin/pip install -q --disable-pip-version-check --extra-index-url "$CPU_INDEX" "torch==$pin+cpu"
      return
    fi
    echo "note: torch's CPU index ($CPU_INDEX) did not answer within ${REACH_TIMEOUT_S} s;" \
         "installing torch $pin from the default index (on Linux that build may pull NVIDIA CUDA wheels)"
  fi
}

if [ ! -x .venv/bin/pytest ] || [ pyproject.toml -nt .venv/.installed ]; then
  python3 -m venv .venv
  install_torch
  .venv/bin/pip install -q --disable-pip-version-check -e ".[all]"
  touch .venv/.installed
fi
# lint and format check first (ruff, configured in pyproject.toml); VGQ_LINT=0 skips it
if [ "${VGQ_LINT:-1}" != 0 ]; then
  .venv/bin/ruff check --quiet . && .venv/bin/ruff format --check --quiet . \
    || { echo "ruff: fix the above (ruff check --fix . && ruff format .), or VGQ_LINT=0 to skip" >&2; exit 1; }
fi
# test files run in parallel worker processes (pytest-xdist; each file on one worker, in its own
# order): one per core up to 4; VGQ_TEST_WORKERS=0 runs them in this process (so does -n 0)
cores=$(nproc 2>/dev/null || echo 1)
workers=${VGQ_TEST_WORKERS:-$(( cores < 4 ? cores : 4 ))}
if [ "$workers" -le 1 ] 2>/dev/null; then workers=0; fi
exec .venv/bin/python -m pytest -n "$workers" --dist loadfile "$@"
