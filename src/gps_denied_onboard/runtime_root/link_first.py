"""The composition root's first stage: the autopilot link, built before anything heavy is imported.

``gdnav run`` opens it right after reading the configuration, so the start-up beacon
(``daemon.beacon``) can talk to the autopilot while the map cache, the models and the estimator load.
Imports here stay light (MAVLink, the clock, the config): tests/test_import_graph.py checks that none
of SciPy, OpenCV, ONNX Runtime or FAISS comes with them.
"""

from __future__ import annotations

from gps_denied_onboard.clock import AutopilotClock, DaemonClock
from gps_denied_onboard.components.c8_mavlink import (
    MavlinkConfigError,
    MavlinkLink,
    VehicleStateTracker,
    load_signing_key,
)
from gps_denied_onboard.config import Config


class StartupError(RuntimeError):
    """The daemon cannot start: ``what`` names the broken thing (cache, model, calibration...)."""

    def __init__(self, what: str, message: str) -> None:
        super().__init__(f"cannot start: {what}: {message}")
        self.what = what


def check_signing_key(config: Config) -> None:
    """Refuse an unusable MAVLink signing key file with the other refused files, naming the key; the
    link reads it again when it opens."""
    if config.mavlink.signing_key_file is None:
        return
    try:
        load_signing_key(config.mavlink.signing_key_file)
    except MavlinkConfigError as exc:
        raise StartupError("mavlink.signing_key_file", str(exc)) from exc


def make_tracker(config: Config, clock: DaemonClock | None = None) -> VehicleStateTracker:
    """The autopilot-state tracker the MAVLink link feeds (on ``clock``; default: a new one)."""
    return VehicleStateTracker(
        autopilot_system_id=config.mavlink.autopilot_system_id,
        attitude_max_age_s=config.mavlink.attitude_max_age_s,
        altitude_max_age_s=config.mavlink.altitude_max_age_s,
        link_timeout_s=config.mavlink.link_timeout_s,
        clock=(clock or DaemonClock()).now_unix_s,
        autopilot_clock=AutopilotClock(),
    )


def open_link_first(config: Config, clock: DaemonClock, *, signing_link_id: int = 0) -> MavlinkLink:
    """The daemon's MAVLink link, open, with its tracker, and without its FDR and local frame yet
    (``compose_root`` attaches them). Raises ``StartupError`` for an unusable signing key file and
    ``MavlinkConfigError`` for a link that cannot work (URL, a UDP port another process holds).
    ``signing_link_id``: see ``MavlinkLink``."""
    check_signing_key(config)
    link = MavlinkLink(
        config.mavlink,
        make_tracker(config, clock),
        None,
        clock.now_unix_s,
        frame_later=True,
        signing_link_id=signing_link_id,
    )
    link.open()
    return link
