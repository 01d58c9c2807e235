"""``compose_root(config)``: the one place where the daemon's objects are built and wired.

Components never read config or build their own collaborators; they get both here, through their
constructors. Strategy names are looked up in explicit registries; an unknown name is an error that
lists the valid ones. Anything that cannot be used (cache, model file, calibration, key file) stops
start-up here with a ``StartupError`` naming it: the daemon refuses to fly on a broken install.

Two stages: ``link_first.open_link_first`` builds the MAVLink link alone (light imports: it talks to the
autopilot while the rest loads), ``compose.compose_root`` everything else. The names below load on first
use (PEP 562), so importing the light stage does not import the heavy one.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from gps_denied_onboard.runtime_root.compose import RuntimeRoot, StartupError, compose_root, preflight

__all__ = ["RuntimeRoot", "StartupError", "compose_root", "preflight"]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.compose"), name)
    globals()[name] = value
    return value
