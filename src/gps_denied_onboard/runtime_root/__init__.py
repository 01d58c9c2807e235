"""``compose_root(config)``: the one place where the daemon's objects are built and wired.

Components never read config or build their own collaborators; they get both here, through their
constructors. Strategy names are looked up in explicit registries; an unknown name is an error that
lists the valid ones. Anything that cannot be used (cache, model file, calibration, key file) stops
start-up here with a ``StartupError`` naming it: the daemon refuses to fly on a broken install.
"""

from __future__ import annotations

from gps_denied_onboard.runtime_root.compose import RuntimeRoot, StartupError, compose_root, preflight

__all__ = ["RuntimeRoot", "StartupError", "compose_root", "preflight"]
