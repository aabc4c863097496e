#!/usr/bin/env bash
# Run the test suite.
#
#   bash scripts/test.sh           everything, in both supported Python stacks (what CI runs: .ci/run):
#     1. pinned: .venv, Python 3 of this machine, the newest releases pinned by constraints.txt
#     2. jazzy:  ROS 2 Jazzy's stack emulated (Python 3.12, apt's numpy 1.26.4, ...) with README's
#                Jazzy install on top (scripts/jazzy_env.sh); without the tests marked source_only
#                when the pinned stack ran them
#   bash scripts/test.sh --fast    the inner loop: the pinned stack only, without the tests marked
#                                  ros, subprocess or slow (setup.cfg lists the markers)
#
# CGAGS_STACKS="pinned" (or "jazzy") runs one stack. Other arguments go to pytest.
# Outside CI a machine without a CPython 3.12 (or without the FreeType/Qhull headers and no apt to
# install them) runs the pinned stack and says the Jazzy stack was skipped; under CI (CI=true)
# both stacks are required.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
stacks="${CGAGS_STACKS:-pinned jazzy}"
args=()
for arg in "$@"; do
  if [ "$arg" = "--fast" ]; then
    stacks="pinned"
    args+=(-m "not ros and not subprocess and not slow")
  else
    args+=("$arg")
  fi
done

# Why the Jazzy stack cannot be built here, or nothing when it can.
jazzy_missing() {
  if [ -z "${JAZZY_PYTHON:-}" ] && ! ls -d "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.12.* >/dev/null 2>&1 \
      && ! command -v python3.12 >/dev/null; then
    echo "no CPython 3.12 (pyenv install 3.12, apt install python3.12, or set JAZZY_PYTHON)"
  elif [ ! -d "${JAZZY_ROOT:-$root/.jazzy}/system" ] && ! command -v apt-get >/dev/null \
      && { [ ! -f /usr/include/libqhull_r/libqhull_r.h ] || ! pkg-config --exists freetype2 2>/dev/null; }; then
    echo "no FreeType/Qhull headers to build matplotlib 3.6.3 (apt install libfreetype-dev libqhull-dev pkg-config)"
  fi
}

for stack in $stacks; do
  case "$stack" in
    pinned)
      "$root/scripts/setup_env.sh"
      echo "[test] pinned stack: $("$root/.venv/bin/python" -c 'import sys, numpy; print(sys.version.split()[0], "numpy", numpy.__version__)')"
      "$root/.venv/bin/python" -m pytest test ${args[@]+"${args[@]}"}
      ;;
    jazzy)
      missing="$(jazzy_missing)"
      if [ -n "$missing" ]; then
        if [ "${CI:-}" = "true" ]; then
          echo "[test] the Jazzy stack is required under CI: $missing" >&2
          exit 1
        fi
        echo "[test] SKIPPED the Jazzy stack (Python 3.12, apt's numpy 1.26.4): $missing." >&2
        echo "[test] Only the pinned stack ran; CI runs both." >&2
        continue
      fi
      "$root/scripts/jazzy_env.sh"
      jazzy="${JAZZY_ROOT:-$root/.jazzy}"
      # shellcheck source=/dev/null
      source "$jazzy/setup.bash"
      echo "[test] jazzy stack: $("$jazzy/venv/bin/python" -c 'import sys, numpy; print(sys.version.split()[0], "numpy", numpy.__version__)')"
      # The tests marked source_only read the repository's text and syntax (docs, comments,
      # layers, generated files), which no Python stack changes: when the pinned stack runs them,
      # the Jazzy one need not run them again. A -m of the arguments comes later and wins.
      only=()
      case " $stacks " in *" pinned "*) only=(-m "not source_only") ;; esac
      CGAGS_JAZZY_STACK=1 "$jazzy/venv/bin/python" -m pytest test -p no:cacheprovider \
          ${only[@]+"${only[@]}"} ${args[@]+"${args[@]}"}
      ;;
    *)
      echo "[test] unknown stack '$stack' (pinned, jazzy)" >&2
      exit 2
      ;;
  esac
done
