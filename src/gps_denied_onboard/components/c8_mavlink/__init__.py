"""C8 MAVLink: the autopilot's state in (``VehicleStateTracker``), estimates and status out
(``MavlinkLink``, message builders in ``messages``)."""

from gps_denied_onboard.components.c8_mavlink.link import (
    LinkStats,
    MavlinkConfigError,
    MavlinkError,
    MavlinkLink,
    load_signing_key,
    severity_for,
)
from gps_denied_onboard.components.c8_mavlink.vehicle_state import (
    AltitudeSource,
    ImuSample,
    TimeSource,
    VehicleStateSnapshot,
    VehicleStateTracker,
)

__all__ = [
    "AltitudeSource",
    "ImuSample",
    "LinkStats",
    "MavlinkConfigError",
    "MavlinkError",
    "MavlinkLink",
    "TimeSource",
    "VehicleStateSnapshot",
    "VehicleStateTracker",
    "load_signing_key",
    "severity_for",
]
