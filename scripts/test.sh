#!/usr/bin/env bash
# Quick start (b): set up, lint, type-check and run the test suite (CI runs exactly this).
GDNAV_EXTRAS="dev,export" source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
.venv/bin/ruff check src daemon sitl tests
.venv/bin/mypy
exec .venv/bin/pytest "$@"
