#!/usr/bin/env bash
# Start the scoring service on the bundled default model (http://127.0.0.1:8000, docs at /docs).
# Installs only the service's dependencies (no torch) into .venv-service on first use.
# Extra arguments go to vgq-serve, e.g. --port 9000 --host 0.0.0.0 (see --help).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv-service/bin/vgq-serve ] || [ pyproject.toml -nt .venv-service/.installed ]; then
  python3 -m venv .venv-service
  .venv-service/bin/pip install -q --disable-pip-version-check -e ".[service]"
  touch .venv-service/.installed
fi
exec .venv-service/bin/vgq-serve "$@"
