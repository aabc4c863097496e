#!/usr/bin/env bash
# Run the whole test suite in both supported Python stacks (what CI runs: .ci/run):
#   1. pinned:  .venv, Python 3 of this machine, the newest releases pinned by constraints.txt
#   2. jazzy:   ROS 2 Jazzy's stack emulated (Python 3.12, apt's numpy 1.26.4, ...) with README's
#               Jazzy install on top (scripts/jazzy_env.sh)
# CGAGS_STACKS="pinned" (or "jazzy") runs one of them. Extra arguments go to pytest.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
stacks="${CGAGS_STACKS:-pinned jazzy}"
for stack in $stacks; do
  case "$stack" in
    pinned)
      "$root/scripts/setup_env.sh"
      echo "[test] pinned stack: $("$root/.venv/bin/python" -c 'import sys, numpy; print(sys.version.split()[0], "numpy", numpy.__version__)')"
      "$root/.venv/bin/python" -m pytest test "$@"
      ;;
    jazzy)
      "$root/scripts/jazzy_env.sh"
      jazzy="${JAZZY_ROOT:-$root/.jazzy}"
      # shellcheck source=/dev/null
      source "$jazzy/setup.bash"
      echo "[test] jazzy stack: $("$jazzy/venv/bin/python" -c 'import sys, numpy; print(sys.version.split()[0], "numpy", numpy.__version__)')"
      CGAGS_JAZZY_STACK=1 "$jazzy/venv/bin/python" -m pytest test -p no:cacheprovider "$@"
      ;;
    *)
      echo "[test] unknown stack '$stack' (pinned, jazzy)" >&2
      exit 2
      ;;
  esac
done
