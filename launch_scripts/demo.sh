#!/usr/bin/env bash
# The main job: bootstrap the venv, then run the full node graph on the sample bag.
# Extra arguments go to `nrsfm-ros demo` (see --help).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
. "$here/bootstrap.sh"
. "$here/ros_env.sh"
cd "$NRSFM_ROOT"
exec "$NRSFM_VENV/bin/nrsfm-ros" demo "$@"
