"""What PX4 does with the daemon's position messages: a TEST DOUBLE of PX4's rules, not the autopilot.

No PX4 binary ships with this project. These rules are the ones knowable from PX4's public source
(main, 2026-03; DESIGN.md, "PX4"), written as pure functions so that the simulator and the tests can
say whether PX4 would use a message. Nothing here is PX4 code, nothing was measured against a running
PX4, and no report may present a verdict from this module as the autopilot's.

- GPS_INPUT: PX4 has no handler for it, so it is never used (:func:`gps_input_used`);
- GLOBAL_POSITION_SENSOR (handled since PX4 PR #26307, 2026-02-27, main): used only when its ``id``
  equals a configured ``EKF2_AGP{i}_ID`` whose ``EKF2_AGP{i}_CTRL`` has bit 0 set, and (the daemon's
  validity policy) only when the GLOBAL_POSITION_UNHEALTHY flag is clear
  (:func:`global_position_sensor_rejection`, :func:`global_position_sensor_used`);
- VISION_POSITION_ESTIMATE (local NED): used only with ``EKF2_EV_CTRL`` bit 0 set (since v1.14)
  (:func:`vision_position_estimate_used`).

Parameters are a mapping of PX4 parameter name to integer value, e.g.
``{"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 1, "EKF2_EV_CTRL": 0}``; a missing parameter counts as 0.
Message fields are pymavlink's ``to_dict()`` of the message.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any, Final

from gps_denied_onboard.components.c8_mavlink.messages import DIALECT

#: ``EKF2_AGP{i}_CTRL`` bit that enables fusing aux global position instance ``i``.
AGP_CTRL_ENABLE_BIT: Final[int] = 1 << 0
#: ``EKF2_EV_CTRL`` bit 0: external-vision position fusion, which VISION_POSITION_ESTIMATE feeds.
EV_CTRL_POSITION_BIT: Final[int] = 1 << 0
#: GLOBAL_POSITION_SENSOR.flags bit that marks the position as not to be used.
UNHEALTHY_FLAG: Final[int] = int(DIALECT.GLOBAL_POSITION_UNHEALTHY)

_AGP_ID_PARAM: Final = re.compile(r"EKF2_AGP(\d+)_ID")


def gps_input_used(fields: Mapping[str, Any], params: Mapping[str, int]) -> bool:
    """Always False: PX4's MAVLink receiver has no GPS_INPUT handler in any release (source, main
    2026-03), whatever the parameters; an ArduPilot-style GPS_INPUT stream gives PX4 nothing."""
    del fields, params
    return False


def agp_instances_for(sensor_id: int, params: Mapping[str, int]) -> list[int]:
    """The aux-global-position instances ``i`` whose ``EKF2_AGP{i}_ID`` equals ``sensor_id`` and whose
    ``EKF2_AGP{i}_CTRL`` has bit 0 set (PX4 source: the message's ``id`` is matched against
    ``EKF2_AGP{i}_ID``; ``EKF2_AGP{i}_CTRL`` bit 0 enables fusion of that instance)."""
    found = []
    for name, value in params.items():
        match = _AGP_ID_PARAM.fullmatch(name)
        if match is None or int(value) != int(sensor_id):
            continue
        index = int(match.group(1))
        if int(params.get(f"EKF2_AGP{index}_CTRL", 0)) & AGP_CTRL_ENABLE_BIT:
            found.append(index)
    return sorted(found)


def global_position_sensor_rejection(fields: Mapping[str, Any], params: Mapping[str, int]) -> str | None:
    """Why PX4 would not use this GLOBAL_POSITION_SENSOR, or None when it would.

    PX4 source (PR #26307, main since 2026-02-27): the message's ``id`` selects the aux global
    position instance ``i`` with ``EKF2_AGP{i}_ID`` equal to it, fused only with ``EKF2_AGP{i}_CTRL``
    bit 0. The UNHEALTHY flag is the daemon's "do not use" (set whenever it would not report a 3D fix);
    this double treats a flagged message as unused. Raises ValueError when ``id`` or ``flags`` is
    missing.
    """
    try:
        sensor_id = int(fields["id"])
        flags = int(fields["flags"])
    except KeyError as exc:
        raise ValueError(
            f"GLOBAL_POSITION_SENSOR fields lack {exc.args[0]!r}; expected id and flags"
        ) from exc
    if not agp_instances_for(sensor_id, params):
        configured = sorted(
            (name, int(value)) for name, value in params.items() if _AGP_ID_PARAM.fullmatch(name)
        )
        return (
            f"id {sensor_id}: no EKF2_AGP<i>_ID equal to it with EKF2_AGP<i>_CTRL bit 0 set "
            f"(configured ids: {configured})"
        )
    if flags & UNHEALTHY_FLAG:
        return "GLOBAL_POSITION_UNHEALTHY flag set"
    return None


def global_position_sensor_used(fields: Mapping[str, Any], params: Mapping[str, int]) -> bool:
    """True when PX4 would fuse this GLOBAL_POSITION_SENSOR (:func:`global_position_sensor_rejection`)."""
    return global_position_sensor_rejection(fields, params) is None


def vision_position_estimate_used(params: Mapping[str, int]) -> bool:
    """True when PX4 fuses VISION_POSITION_ESTIMATE positions: ``EKF2_EV_CTRL`` bit 0 set (PX4 source,
    since v1.14). The position is local NED, so it is only right in the frame PX4 uses; that is the
    sender's job (the daemon's link), not a parameter."""
    return bool(int(params.get("EKF2_EV_CTRL", 0)) & EV_CTRL_POSITION_BIT)


def px4_uses(msg_type: str, fields: Mapping[str, Any], params: Mapping[str, int]) -> bool:
    """Whether PX4 would use one received message of ``msg_type`` (GPS_INPUT, GLOBAL_POSITION_SENSOR,
    VISION_POSITION_ESTIMATE); any other type is not a position input here and gives False."""
    if msg_type == "GLOBAL_POSITION_SENSOR":
        return global_position_sensor_used(fields, params)
    if msg_type == "VISION_POSITION_ESTIMATE":
        return vision_position_estimate_used(params)
    if msg_type == "GPS_INPUT":
        return gps_input_used(fields, params)
    return False
