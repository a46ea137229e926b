#!/usr/bin/env bash
# Run the whole test suite. Installs everything (service, datagen, training with CPU torch)
# into .venv on first use. Extra arguments go to pytest, e.g. -k service.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/pytest ] || [ pyproject.toml -nt .venv/.installed ]; then
  python3 -m venv .venv
  .venv/bin/pip install -q --disable-pip-version-check -e ".[all]"
  touch .venv/.installed
fi
exec .venv/bin/python -m pytest "$@"
