#!/usr/bin/env bash
# The test command: bootstrap the venv, then run the whole pytest suite (extra args go to pytest).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
. "$here/bootstrap.sh"
. "$here/ros_env.sh"
cd "$NRSFM_ROOT"
exec "$NRSFM_VENV/bin/python" -m pytest -q "$@"
