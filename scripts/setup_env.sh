#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv and install the requirements, pinned by
# constraints.txt, plus cgags_ros itself (editable). Re-running is cheap: pip is only called
# again when a requirements file or setup.py changed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${CGAGS_VENV:-$root/.venv}"
python="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment $venv"
  "$python" -m venv "$venv"
fi
stamp="$venv/.cgags_requirements.sha256"
want="$(cat "$root"/requirements*.txt "$root/constraints.txt" "$root/setup.py" "$root/setup.cfg" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[setup] installing pinned requirements (first run downloads ~1 GB, mostly Open3D)"
  "$venv/bin/python" -m pip install --quiet --upgrade pip
  "$venv/bin/python" -m pip install --quiet -c "$root/constraints.txt" -r "$root/requirements.txt" \
      -r "$root/requirements-ros.txt" -r "$root/requirements-dev.txt"
  "$venv/bin/python" -m pip install --quiet --no-deps -e "$root"
  echo "$want" > "$stamp"
else
  echo "[setup] virtual environment $venv is up to date"
fi
