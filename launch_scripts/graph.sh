#!/usr/bin/env bash
# Start the four nodes as separate processes with loopback-only DDS; Ctrl-C stops them cleanly;
# restarts a node that dies (backoff; --max-restarts N, 0: stop the graph) and exits non-zero
# only when it gives up.  Feed it with: nrsfm-ros replay <bag> (another terminal).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
. "$here/bootstrap.sh"
. "$here/ros_env.sh"
echo "graph on ROS_DOMAIN_ID=$ROS_DOMAIN_ID (use the same in other terminals)" >&2
exec "$NRSFM_VENV/bin/python" -m nrsfm_ros.launch "$@"
