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
# With both stacks and no other arguments, the tests that run in the pytest process alone (not
# marked ros or subprocess) run in the two stacks side by side, each printing when both end; the
# tests with DDS or processes of their own then run one stack after the other, so that no two
# contend for the cores or a DDS domain.
#
# CGAGS_STACKS="pinned" (or "jazzy") runs one stack. Other arguments go to pytest, and run the
# stacks one after the other.
# Outside CI a machine without a CPython 3.12 (or without the FreeType/Qhull headers and no apt to
# install them) runs the pinned stack and says the Jazzy stack was skipped; under CI (CI=true)
# both stacks are required.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
stacks="${CGAGS_STACKS:-pinned jazzy}"
jazzy="${JAZZY_ROOT:-$root/.jazzy}"
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
  elif [ ! -d "$jazzy/system" ] && ! command -v apt-get >/dev/null \
      && { [ ! -f /usr/include/libqhull_r/libqhull_r.h ] || ! pkg-config --exists freetype2 2>/dev/null; }; then
    echo "no FreeType/Qhull headers to build matplotlib 3.6.3 (apt install libfreetype-dev libqhull-dev pkg-config)"
  fi
}

# Set a stack up and say which it is; fail (status 1) when the Jazzy stack is skipped here. Called
# as a condition, where `set -e` does not apply: a failed setup exits by itself.
prepare() {
  case "$1" in
    pinned)
      "$root/scripts/setup_env.sh" || exit 1
      echo "[test] pinned stack: $("$root/.venv/bin/python" -c 'import sys, numpy; print(sys.version.split()[0], "numpy", numpy.__version__)')"
      ;;
    jazzy)
      local missing
      missing="$(jazzy_missing)"
      if [ -n "$missing" ]; then
        if [ "${CI:-}" = "true" ]; then
          echo "[test] the Jazzy stack is required under CI: $missing" >&2
          exit 1
        fi
        echo "[test] SKIPPED the Jazzy stack (Python 3.12, apt's numpy 1.26.4): $missing." >&2
        echo "[test] Only the pinned stack ran; CI runs both." >&2
        return 1
      fi
      "$root/scripts/jazzy_env.sh" || exit 1
      echo "[test] jazzy stack: $(source "$jazzy/setup.bash"; "$jazzy/venv/bin/python" -c 'import sys, numpy; print(sys.version.split()[0], "numpy", numpy.__version__)')"
      ;;
    *)
      echo "[test] unknown stack '$1' (pinned, jazzy)" >&2
      exit 2
      ;;
  esac
}

# Run pytest in a stack (in a subshell: the Jazzy stack's setup.bash changes the environment).
run() {
  local stack="$1"
  shift
  case "$stack" in
    pinned) "$root/.venv/bin/python" -m pytest test "$@" ;;
    jazzy)
      ( # shellcheck source=/dev/null
        source "$jazzy/setup.bash"
        CGAGS_JAZZY_STACK=1 "$jazzy/venv/bin/python" -m pytest test -p no:cacheprovider "$@" )
      ;;
  esac
}

ready=()
for stack in $stacks; do
  if prepare "$stack"; then ready+=("$stack"); fi
done

# The tests marked source_only read the repository's text and syntax (docs, comments, layers,
# generated files), which no Python stack changes: when the pinned stack runs them, the Jazzy one
# need not run them again. A -m of the arguments comes later and wins.
only=""
if [[ " ${ready[*]} " == *" pinned "* && " ${ready[*]} " == *" jazzy "* ]]; then
  only=" and not source_only"
fi

if [ "${#ready[@]}" -eq 2 ] && [ "${#args[@]}" -eq 0 ]; then
  logs="$(mktemp -d)"
  trap 'rm -rf "$logs"' EXIT
  alone="not ros and not subprocess"
  echo "[test] both stacks side by side: the tests not marked ros or subprocess (output when both end)"
  run pinned -m "$alone" --basetemp "$logs/pinned" >"$logs/pinned.log" 2>&1 &
  pinned_pid=$!
  run jazzy -m "$alone$only" --basetemp "$logs/jazzy" >"$logs/jazzy.log" 2>&1 &
  jazzy_pid=$!
  status=0
  wait "$pinned_pid" || status=1
  wait "$jazzy_pid" || status=1
  echo "[test] pinned stack, $alone:"
  cat "$logs/pinned.log"
  echo "[test] jazzy stack, $alone$only:"
  cat "$logs/jazzy.log"
  echo "[test] pinned stack: the tests marked ros or subprocess"
  run pinned -m "ros or subprocess" || status=1
  echo "[test] jazzy stack: the tests marked ros or subprocess"
  run jazzy -m "(ros or subprocess)$only" || status=1
  exit "$status"
fi

for stack in "${ready[@]}"; do
  marks=()
  if [ "$stack" = "jazzy" ] && [ -n "$only" ]; then marks=(-m "not source_only"); fi
  run "$stack" ${marks[@]+"${marks[@]}"} ${args[@]+"${args[@]}"}
done
