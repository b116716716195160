#!/usr/bin/env bash
# Create or reuse the project's virtual environment (.venv) idempotently.
# Source it (". launch_scripts/bootstrap.sh") or run it; afterwards $NRSFM_VENV/bin/python works.
# A second run compares a stamp of requirements.txt + setup.py and installs nothing.
set -euo pipefail
NRSFM_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
NRSFM_VENV="${NRSFM_VENV:-$NRSFM_ROOT/.venv}"
export NRSFM_ROOT NRSFM_VENV
_py="${PYTHON:-}"
if [ -z "$_py" ]; then
  for c in python3.11 python3; do
    if command -v "$c" >/dev/null 2>&1 && "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      _py="$c"; break
    fi
  done
fi
[ -n "$_py" ] || { echo "error: Python 3.11 is required (the ROS 2 Jazzy wheels are cp311)" >&2; exit 1; }
_stamp="$(cat "$NRSFM_ROOT/requirements.txt" "$NRSFM_ROOT/setup.py" "$NRSFM_ROOT/setup.cfg" | sha256sum | cut -d' ' -f1)"
if [ -f "$NRSFM_VENV/.bootstrap-stamp" ] && [ "$(cat "$NRSFM_VENV/.bootstrap-stamp")" = "$_stamp" ] \
   && [ -x "$NRSFM_VENV/bin/python" ]; then
  echo "bootstrap: $NRSFM_VENV is up to date (nothing to install)" >&2
else
  echo "bootstrap: creating $NRSFM_VENV with $_py" >&2
  [ -x "$NRSFM_VENV/bin/python" ] || "$_py" -m venv "$NRSFM_VENV"
  "$NRSFM_VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
  "$NRSFM_VENV/bin/python" -m pip install -q --disable-pip-version-check -r "$NRSFM_ROOT/requirements.txt"
  "$NRSFM_VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps \
      --no-build-isolation -e "$NRSFM_ROOT"
  echo "$_stamp" > "$NRSFM_VENV/.bootstrap-stamp"
  echo "bootstrap: done" >&2
fi
