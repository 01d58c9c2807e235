#!/usr/bin/env bash
# Quick start (a): set up, then fly the SITL demo on the embedded procedural map.
# Extra arguments go to `gdnav sitl run` (e.g. --map FILE.tif --scenario nominal_real).
GDNAV_EXTRAS="" source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
exec .venv/bin/gdnav sitl run --scenario demo --report out/demo/report.json "$@"
