#!/usr/bin/env bash
# The first command to try: set up .venv (scripts/setup_env.sh), then replay the bundled
# bags (bunny, redkitchen, lidar) live through the register_node and print recall and
# RE/TE against their ground truth. Results and plots: out/demo/<bag>/.
# Extra arguments go to cgags-demo (e.g. --offline, --bags lidar, --rate 0.5).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$root/scripts/setup_env.sh"
cd "$root"
# Keep the demo's DDS traffic on this machine unless the caller chose otherwise.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
exec "${CGAGS_VENV:-$root/.venv}/bin/python" -m cgags_ros.tools.demo "$@"
