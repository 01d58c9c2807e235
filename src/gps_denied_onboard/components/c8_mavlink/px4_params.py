"""What PX4's parameters must say for its EKF2 to fuse the daemon's GLOBAL_POSITION_SENSOR.

Input: the values read back from PX4 (PARAM_VALUE, by name; None for one not answered) and
``mavlink.global_position_sensor_id``. Output: one line per problem, naming the parameter, its value, the
value to set and whether PX4 must reboot; none when all is well. Nothing here talks to the link.

- ``EKF2_AGP0_ID`` must equal the message's ``id`` and bit 0 of ``EKF2_AGP0_CTRL`` must be set. EKF2 reads
  both when it starts, so either one set at run time does nothing until PX4 reboots (measured on PX4 main
  of 2026-03-02, DESIGN.md). A first message with an id that no ``EKF2_AGP{i}_ID`` holds also takes a
  free instance and binds the link to it until reboot, so the daemon checks before it sends.
- ``EKF2_AGP0_DELAY`` (ms, reboot-required, default 0: PX4's ``params_aux_global_position.yaml``) is how
  old PX4 takes a message to be on arrival (it stamps on arrival and reads no time field). The daemon's
  positions are propagated to their send time, so it should be 0 within ``AGP_DELAY_TOLERANCE_MS``: a
  delay set for a camera's latency would fuse each position as if it were that much older (at 10 m/s,
  0.1 s is 1 m along the track).
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from gps_denied_onboard.components.c8_mavlink.messages import DIALECT

#: The parameters read from PX4, in the order they are asked for.
PX4_AGP_PARAMS: Final[tuple[str, ...]] = ("EKF2_AGP0_ID", "EKF2_AGP0_CTRL", "EKF2_AGP0_DELAY")
#: MAV_PARAM_TYPE values of integer parameters: PX4 sends and expects these byte-wise in the float of
#: PARAM_VALUE and PARAM_SET (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); ArduPilot casts them.
INT_PARAM_TYPES: Final[frozenset[int]] = frozenset(
    {
        DIALECT.MAV_PARAM_TYPE_UINT8,
        DIALECT.MAV_PARAM_TYPE_INT8,
        DIALECT.MAV_PARAM_TYPE_UINT16,
        DIALECT.MAV_PARAM_TYPE_INT16,
        DIALECT.MAV_PARAM_TYPE_UINT32,
        DIALECT.MAV_PARAM_TYPE_INT32,
    }
)


def bytewise_to_value(wire: float, param_type: int) -> float:
    """The value a byte-wise PARAM_VALUE/PARAM_SET float carries for ``param_type`` (integers decoded)."""
    if int(param_type) in INT_PARAM_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", float(wire)))[0])
    return float(wire)


def value_to_bytewise(value: float, param_type: int) -> float:
    """The float that carries ``value`` of ``param_type`` byte-wise (integers encoded)."""
    if int(param_type) in INT_PARAM_TYPES:
        return float(struct.unpack("<f", struct.pack("<i", round(value)))[0])
    return float(value)


#: ``EKF2_AGP0_DELAY`` may differ from 0 by this much before it is reported, ms.
AGP_DELAY_TOLERANCE_MS: Final[float] = 20.0


@dataclass(frozen=True)
class Px4ParamProblem:
    """One parameter problem: ``detail`` for the log and FDR, ``statustext`` (at most 50 bytes) for the
    ground, ``blocks_output`` when GLOBAL_POSITION_SENSOR must not be sent while it stands (a first
    message with an id no instance holds binds the link to a free instance until reboot)."""

    detail: str
    statustext: str
    blocks_output: bool


def px4_agp_problems(values: Mapping[str, float | None], *, sensor_id: int) -> list[Px4ParamProblem]:
    """Problems with PX4's aux-global-position parameters for GLOBAL_POSITION_SENSOR id ``sensor_id``."""
    problems = []
    unread = [name for name in PX4_AGP_PARAMS if values.get(name) is None]
    if unread:
        problems.append(
            Px4ParamProblem(
                f"PX4 did not answer for {', '.join(unread)}: check them by hand",
                "GDN: PX4 EKF2_AGP0 params unread, check",
                False,
            )
        )
    agp_id, ctrl, delay = (values.get(name) for name in PX4_AGP_PARAMS)
    if agp_id is not None and int(agp_id) != int(sensor_id):
        problems.append(
            Px4ParamProblem(
                f"EKF2_AGP0_ID is {int(agp_id)}: set it to {sensor_id} (mavlink.global_position_sensor_id) "
                "and reboot PX4; GLOBAL_POSITION_SENSOR is not sent until then",
                f"GDN: PX4 EKF2_AGP0_ID {int(agp_id)}, set {sensor_id}+reboot",
                True,
            )
        )
    if ctrl is not None and not int(ctrl) & 1:
        problems.append(
            Px4ParamProblem(
                f"EKF2_AGP0_CTRL is {int(ctrl)}: set bit 0 (to {int(ctrl) | 1}) and reboot PX4",
                f"GDN: PX4 EKF2_AGP0_CTRL {int(ctrl)}, set {int(ctrl) | 1}+reboot",
                False,
            )
        )
    if delay is not None and abs(float(delay)) > AGP_DELAY_TOLERANCE_MS:
        problems.append(
            Px4ParamProblem(
                f"EKF2_AGP0_DELAY is {float(delay):g} ms: set it to 0 (the daemon's positions are valid at "
                "their send time) and reboot PX4",
                f"GDN: PX4 EKF2_AGP0_DELAY {float(delay):.0f}ms, set 0+reboot",
                False,
            )
        )
    return problems
