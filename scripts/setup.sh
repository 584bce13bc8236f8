#!/usr/bin/env bash
# Set up (or refresh) nvp's virtual environment in .venv. Idempotent; needs only Python 3.11 and the
# package registries. torch is pinned to the CPU build in pyproject.toml.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e '.[dev]' 2>&1 \
  | grep -v "^WARNING: Location" || true
.venv/bin/python -m pip check
