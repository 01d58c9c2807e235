"""Daemon configuration: YAML profiles loaded into frozen dataclasses, validated strictly.

Every key is declared here with its type, unit (in the name) and range. Unknown keys, wrong types and
out-of-range values are errors that name the key path and what was expected; nothing is coerced from a
string and nothing unknown is ignored. Command-line overrides (``--set a.b=value``) go through the same
validation.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, ClassVar, Final, Literal

import yaml
from pydantic import AfterValidator, ConfigDict, Field, Strict, TypeAdapter, ValidationError

# Every section is a frozen stdlib dataclass that pydantic validates with this config (extra keys
# forbidden); every scalar is Strict, so "3" is not an int and "yes" is not a bool. No setting has a
# meaning for NaN or infinity (YAML's .nan/.inf): they would pass range checks such as gt=0 and poison
# the maths downstream, so every float must be finite.
_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
Str = Annotated[str, Strict()]
Bool = Annotated[bool, Strict()]
PosFloat = Annotated[float, Strict(), Field(gt=0)]
PosInt = Annotated[int, Strict(), Field(ge=1)]
Fraction = Annotated[float, Strict(), Field(ge=0, le=1)]

#: pymavlink connection schemes that take HOST:PORT (anything else must be a serial device path).
MAVLINK_URL_SCHEMES: Final[tuple[str, ...]] = ("udpin:", "udpout:", "udp:", "tcp:", "tcpin:")


def check_mavlink_url(url: str) -> str:
    """Return ``url`` when it is ``SCHEME:HOST:PORT`` (PORT 1..65535) or a serial device path; otherwise
    raise ValueError saying what was expected. The one grammar for ``mavlink.url``: the config validates
    with it and ``MavlinkLink.open()`` re-checks a config built without validation."""
    if url.startswith(MAVLINK_URL_SCHEMES):
        host, sep, port = url.split(":", 1)[1].rpartition(":")
        if not sep or not host or not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
            raise ValueError("expected SCHEME:HOST:PORT with PORT 1..65535 (e.g. udpin:0.0.0.0:14550)")
        return url
    if url.startswith("/") or url.upper().startswith("COM"):
        return url  # serial device
    raise ValueError(
        f"unsupported connection string; expected one of {', '.join(MAVLINK_URL_SCHEMES)} "
        "or a serial device path"
    )


MavlinkUrl = Annotated[str, Strict(), AfterValidator(check_mavlink_url)]


class SettingError(ValueError):
    """A rule between settings of one section is broken (raised from a section's ``__post_init__``);
    ``key`` is the setting to change, so the ConfigError can name its full path."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


@dataclasses.dataclass(frozen=True)
class IntrinsicsConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Image size the intrinsics are for; frames of another size are refused (recorded, not used).
    width_px: PosInt = 640
    height_px: PosInt = 480
    #: Horizontal field of view; used when fx_px is not given.
    hfov_deg: Annotated[float, Strict(), Field(gt=1, lt=179)] = 70.0
    #: Focal lengths and principal point, px (fy defaults to fx; cx, cy to the image centre).
    fx_px: PosFloat | None = None
    fy_px: PosFloat | None = None
    cx_px: Float | None = None
    cy_px: Float | None = None
    #: OpenCV distortion coefficients (k1, k2, p1, p2[, k3...]).
    dist_coeffs: tuple[Float, ...] = ()


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: ``tcp://HOST:PORT`` (SITL/network frame stream), ``file:PATH`` (video), ``v4l2:/dev/videoN``,
    #: ``rtsp://...``.
    source: Str = "tcp://127.0.0.1:5600"
    #: OpenCV calibration YAML; when null the ``intrinsics`` block is used.
    calibration_file: Str | None = None
    intrinsics: IntrinsicsConfig = dataclasses.field(default_factory=IntrinsicsConfig)
    #: Timeouts for connecting to the source and for waiting for the next frame, s.
    connect_timeout_s: PosFloat = 5.0
    frame_timeout_s: PosFloat = 3.0
    #: Cap of the jittered exponential backoff between reconnects, s.
    reconnect_backoff_max_s: PosFloat = 5.0
    #: Frames waiting for the pipeline; when full the oldest is dropped (newest frame wins).
    queue_depth: PosInt = 1
    #: Boresight: the camera's rotation from the nominal nadir mount about the body's roll (forward)
    #: and pitch (right) axes, deg, applied to the autopilot's attitude wherever the camera's is used
    #: (VO, pose, tilt checks; not the IMU). Measure it with `gdnav fdr boresight`.
    mount_roll_deg: Annotated[float, Strict(), Field(ge=-10, le=10)] = 0.0
    mount_pitch_deg: Annotated[float, Strict(), Field(ge=-10, le=10)] = 0.0
    #: How well a frame's stamp gives its exposure time (1 sigma, s) until the daemon has measured the
    #: camera's lateness (clock.CameraStampOffset): the tilt and position doubt a timing error carries at
    #: the vehicle's attitude rate and speed. A camera that stamps on receipt is typically 30-150 ms late.
    stamp_sigma_s: Annotated[float, Strict(), Field(gt=0, le=1)] = 0.1
    #: The largest lateness of the stamps the daemon corrects, s (earliness: up to 0.04 s); a measured
    #: one beyond it is reported (``camera.stamp_offset``, out_of_bounds) and corrected only up to it.
    max_stamp_offset_s: Annotated[float, Strict(), Field(ge=0, le=1)] = 0.3


OutputKind = Literal["gps_input", "global_position_sensor", "vision_position_estimate"]


@dataclasses.dataclass(frozen=True)
class MavlinkConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: pymavlink connection string: ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``,
    #: ``/dev/ttyACM0`` (serial, with ``baud``).
    url: MavlinkUrl = "udpin:127.0.0.1:14560"
    #: Serial baud rate (serial URLs only).
    baud: PosInt = 921600
    #: This daemon's MAVLink identity: the vehicle's system id, component 197 (VISUAL_INERTIAL_ODOMETRY).
    system_id: Annotated[int, Strict(), Field(ge=1, le=255)] = 1
    component_id: Annotated[int, Strict(), Field(ge=1, le=255)] = 197
    #: System id of the autopilot whose messages are used (others are ignored).
    autopilot_system_id: Annotated[int, Strict(), Field(ge=1, le=255)] = 1
    #: What is sent per estimate: GPS_INPUT (ArduPilot, GPS1_TYPE=14), GLOBAL_POSITION_SENSOR (PX4 1.18+),
    #: VISION_POSITION_ESTIMATE (ArduPilot VISO_TYPE=1, PX4 EKF2_EV_CTRL bit 0; local NED at the origin
    #: set with SET_GPS_GLOBAL_ORIGIN or the one the autopilot reports). NAMED_VALUE_* status is always sent.
    outputs: tuple[OutputKind, ...] = ("gps_input",)
    #: GLOBAL_POSITION_SENSOR.id (the message's uint8 sensor instance): PX4 fuses the message only when
    #: one of its EKF2_AGP{i}_ID parameters equals it (and EKF2_AGP{i}_CTRL has bit 0 set).
    global_position_sensor_id: Annotated[int, Strict(), Field(ge=0, le=255)] = 1
    #: GPS_INPUT.gps_id: 0 feeds ArduPilot's GPS1 (GPS1_TYPE=14), 1 feeds GPS2 (GPS2_TYPE=14, e.g. next to
    #: a real GNSS with GPS_AUTO_SWITCH=1); ArduPilot ignores other ids.
    gps_input_gps_id: Annotated[int, Strict(), Field(ge=0, le=1)] = 0
    #: Rate of this daemon's own HEARTBEAT, Hz.
    heartbeat_hz: PosFloat = 1.0
    #: Rate of the estimate stream (GPS_INPUT etc.), propagated to the send time between frames, Hz.
    #: ArduPilot counts a MAVLink GPS healthy only while the mean interval is < 215 ms with no two
    #: consecutive intervals > 245 ms, so at least 5 Hz is enforced.
    estimate_rate_hz: Annotated[float, Strict(), Field(ge=5, le=50)] = 10.0
    #: Rate of the NAMED_VALUE_* status set for the ground station, Hz.
    named_value_hz: Annotated[float, Strict(), Field(gt=0, le=10)] = 2.0
    #: Attitude/altitude older than this at a frame's exposure make the frame invalid for fixes.
    attitude_max_age_s: PosFloat = 0.3
    altitude_max_age_s: PosFloat = 1.0
    #: No autopilot HEARTBEAT for this long = link lost (reported; estimation continues). On a listening
    #: link (udpin/tcpin) also how long the autopilot's address must be silent before its HEARTBEAT from
    #: another address moves the output there (until then that address is an impostor).
    link_timeout_s: PosFloat = 3.0
    #: MAVLink 2 signing key file (32 bytes, or 64 hex chars); mode 0600 required. Null = unsigned.
    signing_key_file: Str | None = None


@dataclasses.dataclass(frozen=True)
class CacheConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Cache directory built by ``gdnav cache build``.
    dir: Str = "cache"
    #: Add a full check (sha256 of every artifact) to a start the autopilot says is on the ground. Off:
    #: ``gdnav cache build`` and ``gdnav preflight`` verify every byte, and every start checks the
    #: manifest's own hash, every size, the small tables and each map cell on read. Never at a start in
    #: the air (a restart), whatever this says: docs/design.md, "Opening the cache in constant time".
    verify_hashes: Bool = False


@dataclasses.dataclass(frozen=True)
class TerrainConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Flat-ground model: ground height above mean sea level, metres.
    ground_alt_amsl_m: Float = 0.0
    #: The autopilot's ground altitude at home (its EKF's, once it has an origin) may differ from
    #: ``ground_alt_amsl_m`` by this much, m; beyond it the daemon says so and stops giving GPS_INPUT an
    #: altitude (a 520 m error was measured from a driver that read it before the origin existed).
    max_ground_alt_disagreement_m: PosFloat = 15.0


@dataclasses.dataclass(frozen=True)
class InitConfig:
    """Where the estimator starts: see ``components.c5_estimator.prior`` for the rules."""

    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Starting position when known (e.g. the last GNSS fix before denial); null = use HOME_POSITION.
    lat_deg: Annotated[float, Strict(), Field(ge=-90, le=90)] | None = None
    lon_deg: Annotated[float, Strict(), Field(ge=-180, le=180)] | None = None
    #: 1-sigma horizontal uncertainty of the starting position, m.
    sigma_m: PosFloat = 50.0
    #: Use the autopilot's HOME_POSITION as the initial prior when no lat/lon is configured.
    use_home_position: Bool = True
    #: Restart (F8): resume from the previous run's last 3D estimate (in the FDR or the resume state file)
    #: when it is at most this old; a previous run recorded within it also means "restarted in flight", s.
    resume_max_age_s: PosFloat = 120.0
    #: The resume state file: the last 3D estimate sent, rewritten atomically about once a second apart
    #: from the FDR's low-disk policy; null = resume_state.json in fdr.dir.
    resume_state_path: Str | None = None
    #: The vehicle's top ground speed: a resumed estimate's sigma grows by this times its age, m/s.
    max_speed_m_s: PosFloat = 25.0
    #: At or below this height above home, with no landed_state saying it flies, the vehicle is on the
    #: ground: the only place where the configured position and HOME_POSITION are priors, m.
    on_ground_max_alt_agl_m: PosFloat = 10.0
    #: After a restart or a start in flight, ask the autopilot for its estimate (GLOBAL_POSITION_INT and
    #: EKF_STATUS_REPORT, MAV_CMD_REQUEST_MESSAGE) and wait at most this long for it before starting
    #: without it; 0 = do not ask, s.
    autopilot_wait_s: Annotated[float, Strict(), Field(ge=0, le=2)] = 1.0
    #: A wrong prior is found out (c5_estimator/prior_doubt.py): after this many failed fix attempts in a
    #: row on frames that should match (texture, the footprint on textured map) while no map fix has
    #: confirmed the start prior, its sigma grows, and again with each further one; 0 = never.
    doubt_after_failures: Annotated[int, Strict(), Field(ge=0)] = 2
    #: Each counted failure from then on multiplies the sigma the failed attempt searched with by this.
    doubt_growth: Annotated[float, Strict(), Field(gt=1, le=10)] = 2.0
    #: Least edge share (helpers/texture.py) of the frame, and of the map where the prior puts it, for a
    #: failed attempt to count against the prior: fog, snow, water or a covered lens measure < 0.01.
    doubt_min_texture: Annotated[float, Strict(), Field(gt=0, lt=1)] = 0.05


@dataclasses.dataclass(frozen=True)
class VprConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: C2 strategy: geo_prior (tiles nearest the prior, no index), vlad (appearance, weights-free dense
    #: RootSIFT) or vlad_xfeat (appearance, VLAD over the XFeat extractor's descriptors: works across
    #: dates). Both vlad strategies need `gdnav cache vpr [--descriptor xfeat]` to have added their index
    #: to the cache; vlad_xfeat refuses a cache built with another XFeat model.
    strategy: Literal["geo_prior", "vlad", "vlad_xfeat"] = "geo_prior"
    #: vlad_xfeat: XFeat extractor ONNX file; null = the XFeat extractor of matcher.model_dir (verified).
    xfeat_weights_path: Str | None = None
    #: Candidates retrieved per frame (K).
    top_k: PosInt = 10
    #: Search radius = clamp(sigma_scale x horizontal sigma, min, max) around the prior.
    prior_sigma_scale: PosFloat = 3.0
    prior_radius_min_m: PosFloat = 60.0
    prior_radius_max_m: PosFloat = 2000.0
    #: F6 re-localisation: above this horizontal sigma, search the whole corpus instead of the prior's
    #: region (only with an appearance strategy; geo_prior keeps searching the widest region).
    corpus_wide_sigma_m: PosFloat = 300.0
    #: WARN when the best candidate's descriptor distance exceeds this (possible false retrieval). For
    #: vlad, correct top-1 distances measured p50 1.09 / p95 1.25 (wrong ones p50 1.16: a weak signal).
    top1_distance_warn: PosFloat = 1.25

    def __post_init__(self) -> None:
        if self.xfeat_weights_path is not None and self.strategy != "vlad_xfeat":
            raise SettingError(
                "xfeat_weights_path", f"is used only by strategy vlad_xfeat, strategy is {self.strategy!r}"
            )


@dataclasses.dataclass(frozen=True)
class RerankConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: C2.5 strategy: passthrough (keep C2's order) or inliers (re-rank K to N by cheap inlier counts).
    strategy: Str = "passthrough"
    #: Candidates handed to the matcher (N).
    top_n: Annotated[int, Strict(), Field(ge=1, le=10)] = 3
    #: While the prior places the camera's footprint within 1/8 of a chip at 3 sigma, the first chip is cut
    #: around the footprint instead of around a tile (c2_5_rerank/footprint.py): more of the frame on it.
    footprint_chip: Bool = True


@dataclasses.dataclass(frozen=True)
class LadderRung:
    """One rung of the fix path's effort ladder (``matcher.ladder``; ``c3_matcher/ladder.py``)."""

    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: The rung's name, as the FDR (pipeline.fix "rung") and daemon.status give it.
    name: Str
    #: C3 strategy on this rung; null = matcher.strategy (as resolved: auto, model_dir).
    strategy: Str | None = None
    #: Candidates the matcher gets, best first: 1 = the footprint chip (or the best tile) alone; at most
    #: rerank.top_n.
    candidates: Annotated[int, Strict(), Field(ge=1, le=10)] = 1
    #: The rung applies only while the prior's horizontal sigma is at most this, m; null = any prior.
    max_prior_sigma_m: PosFloat | None = None
    #: After this many attempts in a row on this rung without an accepted fix, the next rung's turn (an
    #: accepted fix on any rung starts again at the bottom); null = never.
    give_up_after: PosInt | None = None


@dataclasses.dataclass(frozen=True)
class CorrelationConfig:
    """The area correlation (``matcher.strategy: orientation_corr``; ``c3_matcher/orientation_corr.py``):
    which heading and height hypotheses it tries. The rest is fixed by the map's calibration."""

    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: 1-sigma of the autopilot's heading as the nav camera sees it (compass or GSF yaw, and the camera's
    #: mount in yaw), degrees. Rotations out to 3 sigma are tried (at most ``max_steps`` each way).
    heading_sigma_deg: PosFloat = 1.5
    #: 1-sigma of the autopilot's height above the map's ground, as a share of it (baro drift, and ground
    #: that is not at ``terrain.ground_alt_amsl_m``). Scales out to 3 sigma are tried.
    height_sigma_frac: Annotated[float, Strict(), Field(gt=0, le=0.2)] = 0.02
    #: Steps of the hypothesis grid: one template tolerates about a degree and 2 % (docs/design.md).
    heading_step_deg: Annotated[float, Strict(), Field(gt=0, le=5)] = 1.0
    height_step_frac: Annotated[float, Strict(), Field(gt=0, le=0.1)] = 0.02
    #: Most steps tried on each side of the autopilot's heading and height.
    max_steps: Annotated[int, Strict(), Field(ge=0, le=8)] = 4


@dataclasses.dataclass(frozen=True)
class MatcherConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: C3 strategy: classical (weights-free), disk_lightglue, aliked_lightglue, xfeat, xfeat_mnn (the XFeat
    #: extractor matched by mutual nearest neighbour, no LightGlue: the fast one on a CPU),
    #: orientation_corr (the whole frame correlated with the map's orientation fields: weights-free, the
    #: real-time cross-date matcher on a CPU; needs the cache's calibrated map fields), or auto (by what
    #: this machine runs: with a CUDA or TensorRT provider disk_lightglue, aliked_lightglue, xfeat; on a CPU
    #: alone xfeat, aliked_lightglue, disk_lightglue; the first whose export in model_dir passed `gdnav
    #: models verify`; else an ALIKED extractor alone with mutual NN; else classical; logged with why).
    strategy: Str = "classical"
    #: Model directory made by `gdnav models export` (its manifest is verified at start-up); a learned
    #: strategy whose extractor path is null takes its extractor, and its LightGlue when
    #: lightglue_weights_path is null too, from it.
    model_dir: Str | None = None
    #: Below this many RANSAC inliers on every candidate: InsufficientInliersError, VIO-only fallback.
    #: Measured across dates (DISK, NAIP 2009 map, 2014 frames, every frame): at 12, half the solutions
    #: from 12-24 inliers had the camera tilted > 15 deg, and the wrong ones that passed took the attitude
    #: check's verdict with them: 74 fixes accepted instead of 131 (docs/benchmarks.md).
    min_inliers_threshold: PosInt = 25
    #: Best candidate's median residual above this is logged as a WARN (C3.5 refinement trigger).
    residual_warn_threshold_px: PosFloat = 2.5
    #: RANSAC (USAC MAGSAC) inlier threshold, confidence and iteration cap.
    ransac_threshold_px: PosFloat = 3.0
    ransac_confidence: Annotated[float, Strict(), Field(gt=0.5, lt=1.0)] = 0.999
    ransac_max_iters: PosInt = 5000
    #: Side of the map chip matched per candidate, px (the chip is centred on the tile).
    chip_size_px: Annotated[int, Strict(), Field(ge=128, le=4096)] = 512
    #: The area correlation's hypotheses (``orientation_corr``).
    correlation: CorrelationConfig = CorrelationConfig()
    #: Classical (weights-free) strategy.
    classical_detector: Literal["sift", "orb"] = "sift"
    #: Features per image and Lowe's ratio for the classical strategy.
    max_features: PosInt = 1500
    ratio_test: Annotated[float, Strict(), Field(gt=0, le=1)] = 0.8
    #: Learned strategies: ONNX extractor files in the LightGlue-ONNX layout (see README "Models").
    disk_weights_path: Str | None = None
    aliked_weights_path: Str | None = None
    xfeat_weights_path: Str | None = None
    #: LightGlue-ONNX matcher file; null = mutual nearest neighbour on the descriptors.
    lightglue_weights_path: Str | None = None
    #: Long side of the image given to a dynamic-size extractor, px (fixed-size models use their own).
    input_long_side_px: Annotated[int, Strict(), Field(ge=64, le=4096)] = 640
    #: Keypoints kept per image by learned extractors (top scores).
    max_keypoints: PosInt = 2048
    #: Learned strategies: the cache's precomputed tile features (`gdnav cache features`). auto = use
    #: them when the cache has a set made by this very extractor (model sha256, chip size, keypoints)
    #: and it verifies, else extract live (logged, recorded); require = refuse to start without such a
    #: set (exit 3); off = always extract live.
    tile_features: Literal["auto", "require", "off"] = "auto"
    #: The fix path's effort ladder, cheapest rung first (each: name, strategy, candidates,
    #: max_prior_sigma_m, give_up_after; see LadderRung and docs/design.md "Effort ladder"). Each attempt
    #: takes the first rung the prior's sigma and that rung's run of failures allow. Empty = one rung:
    #: matcher.strategy with rerank.top_n candidates.
    ladder: tuple[LadderRung, ...] = ()


@dataclasses.dataclass(frozen=True)
class PoseConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Fewer inliers than this: no pose (degenerate).
    min_inliers: Annotated[int, Strict(), Field(ge=4)] = 12
    #: Solved camera axis vs autopilot camera axis: larger = implausible, rejected.
    max_attitude_disagreement_deg: PosFloat = 15.0
    #: Solved height above ground vs autopilot AGL: larger relative difference = rejected.
    max_alt_disagreement_frac: Fraction = 0.35
    #: Floor on the per-axis position sigma (model error the residuals cannot see), metres; also the
    #: error every fix shares, never averaged away (set it to at least the map's absolute accuracy).
    min_sigma_m: PosFloat = 1.0
    #: 1-sigma of the autopilot's roll and pitch as the nav camera sees them, degrees: the AHRS's own
    #: error, the camera mount's boresight calibration and the ATTITUDE-to-exposure timing together. The
    #: solver weighs the autopilot's tilt against the image's with it (position error from a tilt error
    #: grows with height: 0.5 deg at 1200 m AGL is 10 m), and states the result in the fix's sigma. Set it
    #: to what the aircraft's attitude is known to, never below: a smaller value makes fixes overconfident.
    attitude_sigma_deg: PosFloat = 0.5
    #: Matches beyond this many are not counted as independent evidence: the image noise the solver
    #: weighs them with is scaled by sqrt(inliers / this). Match errors against a map are correlated
    #: (the same changed field, the same resampling), so a few hundred inliers do not pin the camera's
    #: tilt a few hundred times better than a few: across dates the image-only tilt was measured 1-3 deg
    #: off with a formal sigma near 0.1 deg.
    max_independent_matches: Annotated[int, Strict(), Field(ge=6)] = 10
    #: The attitude check (``c4_pose/attitude_check.py``): the image-only tilts of up to this many recent
    #: solved fixes (windows of 4, 8, ... and all of them) say whether the autopilot's is off by more than
    #: 3 x ``attitude_sigma_deg``; while it is, every fix is refused. Unless its fixes pin the tilt better
    #: than that sigma, a window proves nothing over less ground than two footprints (the image's tilt
    #: error across dates is shared over one). 400 holds ``attitude_check_max_age_s`` at a camera rate of
    #: 3 Hz, the fix path on every frame (a GPU).
    attitude_check_fixes: Annotated[int, Strict(), Field(ge=4)] = 400
    #: Fixes older than this, s, leave the attitude check's window.
    attitude_check_max_age_s: PosFloat = 120.0
    #: The same check on VO's ground tilt (``c1_vio/ground_tilt.py``: the camera's tilt to the ground
    #: from each pair of frames, at the camera rate, with no map): while it finds the autopilot's tilt
    #: off, fixes are refused (``vo_attitude_off``), the estimate states what it may carry and the IMU
    #: is left out, as for the fixes' check. It sees a bias within seconds whatever the matcher's speed.
    #: False: the fixes' check alone.
    ground_tilt_check: Bool = True
    #: VO ground tilts kept (windows of 4, 8, ... and all of them); at 3 Hz, 24 is 8 s.
    ground_tilt_check_samples: Annotated[int, Strict(), Field(ge=4)] = 24
    #: VO ground tilts older than this, s, leave the window (how soon it clears once the attitude is back).
    ground_tilt_check_max_age_s: PosFloat = 10.0


@dataclasses.dataclass(frozen=True)
class IntegrityConfig:
    """Fix integrity (``components/c4_pose/integrity.py``): when a solved fix is refused, and how its
    covariance grows with weak evidence."""

    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Off: every solved fix goes to the estimator with the solver's covariance (the evidence is still
    #: recorded). For measurements only; never fly with it off.
    enabled: Bool = True
    #: Refuse a fix from fewer RANSAC inliers than this.
    min_inliers: PosInt = 20
    #: Refuse a fix whose inliers are a smaller share of the putative matches than this.
    min_inlier_ratio: Fraction = 0.2
    #: Refuse a fix whose inliers' convex hull covers a smaller share of the nav frame than this.
    min_spread_share: Fraction = 0.05
    #: Refuse a fix whose inliers' mean matcher confidence (LightGlue) is below this; not applied to
    #: matchers that give no confidence (classical, mutual nearest neighbour). Measured with the attitude
    #: prior: the 20 cross-date fixes with 0.20-0.30 (XFeat, ALIKED; NAIP 2009 map, 2014 frames) were all
    #: within 2 solver sigmas of the truth, and their sigma is scaled up 3-7x below
    #: ``full_evidence_confidence``. Below 0.20: of 16 ALIKED fixes refused (same flight, every frame),
    #: 15 were within 3 sigmas and one 4.05 sigmas off, so the bar stays.
    min_mean_confidence: Fraction = 0.2
    #: A candidate with at least this share of the best candidate's inliers is a rival: its pose is
    #: solved, and one farther from the best's than ``ambiguity_sigma`` combined sigmas (the solvers'
    #: sigmas floored at the map pixel, not inflated) refuses the fix.
    ambiguity_inlier_share: Annotated[float, Strict(), Field(gt=0, le=1)] = 0.5
    ambiguity_sigma: PosFloat = 3.0
    #: A fix with weak evidence (sigma scale at least ``weak_evidence_scale``) must agree with the prior:
    #: horizontal NIS (2 dof) within ``prior_gate_chi2`` (9.21 = 99 %), checked while the prior's sigma
    #: is at most ``prior_max_sigma_m``. Stronger fixes are left to the estimator's gate. At 1.5 a
    #: cross-date XFeat fix with scale 1.42 and prior NIS 15 was accepted 4.0 sigma off; every
    #: same-date fix of `gdnav bench flights` (512, four strategies) had scale 1.0.
    weak_evidence_scale: Annotated[float, Strict(), Field(ge=1)] = 1.1
    prior_gate_chi2: PosFloat = 9.21
    prior_max_sigma_m: PosFloat = 150.0
    #: Full evidence: at or above these the sigma is not inflated; below, each scales it up (inliers by
    #: the square root of the shortfall, the inlier ratio linearly). The inliers' number and geometry
    #: are already in the solver's covariance: these stand for the risk of a wrong alignment.
    full_evidence_inliers: PosInt = 50
    full_evidence_ratio: Fraction = 0.5
    #: The same for the inliers' mean matcher confidence (LightGlue; linearly). Every same-date fix of
    #: `gdnav bench flights` had 0.58 or more, the cross-date ones 0.25-0.64.
    full_evidence_confidence: Fraction = 0.6
    #: A fix short of full evidence (sigma scale at least ``weak_evidence_scale``) also states this
    #: regional error, in map pixels, on top of the rest, and carries it as error every nearby fix shares
    #: (it is left out where map fixes are compared: the prior check, the consistency pairs): for a map
    #: whose georeference is known to wander by region. 0 = off, the default: the shared offsets of
    #: 20-50 m measured on cross-date XFeat fixes at 1200 m AGL were the camera's tilt solved from the
    #: image alone; with the attitude prior (``pose.attitude_sigma_deg``) they are gone (docs/benchmarks.md).
    regional_sigma_map_px: Annotated[float, Strict(), Field(ge=0)] = 0.0
    #: An area correlation's fix (``orientation_corr``) is refused when its peak-to-sidelobe ratio is below
    #: ``min_psr``, or below ``psr_null_margin`` times what a wrong place scores on this map (the cache's
    #: calibration); likewise its normalised peak against ``min_peak`` and ``peak_null_margin``; and when
    #: a second place scores ``max_secondary_ratio`` of the peak or more. Measured on NAIP across dates
    #: (docs/benchmarks.md, "Area correlation"): right fixes PSR p5 12-14, peak p5 0.13; wrong places
    #: PSR at most 5.7, peak at most 0.045.
    min_psr: PosFloat = 8.0
    psr_null_margin: Annotated[float, Strict(), Field(ge=1)] = 1.5
    min_peak: Fraction = 0.06
    peak_null_margin: Annotated[float, Strict(), Field(ge=1)] = 2.0
    max_secondary_ratio: Annotated[float, Strict(), Field(gt=0, le=1)] = 0.8
    #: An area correlation's fix whose frame is close enough to the map that its patches were tried, and of
    #: whose patches fewer than this share agree, is refused: the frame matches as a whole but not in its
    #: parts, so the tilt it was rectified with is off (a 3 deg roll fault at 120 m over GeoVision: 23 of 43
    #: agreed, against 42 of 42 the frame before). 0.8 is the share at which the patches are handed to C4.
    min_patch_agreement: Fraction = 0.8
    #: Full evidence of an area fix: at or above these its sigma is not inflated; below, each scales it up
    #: linearly.
    full_evidence_psr: PosFloat = 15.0
    full_evidence_peak: Fraction = 0.15
    #: Cap on the sigma factor.
    max_sigma_scale: Annotated[float, Strict(), Field(ge=1)] = 10.0
    #: Floor on the per-axis sigma in map pixels (a match is never better than the map's pixel).
    min_sigma_map_px: Annotated[float, Strict(), Field(ge=0)] = 1.0
    #: Fix consistency (``components/c4_pose/consistency.py``): each passed fix's covariance is scaled
    #: by what the last pairs of fixes, compared through VO, measured. Off: the rule's covariance as is.
    consistency_enabled: Bool = True
    #: Pairs of consecutive fixes the scale is measured on.
    consistency_window_pairs: PosInt = 20
    #: One-sided confidence level of the scale's upper bound (smaller = more conservative).
    consistency_confidence: Annotated[float, Strict(), Field(gt=0, lt=1)] = 0.05
    #: One pair's NIS counts at most this much (a wrong-tile outlier is the estimator gate's business).
    consistency_nis_cap: PosFloat = 100.0
    #: Two fixes farther apart than this are not paired (VO drift over the gap says little), s.
    consistency_max_gap_s: PosFloat = 60.0
    #: Sigma factor for a fix with no pair measured yet (the first of a run, or after VO broke the chain).
    unverified_sigma_scale: Annotated[float, Strict(), Field(ge=1)] = 3.0


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: White-noise acceleration spectral density for the constant-velocity model (used while the
    #: autopilot's IMU is not available), m/s^2/sqrt(Hz). It must cover a manoeuvre nobody measures: at
    #: 1.5 a 5 s link drop in a 15 deg/s, 12 m/s turn left the stated sigma 4x too small (soak); 3.0
    #: keeps that turn inside 3 sigma.
    accel_noise_m_s2: PosFloat = 3.0
    #: The same while the prediction is driven by the autopilot's IMU and attitude: what the IMU leaves
    #: unexplained (accelerometer bias, attitude error, vibration), m/s^2/sqrt(Hz).
    imu_accel_noise_m_s2: PosFloat = 0.5
    #: Chi-square gate on absolute fixes (2 dof); 13.8 = 99.9 %.
    fix_gate_chi2: PosFloat = 13.8
    #: Accept an ungated fix once the horizontal sigma exceeds this (re-acquisition after a gap).
    reacquire_sigma_m: PosFloat = 150.0
    #: Above this horizontal sigma the output is labelled no_estimate (fix_type 0).
    max_output_sigma_m: PosFloat = 500.0
    #: A start prior no fix has confirmed yet, contradicted by consecutive gated fixes that agree with
    #: each other over at least this much ground, is given up for them (``c5_estimator/ekf.py``), m.
    prior_conflict_span_m: PosFloat = 200.0
    #: Multiplies the visual-odometry covariance (tune for a real camera; 1 = as measured).
    vo_noise_scale: PosFloat = 1.0
    #: Time axis: an input stamped more than this ahead of the daemon's clock is refused, s.
    max_future_s: Annotated[float, Strict(), Field(gt=0, le=5)] = 0.25
    #: Time axis: how far behind the newest input a late one (a slow absolute fix) may still be fused
    #: at its own exposure time; older ones are refused as too late, s. It must cover the fix path's
    #: latency on this computer, or every fix is dropped: DISK + LightGlue on a 2-core CPU answers 7-17 s
    #: after the exposure (with 5 s, a DISK flight fused none of them). A fix fused late is as right as
    #: one on time; the cost is the rewind, 0.2-0.3 ms per input fused again (9 inputs a second at 3 Hz),
    #: under the lock the 10 Hz output waits for (docs/benchmarks.md, "Late fixes").
    max_fix_delay_s: Annotated[float, Strict(), Field(gt=0, le=60)] = 20.0
    #: Provenance: an accepted fix keeps the output ``satellite_anchored`` until its exposure is this
    #: old, while no later fix attempt has failed (a failed one ends it at once), s. It must cover the
    #: fix path's own period: a fix arrives its latency after its exposure, and the next one a period
    #: later. XFeat + LighterGlue on a 2-core CPU answers 1.6-1.8 s after the exposure (3.4 s p95
    #: under the soak's faults), so a 1 s window never labelled its output anchored.
    anchored_window_s: Annotated[float, Strict(), Field(gt=0, le=60)] = 5.0


@dataclasses.dataclass(frozen=True)
class FdrConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Flight data recorder directory; total size bounded by max_bytes (oldest segments deleted).
    dir: Str = "fdr"
    max_bytes: Annotated[int, Strict(), Field(ge=1 << 16)] = 256 << 20
    segment_bytes: Annotated[int, Strict(), Field(ge=1 << 14)] = 16 << 20
    #: Store every N-th nav frame (camera seq a multiple of N) as a JPEG in <dir>/images; 0 = off.
    frame_jpeg_every_n: Annotated[int, Strict(), Field(ge=0)] = 0
    #: Encoding of those frames: jpeg (small, lossy) or png (lossless: with frame_jpeg_every_n 1, `gdnav
    #: replay` reproduces the flight's per-frame estimates exactly).
    frames_format: Literal["jpeg", "png"] = "jpeg"
    #: JPEG quality of those frames (1..100).
    frame_jpeg_quality: Annotated[int, Strict(), Field(ge=1, le=100)] = 80
    #: Budget of the frame images, bytes, apart from max_bytes (oldest images deleted first).
    frame_jpeg_max_bytes: Annotated[int, Strict(), Field(ge=0)] = 64 << 20
    #: Below this much free space on the file system, images are deleted and no longer written; below a
    #: quarter of it, records are dropped too (counted, reported as GDN_FDR). 0 = not checked.
    min_free_bytes: Annotated[int, Strict(), Field(ge=0)] = 64 << 20

    def __post_init__(self) -> None:
        # The recorder deletes whole segments to stay under max_bytes: the bound must hold one segment.
        if self.max_bytes < self.segment_bytes:
            raise SettingError(
                "max_bytes", f"must be at least segment_bytes ({self.segment_bytes}), got {self.max_bytes}"
            )
        if self.frame_jpeg_every_n > 0 and self.frame_jpeg_max_bytes < 1 << 16:
            raise SettingError(
                "frame_jpeg_max_bytes",
                f"must be at least 65536 when frame_jpeg_every_n > 0, got {self.frame_jpeg_max_bytes}",
            )


@dataclasses.dataclass(frozen=True)
class LoggingConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Structured-log level and format (JSON lines on stderr; false = human-readable).
    level: Literal["debug", "info", "warning", "error"] = "info"
    json: Bool = True


@dataclasses.dataclass(frozen=True)
class DaemonConfig:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Rate of the status log line and systemd STATUS, Hz.
    status_hz: PosFloat = 1.0
    #: Frames older than this when the pipeline gets to them are dropped, s.
    max_frame_age_s: PosFloat = 1.0
    #: ONNX Runtime intra-op threads for learned strategies.
    onnx_intra_op_threads: PosInt = 2
    #: At stop, how long the worker threads may take to finish the frame they are in before the process
    #: ends without them (it then exits at once, without tearing down a running ONNX Runtime), s.
    frame_stop_grace_s: Annotated[float, Strict(), Field(gt=0, le=1.5)] = 0.5
    #: Threads of numpy's BLAS (OpenBLAS, OpenMP), set before numpy loads (`gdnav run` only). 1: a matrix
    #: product (mutual NN, RANSAC) runs on the thread that asked for it instead of spreading over both
    #: cores beside the event loop; measured: the xfeat_mnn fix path 0.75x, its matrix product 0.53x.
    blas_threads: PosInt = 1
    #: The fix thread's nice value above the daemon's (Linux: per thread); 0 = the same priority. With two
    #: busy loops at nice 0 on the 2 cores (AMD EPYC, the daemon at nice -5) 5 made the fix path give way
    #: to them without helping the output: the area correlation's exposure-to-judged-fix p95 420 ms
    #: against 176 ms at 0, and XFeat flat out 0.55 attempts/s and GPS_INPUT interval p99 119 ms, max
    #: 149 ms, against 1.27/s and 103 / 108 ms at 0 (docs/benchmarks.md, "Priorities under load").
    fix_thread_nice: Annotated[int, Strict(), Field(ge=0, le=19)] = 0
    #: The daemon's own nice value: ahead of a companion's ordinary work (nice 0), so that its output, VO
    #: and fix path keep their pace when the computer is busy. The systemd unit sets it (``Nice=-5``);
    #: `gdnav run` started otherwise lowers its nice value to this at start where the process may (root,
    #: or CAP_SYS_NICE) and logs what it got (never raises it: an operator who started it nicer meant
    #: it). null = leave it as started.
    process_nice: Annotated[int, Strict(), Field(ge=-20, le=19)] | None = -5
    #: Run the vision (camera, VO, VPR, matching, pose, fusion) in a worker process under a light navigator
    #: core that holds the MAVLink link and the output (``daemon/core.py``): a crash, a kill or an OOM of
    #: the worker then costs sigma growth on the IMU, never a gap in the autopilot's estimate stream.
    #: false: one process holds both, and any crash silences the output until systemd restarts it.
    vision_worker: Bool = True
    #: The vision worker's nice value above the core's (the core ahead of it, the worker behind).
    worker_nice_offset: Annotated[int, Strict(), Field(ge=0, le=19)] = 5
    #: A started worker that sends nothing for this long is stalled: killed and started again, s.
    worker_silence_s: Annotated[float, Strict(), Field(gt=0.5, le=60)] = 3.0
    #: From a worker's start to its first message (its imports, the map, the models), at most, s.
    worker_start_s: Annotated[float, Strict(), Field(gt=1, le=600)] = 60.0
    #: A worker whose core has gone (killed, crashed, stopped by its watchdog) keeps its pipeline running
    #: this long for the core's next start to adopt it, so a core restart costs no vision start-up; then it
    #: ends itself (also when stuck in native code), s. It never speaks to the autopilot itself.
    worker_orphan_s: Annotated[float, Strict(), Field(gt=0.5, le=120)] = 10.0


@dataclasses.dataclass(frozen=True)
class Config:
    __pydantic_config__: ClassVar[ConfigDict] = _STRICT

    #: Name of the profile (logged and recorded; no behaviour depends on it).
    profile: Str = "default"
    camera: CameraConfig = dataclasses.field(default_factory=CameraConfig)
    mavlink: MavlinkConfig = dataclasses.field(default_factory=MavlinkConfig)
    cache: CacheConfig = dataclasses.field(default_factory=CacheConfig)
    terrain: TerrainConfig = dataclasses.field(default_factory=TerrainConfig)
    init: InitConfig = dataclasses.field(default_factory=InitConfig)
    vpr: VprConfig = dataclasses.field(default_factory=VprConfig)
    rerank: RerankConfig = dataclasses.field(default_factory=RerankConfig)
    matcher: MatcherConfig = dataclasses.field(default_factory=MatcherConfig)
    pose: PoseConfig = dataclasses.field(default_factory=PoseConfig)
    integrity: IntegrityConfig = dataclasses.field(default_factory=IntegrityConfig)
    estimator: EstimatorConfig = dataclasses.field(default_factory=EstimatorConfig)
    fdr: FdrConfig = dataclasses.field(default_factory=FdrConfig)
    logging: LoggingConfig = dataclasses.field(default_factory=LoggingConfig)
    daemon: DaemonConfig = dataclasses.field(default_factory=DaemonConfig)


class ConfigError(ValueError):
    """Invalid configuration. ``key_path`` is dotted (``matcher.min_inliers_threshold``)."""

    def __init__(self, key_path: str, message: str, *, source: str | None = None) -> None:
        where = f"{source}: " if source else ""
        super().__init__(f"config error: {where}{key_path}: {message}")
        self.key_path = key_path
        self.source = source


_ADAPTER = TypeAdapter(Config)


def _tuples(value: Any) -> Any:
    """YAML lists -> tuples (strict mode accepts only tuples for tuple fields)."""
    if isinstance(value, Mapping):
        return {k: _tuples(v) for k, v in value.items()}
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value


def _describe(err: Mapping[str, Any]) -> tuple[str, str]:
    loc = ".".join(str(p) for p in err.get("loc", ()) if not isinstance(p, int)) or "<root>"
    typ = err.get("type", "")
    got = err.get("input")
    if typ in ("extra_forbidden", "unexpected_keyword_argument"):
        return loc, "unknown key (not a setting; check the spelling against config/airborne.yaml)"
    if typ == "value_error":  # raised by our own checks (check_mavlink_url, __post_init__ rules)
        cause = err.get("ctx", {}).get("error")
        if isinstance(cause, SettingError):
            return f"{loc}.{cause.key}", str(cause)
        return loc, f"{cause}, got {got!r}"
    msg = str(err.get("msg", "invalid value"))
    if msg.startswith("Input should be"):
        msg = "expected" + msg[len("Input should be") :]
    return loc, f"{msg}, got {got!r}"


def config_from_mapping(data: Mapping[str, Any], *, source: str | None = None) -> Config:
    if not isinstance(data, Mapping):
        raise ConfigError(
            "<root>", f"expected a mapping of sections, got {type(data).__name__}", source=source
        )
    try:
        return _ADAPTER.validate_python(_tuples(dict(data)))
    except ValidationError as exc:
        loc, msg = _describe(exc.errors()[0])
        raise ConfigError(loc, msg, source=source) from exc


def _apply_override(data: dict[str, Any], assignment: str) -> None:
    key, sep, raw = assignment.partition("=")
    if not sep or not key.strip():
        raise ConfigError(assignment, "override must be KEY.PATH=VALUE")
    parts = key.strip().split(".")
    node = data
    for part in parts[:-1]:
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(key, f"'{part}' is not a section")
        node = nxt
    try:
        node[parts[-1]] = _safe_load(raw, key, None) if raw.strip() else None
    except yaml.YAMLError as exc:
        raise ConfigError(key, f"override value is not valid YAML: {exc}".replace("\n", " ")) from exc


#: Bounds on what a profile (or one override) may hold: its file's size, and its nesting and node count
#: with YAML aliases expanded (a profile is a few kB, 3 levels deep, a few hundred values; an alias
#: "billion laughs" expands exponentially in every later step).
MAX_PROFILE_BYTES: Final[int] = 1 << 20
MAX_PROFILE_DEPTH: Final[int] = 32
MAX_PROFILE_NODES: Final[int] = 100_000


def _check_shape(data: Any, key: str, source: str | None) -> None:
    """Refuse ``data`` nested deeper or holding more values than the bounds above (walked without
    recursion, aliases counted each time they are used)."""
    stack: list[tuple[Any, int]] = [(data, 1)]
    nodes = 0
    while stack:
        node, depth = stack.pop()
        nodes += 1
        if depth > MAX_PROFILE_DEPTH or nodes > MAX_PROFILE_NODES:
            if depth > MAX_PROFILE_DEPTH:
                what = f"nested deeper than {MAX_PROFILE_DEPTH}"
            else:
                what = f"more than {MAX_PROFILE_NODES} values (YAML aliases expanded)"
            raise ConfigError(key, f"{what}: not a profile", source=source)
        if isinstance(node, Mapping):
            stack.extend((v, depth + 1) for v in node.values())
        elif isinstance(node, (list, tuple)):
            stack.extend((v, depth + 1) for v in node)


def _safe_load(text: str, key: str, source: str | None) -> Any:
    """``yaml.safe_load`` whose deep nesting (RecursionError in PyYAML's composer) is a ConfigError."""
    try:
        loaded = yaml.safe_load(text)
    except RecursionError:
        raise ConfigError(key, "nested too deeply to parse: not a profile", source=source) from None
    _check_shape(loaded, key, source)
    return loaded


def config_with_overrides(
    data: Mapping[str, Any], overrides: Sequence[str] = (), *, source: str | None = None
) -> Config:
    """A config from a mapping (e.g. the ``daemon.config`` an FDR recorded) with ``KEY.PATH=VALUE``
    overrides applied, validated like a file."""
    _check_shape(data, "<root>", source)
    copy = json.loads(json.dumps(dict(data)))
    for item in overrides:
        _apply_override(copy, item)
    return config_from_mapping(copy, source=source)


def load_config(path: str | Path | None, overrides: Sequence[str] = ()) -> Config:
    """Load a YAML profile (or defaults when ``path`` is None) and apply ``KEY.PATH=VALUE`` overrides.

    Relative paths inside the profile (cache.dir, fdr.dir, model files) are resolved against the
    current working directory by their users, not here.
    """
    data: dict[str, Any] = {}
    source = None
    if path is not None:
        p = Path(path)
        source = str(p)
        if not p.is_file():
            raise ConfigError("<file>", "config file not found", source=source)
        try:
            if p.stat().st_size > MAX_PROFILE_BYTES:
                raise ConfigError(
                    "<file>", f"larger than {MAX_PROFILE_BYTES} bytes: not a profile", source=source
                )
            loaded = _safe_load(p.read_text(encoding="utf-8"), "<file>", source)
        except UnicodeDecodeError as exc:
            raise ConfigError(
                "<file>", f"not UTF-8 text (byte {exc.start}: {exc.reason})", source=source
            ) from exc
        except OSError as exc:
            raise ConfigError("<file>", f"cannot be read: {exc.strerror}", source=source) from exc
        except yaml.YAMLError as exc:
            raise ConfigError("<file>", f"not valid YAML: {exc}".replace("\n", " "), source=source) from exc
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise ConfigError("<root>", f"expected a mapping, got {type(loaded).__name__}", source=source)
        data = loaded
    for item in overrides:
        _apply_override(data, item)
    return config_from_mapping(data, source=source)


def config_to_dict(cfg: Config) -> dict[str, Any]:
    """Plain, JSON-serialisable view (for the start-up log and the FDR)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=list))
