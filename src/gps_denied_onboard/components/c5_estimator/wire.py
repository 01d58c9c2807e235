"""The estimator's state as the vision worker hands it to the navigator core (``daemon/core.py``).

A :class:`~gps_denied_onboard.components.c5_estimator.ekf.EstimatorCheckpoint` and the local frame it is
in, as plain msgpack values: no pickle, so a message is data and never code, and a malformed one is
refused with the field that is wrong (:class:`WireError`). The core restores it into its own
:class:`~gps_denied_onboard.components.c5_estimator.ekf.NavEstimator` and predicts it to each send time
with the autopilot's IMU; a restarted worker starts from the core's (the handover).

Its times are on the sender's ``DaemonClock``. With the sender's anchor on the wire and the receiver's
given, they are mapped onto the receiver's clock (both count the host's monotonic time, from anchors
that differ by what the wall clock slewed or stepped between the two starts: a core started minutes
after the worker it adopts).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from gps_denied_onboard.components.c5_estimator.ekf import EstimatorCheckpoint, PriorConflict, VoGated
from gps_denied_onboard.geo import LocalTangentPlane


class WireError(ValueError):
    """A message between the core and the worker that cannot be what it says it is."""


@dataclass(frozen=True)
class WireState:
    """A checkpoint and its frame: what one message carries."""

    checkpoint: EstimatorCheckpoint
    ltp: LocalTangentPlane


def _matrix(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    try:
        out = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise WireError(f"{name}: expected numbers of shape {shape}, got {value!r}") from exc
    if out.shape != shape or not np.all(np.isfinite(out)):
        raise WireError(f"{name}: expected finite numbers of shape {shape}, got shape {out.shape}")
    return out


def _vo_gated(v: np.ndarray) -> VoGated:
    return (float(v[0]), float(v[1]), float(v[2]), float(v[3]), float(v[4]), float(v[5]))


def _opt_int(value: Any, name: str) -> int | None:
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool):
        raise WireError(f"{name}: expected an integer or nil, got {value!r}")
    return value


def _shifted(usec: int | None, shift_usec: int) -> int | None:
    return None if usec is None else usec + shift_usec


def _opt_float(value: Any, name: str) -> float | None:
    if value is None:
        return None
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise WireError(f"{name}: expected a finite number or nil, got {value!r}")
    return float(value)


def state_to_wire(
    checkpoint: EstimatorCheckpoint, ltp: LocalTangentPlane, *, clock_anchor_ns: int | None = None
) -> dict[str, Any]:
    """``checkpoint`` in ``ltp`` as msgpack-ready values; ``clock_anchor_ns``: the sender's clock's anchor
    (``DaemonClock.anchor_unix_ns``; None: not said, the receiver takes the times as its own)."""
    cp = checkpoint
    conflict = cp.prior_conflict
    return {
        "anchor": clock_anchor_ns,
        "ltp": [ltp.origin_lat_deg, ltp.origin_lon_deg, ltp.origin_alt_m],
        "x": cp.x.reshape(-1).tolist(),
        "p": cp.p_mat.reshape(-1).tolist(),
        "t": cp.time_usec,
        "last_fix": cp.last_fix_usec,
        "last_no_fix": cp.last_no_fix_usec,
        "last_vo": cp.last_vo_usec,
        "gated": cp.consecutive_gated,
        "yaw": cp.yaw_rad,
        "shared": cp.shared_sigma_m,
        "imu": cp.imu_trusted,
        "conflict": None
        if conflict is None
        else {
            "first": conflict.first_pos_ne.reshape(-1).tolist(),
            "innov": conflict.innov_ne.reshape(-1).tolist(),
            "fix_cov": conflict.fix_cov_ne.reshape(-1).tolist(),
            "p_ne": conflict.p_ne.reshape(-1).tolist(),
            "count": conflict.count,
        },
        "confirmed": cp.map_confirmed,
        "vo_nis": list(cp.vo_nis),
        "vo_gated_run": [list(e) for e in cp.vo_gated_run],
        "dr_since_fix": cp.dr_since_fix,
    }


def state_from_wire(fields: Mapping[str, Any], *, clock_anchor_ns: int | None = None) -> WireState:
    """The checkpoint and frame of ``fields`` (``state_to_wire``'s), validated; raises ``WireError``. Its
    times on the clock whose anchor is ``clock_anchor_ns`` when both it and the sender's are given."""
    try:
        sender_anchor = _opt_int(fields.get("anchor"), "anchor")
        shift_usec = 0
        if sender_anchor is not None and clock_anchor_ns is not None:
            shift_usec = (clock_anchor_ns - sender_anchor) // 1000
        lat, lon, alt = (float(v) for v in fields["ltp"])
        x = _matrix(fields["x"], (6,), "x").reshape(6, 1)
        p_mat = _matrix(fields["p"], (36,), "p").reshape(6, 6)
        conflict_fields = fields["conflict"]
        conflict = None
        if conflict_fields is not None:
            conflict = PriorConflict(
                _matrix(conflict_fields["first"], (2,), "conflict.first"),
                _matrix(conflict_fields["innov"], (2,), "conflict.innov"),
                _matrix(conflict_fields["fix_cov"], (4,), "conflict.fix_cov").reshape(2, 2),
                _matrix(conflict_fields["p_ne"], (4,), "conflict.p_ne").reshape(2, 2),
                int(conflict_fields["count"]),
            )
        gated = fields["gated"]
        if not isinstance(gated, int) or gated < 0:
            raise WireError(f"gated: expected a count, got {gated!r}")
        shared = _opt_float(fields["shared"], "shared")
        if shared is None or shared < 0:
            raise WireError(f"shared: expected a sigma >= 0 m, got {fields['shared']!r}")
        nis = tuple(float(v) for v in fields["vo_nis"])
        vo_run = tuple(  # absent from handovers recorded before it was sent
            _vo_gated(_matrix(e, (6,), "vo_gated_run")) for e in fields.get("vo_gated_run", ())
        )
        checkpoint = EstimatorCheckpoint(
            x=x,
            p_mat=p_mat,
            time_usec=_shifted(_opt_int(fields["t"], "t"), shift_usec),
            last_fix_usec=_shifted(_opt_int(fields["last_fix"], "last_fix"), shift_usec),
            last_no_fix_usec=_shifted(_opt_int(fields["last_no_fix"], "last_no_fix"), shift_usec),
            last_vo_usec=_shifted(_opt_int(fields["last_vo"], "last_vo"), shift_usec),
            consecutive_gated=gated,
            yaw_rad=_opt_float(fields["yaw"], "yaw"),
            shared_sigma_m=shared,
            imu_trusted=bool(fields["imu"]),
            prior_conflict=conflict,
            map_confirmed=bool(fields["confirmed"]),
            vo_nis=nis,
            vo_gated_run=vo_run,
            dr_since_fix=bool(fields.get("dr_since_fix", False)),
        )
    except KeyError as exc:
        raise WireError(f"missing field {exc.args[0]!r}") from exc
    except (TypeError, ValueError) as exc:
        if isinstance(exc, WireError):
            raise
        raise WireError(f"malformed state: {exc}") from exc
    if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)):
        raise WireError(f"ltp: expected a finite origin, got {fields['ltp']!r}")
    if not np.allclose(p_mat, p_mat.T, rtol=1e-6, atol=1e-9):
        raise WireError("p: the covariance is not symmetric")
    return WireState(checkpoint, LocalTangentPlane(lat, lon, alt))


def pack(message: Mapping[str, Any]) -> bytes:
    """One message (a map with a ``kind``) as msgpack bytes."""
    return msgpack.packb(message, use_bin_type=True)


def unpack(data: bytes) -> dict[str, Any]:
    """The message in ``data``; raises ``WireError`` when it is not a map with a string ``kind``."""
    try:
        message = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except (ValueError, msgpack.UnpackException) as exc:
        raise WireError(f"not a msgpack message: {exc}") from exc
    if not isinstance(message, dict) or not isinstance(message.get("kind"), str):
        raise WireError(f"expected a map with a string 'kind', got {type(message).__name__}")
    return message
