"""What PX4 does with the daemon's position messages: a TEST DOUBLE of PX4's rules, not the autopilot.

No PX4 binary ships with this project. These rules come from PX4 main of 2026-03-02 run as SITL with
the SIH simulator and fed with pymavlink on these machines (DESIGN.md, "What a real PX4 does with an
external position"; "measured" below) and from its source where a rule was read there ("source"). The
real PX4 is the judge: a verdict from this module is never presented as the autopilot's.

Stateless rules:
- GPS_INPUT: PX4 has no handler for it, so it is never used (:func:`gps_input_used`; source);
- GLOBAL_POSITION_SENSOR (handled since PX4 PR #26307, 2026-02-27, main): routed to the aux global
  position instance ``i`` whose ``EKF2_AGP{i}_ID`` equals the message's ``id``, with bit 0 of
  ``EKF2_AGP{i}_CTRL`` (:func:`agp_instances_for`, :func:`global_position_sensor_rejection`; source).
  ``flags`` (GLOBAL_POSITION_UNHEALTHY included), ``time_usec`` and ``processing_time`` are not read
  (source and measured): a flagged message is used like any other;
- VISION_POSITION_ESTIMATE (local NED): used only with ``EKF2_EV_CTRL`` bit 0 set (since v1.14)
  (:func:`vision_position_estimate_used`; source).

What one EKF2 does with a stream of GLOBAL_POSITION_SENSOR over time is :class:`Px4AuxGlobalPosition`.

Parameters are a mapping of PX4 parameter name to value, e.g.
``{"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 1, "EKF2_EV_CTRL": 0}``; a missing parameter counts as 0.
Message fields are pymavlink's ``to_dict()`` of the message.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from gps_denied_onboard.geo import LocalTangentPlane

#: ``EKF2_AGP{i}_CTRL`` bit that enables fusing aux global position instance ``i``.
AGP_CTRL_ENABLE_BIT: Final[int] = 1 << 0
#: ``EKF2_EV_CTRL`` bit 0: external-vision position fusion, which VISION_POSITION_ESTIMATE feeds.
EV_CTRL_POSITION_BIT: Final[int] = 1 << 0
#: Aux global position instances EKF2 has (``EKF2_AGP0_*`` … ``EKF2_AGP3_*``; source:
#: ``src/modules/ekf2/params_aux_global_position.yaml``, ``max_num_agp_instances``).
AGP_INSTANCES: Final[int] = 4
#: A stream of messages that are not fused (``eph`` = inf, or rejected by the innovation gate) resets
#: EKF2's horizontal position to the message about this often, s (measured: "about every 7 s").
RESET_TO_INPUT_S: Final[float] = 7.0
#: EKF2's position is invalid this long after its last fusion, and the commander fails safe (descend):
#: measured 5.3 s after the last message, and ~5 s after a rejected 20 m step.
POSITION_TIMEOUT_S: Final[float] = 5.3
#: Innovation gate of the aux global position, in standard deviations (source: ``EKF2_AGP0_GATE``'s default
#: in ``params_aux_global_position.yaml``).
AGP_GATE_SIGMAS: Final[float] = 3.0
#: The noise floor of a fused position, m (source: ``EKF2_AGP0_NOISE``'s default in
#: ``params_aux_global_position.yaml``; max(eph, it) is used).
AGP_NOISE_FLOOR_M: Final[float] = 1.0
#: How fast the double's own position variance grows between fusions, m^2/s (an assumption: a hovering
#: multirotor's EKF2 without GNSS; it only sets how wide the gate opens after a gap).
PROCESS_NOISE_M2_S: Final[float] = 0.5

_AGP_ID_PARAM: Final = re.compile(r"EKF2_AGP(\d+)_ID")


def gps_input_used(fields: Mapping[str, Any], params: Mapping[str, int]) -> bool:
    """Always False: PX4's MAVLink receiver has no GPS_INPUT handler in any release (source, main
    2026-03; measured), whatever the parameters; an ArduPilot-style GPS_INPUT stream gives PX4 nothing."""
    del fields, params
    return False


def agp_instances_for(sensor_id: int, params: Mapping[str, int]) -> list[int]:
    """The aux-global-position instances ``i`` whose ``EKF2_AGP{i}_ID`` equals ``sensor_id`` and whose
    ``EKF2_AGP{i}_CTRL`` has bit 0 set (source: the message's ``id`` is matched against
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
    """Why PX4 would not route this GLOBAL_POSITION_SENSOR to a fusing instance, or None when it would.

    Only the ``id`` decides (source, PR #26307): the message goes to the instance ``i`` with
    ``EKF2_AGP{i}_ID`` equal to it, fused only with ``EKF2_AGP{i}_CTRL`` bit 0. The flags are not read,
    so a message flagged GLOBAL_POSITION_UNHEALTHY is not rejected (measured). Raises ValueError when
    ``id`` is missing.
    """
    try:
        sensor_id = int(fields["id"])
    except KeyError as exc:
        raise ValueError(f"GLOBAL_POSITION_SENSOR fields lack {exc.args[0]!r}; expected id") from exc
    if not agp_instances_for(sensor_id, params):
        configured = sorted(
            (name, int(value)) for name, value in params.items() if _AGP_ID_PARAM.fullmatch(name)
        )
        return (
            f"id {sensor_id}: no EKF2_AGP<i>_ID equal to it with EKF2_AGP<i>_CTRL bit 0 set "
            f"(configured ids: {configured})"
        )
    return None


def global_position_sensor_used(fields: Mapping[str, Any], params: Mapping[str, int]) -> bool:
    """True when PX4 routes this GLOBAL_POSITION_SENSOR to a fusing instance
    (:func:`global_position_sensor_rejection`); what it then does is :class:`Px4AuxGlobalPosition`."""
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


@dataclass(frozen=True)
class Origin:
    """EKF2's global origin: where its local frame is, and whether its altitude is valid."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_valid: bool


class Px4AuxGlobalPosition:
    """One EKF2 fed GLOBAL_POSITION_SENSOR over one MAVLink link, horizontally, by the measured rules.

    ``boot_params`` are the parameters at boot: ``EKF2_AGP{i}_ID`` and ``EKF2_AGP{i}_CTRL`` are read when
    EKF2 starts, so :meth:`set_param` at run time changes nothing until :meth:`reboot` (measured).

    Rules, each measured on PX4 main of 2026-03-02 SITL (SIH) unless marked "source":
    - **Routing and id slots.** A message goes to the instance whose boot ``EKF2_AGP{i}_ID`` equals its
      ``id``. A first message whose id no instance has takes a free instance (``EKF2_AGP{i}_ID`` 0),
      saves its id there (in the parameters, for the next boot) and binds this link to that instance
      until reboot: from then on, messages with the configured id on this link are never fused.
    - **Origin.** The first message routed to an instance with ``CTRL`` bit 0 sets EKF2's global origin
      when there is none, its altitude included, whatever its ``eph`` and flags: lat/lon 0,0 sets the
      origin there for good, and a NaN ``alt`` gives origin altitude 0 with no valid global altitude.
    - **Fusion.** Horizontal position only, stamped on arrival (``time_usec`` is not read), with noise
      max(``eph``, ``EKF2_AGP0_NOISE``) (source), behind an innovation gate of ``AGP_GATE_SIGMAS``
      (source). A message whose ``eph`` is not finite is never fused. A slow bias is followed
      completely; a step beyond the gate is rejected.
    - **Reset to the input.** While messages arrive and none is fused (``eph`` = inf, or rejected), the
      horizontal position is reset to the newest message about every ``RESET_TO_INPUT_S`` (to 0,0 when
      it says 0,0), and the position is then valid again.
    - **Timeout.** ``POSITION_TIMEOUT_S`` after the last fusion or reset, the position is invalid and
      the commander fails safe (descend).
    """

    def __init__(self, boot_params: Mapping[str, float]) -> None:
        self._params: dict[str, float] = dict(boot_params)
        self.reboot()

    def set_param(self, name: str, value: float) -> None:
        """Set a parameter at run time: saved, used from the next :meth:`reboot` (measured)."""
        self._params[name] = value

    @property
    def params(self) -> dict[str, float]:
        """The parameters as saved now (what the next boot reads)."""
        return dict(self._params)

    def reboot(self) -> None:
        """A PX4 reboot: the parameters are read again; origin, position and the link's binding are gone."""
        self._boot: dict[str, float] = dict(self._params)
        self._bound_instance: int | None = None
        self.origin: Origin | None = None
        self._pos: tuple[float, float] | None = None  # lat_deg, lon_deg
        self._var_m2 = math.inf
        self._last_update_s: float | None = None  # last fusion or reset, s
        self._last_message_s: float | None = None
        self.fused = 0
        self.rejected = 0
        self.resets = 0
        self.ignored = 0

    def _boot_id(self, index: int) -> int:
        return int(self._boot.get(f"EKF2_AGP{index}_ID", 0))

    def _route(self, sensor_id: int) -> int | None:
        """The instance this message goes to on this link, or None (ignored)."""
        if self._bound_instance is not None:
            bound = self._bound_instance
            return bound if self._boot_id(bound) == sensor_id else None
        for index in range(AGP_INSTANCES):
            if self._boot_id(index) == sensor_id:
                return index
        free = [i for i in range(AGP_INSTANCES) if self._boot_id(i) == 0]
        if not free:
            return None
        index = free[0]
        self._boot[f"EKF2_AGP{index}_ID"] = sensor_id
        self._params[f"EKF2_AGP{index}_ID"] = sensor_id
        self._bound_instance = index
        return index

    def receive(self, fields: Mapping[str, Any], arrival_s: float) -> str:
        """Take one GLOBAL_POSITION_SENSOR that arrived at ``arrival_s``; returns what EKF2 did with it:
        ``ignored``, ``origin``, ``fused``, ``rejected`` or ``reset``."""
        index = self._route(int(fields["id"]))
        if index is None or not int(self._boot.get(f"EKF2_AGP{index}_CTRL", 0)) & AGP_CTRL_ENABLE_BIT:
            self.ignored += 1
            return "ignored"
        lat, lon = int(fields["lat"]) / 1e7, int(fields["lon"]) / 1e7
        alt, eph = float(fields["alt"]), float(fields["eph"])
        self._last_message_s = arrival_s
        if self.origin is None:
            finite_alt = math.isfinite(alt)
            self.origin = Origin(lat, lon, alt if finite_alt else 0.0, finite_alt)
        if self._pos is None:
            return self._reset((lat, lon), eph, arrival_s)
        last = self._last_update_s if self._last_update_s is not None else arrival_s
        dt = max(0.0, arrival_s - last)
        var = self._var_m2 + PROCESS_NOISE_M2_S * dt
        here = LocalTangentPlane(self._pos[0], self._pos[1], 0.0)
        innov = here.to_ned(lat, lon, 0.0)[:2]
        if math.isfinite(eph):
            noise = max(eph, AGP_NOISE_FLOOR_M) ** 2
            if float(np.hypot(*innov)) <= AGP_GATE_SIGMAS * math.sqrt(var + noise):
                gain = var / (var + noise)
                new_lat, new_lon, _alt = here.to_geodetic(np.array([gain * innov[0], gain * innov[1], 0.0]))
                self._pos = (float(new_lat), float(new_lon))
                self._var_m2 = (1.0 - gain) * var
                self._last_update_s = arrival_s
                self.fused += 1
                return "fused"
        if dt >= RESET_TO_INPUT_S:
            return self._reset((lat, lon), eph, arrival_s)
        self.rejected += 1
        return "rejected"

    def _reset(self, pos: tuple[float, float], eph: float, arrival_s: float) -> str:
        self._pos = pos
        self._var_m2 = max(eph, AGP_NOISE_FLOOR_M) ** 2 if math.isfinite(eph) else 1e6
        self._last_update_s = arrival_s
        self.resets += 1
        return "reset"

    def position_valid(self, now_s: float) -> bool:
        """Whether EKF2 has a valid horizontal position at ``now_s`` (fused or reset within the timeout)."""
        return self._last_update_s is not None and now_s - self._last_update_s < POSITION_TIMEOUT_S

    def failsafe(self, now_s: float) -> bool:
        """Whether the commander has failed safe by ``now_s``: a position once held, lost past the timeout."""
        return self._last_update_s is not None and not self.position_valid(now_s)

    def global_position(self) -> tuple[float, float] | None:
        """EKF2's global position (lat_deg, lon_deg), or None before it has an origin and a position."""
        if self.origin is None or self._pos is None:
            return None
        return self._pos
