#!/usr/bin/env bash
# Set up (or refresh) nvp's virtual environment in .venv. Idempotent; needs only Python 3.11 and the
# package registries. pyproject.toml pins torch==2.13.0, which on these machines pip takes from the local
# CPU build (a newer or unpinned torch would pull a CUDA build of several GB).
#   bash scripts/setup.sh          # nvp + test tools + the cluster extra (Dask, for nvp cluster; its tests)
#   bash scripts/setup.sh tts      # also the optional text-to-speech extra (piper, GPL-3.0)
set -euo pipefail
cd "$(dirname "$0")/.."
extras="dev,cluster"
for extra in "$@"; do
  case "$extra" in
    tts) extras="$extras,tts" ;;
    cluster) ;;  # always installed: small, and CI runs its tests
    *) echo "setup.sh: unknown extra '$extra' (known: tts, cluster)" >&2; exit 2 ;;
  esac
done
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[$extras]" 2>&1 \
  | grep -v "^WARNING: Location" || true
.venv/bin/python -m pip check
