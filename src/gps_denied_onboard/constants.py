"""Every name and number that another program sees, in one place.

MAVLink identities and rates, provenance labels, structured-log event names and FDR record kinds are
part of the daemon's external contract: ground stations, log pipelines and replay tools key on them.
Change them here only, and only on purpose.
"""

from __future__ import annotations

from enum import Enum
from typing import Final

# --- MAVLink identity -------------------------------------------------------------------------------
#: Component id of this daemon (MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY = 197).
MAV_COMPONENT_ID: Final[int] = 197
#: Minimum spacing between two STATUSTEXT messages about provenance, s (rate limit).
STATUSTEXT_MIN_INTERVAL_S: Final[float] = 1.0
#: GPS_INPUT.gps_id for GPS1 (ArduPilot silently ignores other ids for the first GPS).
GPS_INPUT_GPS_ID: Final[int] = 0
#: SET_GPS_GLOBAL_ORIGIN is repeated at this interval until the autopilot reports GPS_GLOBAL_ORIGIN, s.
SET_GPS_GLOBAL_ORIGIN_INTERVAL_S: Final[float] = 10.0
#: An impostor (another address claiming the autopilot's system and component ids) is reported (log,
#: FDR, STATUSTEXT) at most once per this interval, with the messages ignored since the last report, s.
IMPOSTOR_REPORT_INTERVAL_S: Final[float] = 10.0
#: The ``mavlink.link_event`` record's ``event`` for an impostor report (docs/fdr.md).
LINK_EVENT_IMPOSTOR: Final[str] = "impostor"
#: The STATUSTEXT that reports an impostor to the ground: its address and the messages ignored so far (fits
#: STATUSTEXT's 50 characters for any IPv4 address).
IMPOSTOR_STATUSTEXT: Final[str] = "GDN: impostor {source} x{messages}"
#: The autopilot's own TIMESYNC requests are answered at most once per this interval, s (ArduPilot asks
#: every 10 s; a flood of 75,000 requests/s drew 50,538 answers in 10 s and cut GPS_INPUT to 4.6/s).
TIMESYNC_ANSWER_MIN_INTERVAL_S: Final[float] = 0.1
#: F8 resume state file (``c5_estimator.resume_state``): its name in ``fdr.dir`` when
#: ``init.resume_state_path`` is null, and how often it is rewritten at most, s.
RESUME_STATE_FILENAME: Final[str] = "resume_state.json"
RESUME_STATE_INTERVAL_S: Final[float] = 1.0

#: Where a command's unexpected exception (a bug) keeps its traceback: the file this environment variable
#: names, else DEBUG_LOG_FILENAME in $LOGS_DIRECTORY (systemd's LogsDirectory=), else in
#: ~/.local/state/gdnav. The file is started afresh once it exceeds DEBUG_LOG_MAX_BYTES.
DEBUG_LOG_ENV: Final[str] = "GDNAV_DEBUG_LOG"
DEBUG_LOG_FILENAME: Final[str] = "debug.log"
DEBUG_LOG_MAX_BYTES: Final[int] = 1 << 20

# NAMED_VALUE_* names: 10 characters at most (MAVLink field size).
NV_PROVENANCE: Final[str] = "GDN_PROV"
NV_INLIERS: Final[str] = "GDN_INL"
NV_RESIDUAL_PX: Final[str] = "GDN_RES"
NV_HORIZ_SIGMA_M: Final[str] = "GDN_HSIG"
NV_FRAME_DROPS: Final[str] = "GDN_DROP"
#: Flight data recorder health: ``FdrHealthState.code`` (0 ok, 1 degraded, 2 failing).
NV_FDR_HEALTH: Final[str] = "GDN_FDR"
#: Solved fixes the fix-integrity rule refused since start (all reasons; by reason in daemon.status).
NV_INTEGRITY_REFUSED: Final[str] = "GDN_IREF"

# STATUSTEXT the operator reads about the start prior (``c5_estimator/prior.py``, ``prior_doubt.py``);
#: 50 characters at most (MAVLink field size), ``{}`` fields filled by the daemon.
STATUSTEXT_PRIOR_DISPUTED: Final[str] = "GDN: start points {:.0f} m apart, searching wide"
STATUSTEXT_PRIOR_UNCONFIRMED: Final[str] = "GDN: {} is a claim: no 3D until map fix"
STATUSTEXT_PRIOR_DOUBTED: Final[str] = "GDN: prior doubted, {} fails, search {:.0f} m"
STATUSTEXT_PRIOR_REANCHORED: Final[str] = "GDN: re-anchored {:.0f} m from the prior"
# STATUSTEXT about the vision worker (``daemon/core.py``).
STATUSTEXT_WORKER_LOST: Final[str] = "GDN: vision lost ({}), on IMU, restarting"
STATUSTEXT_WORKER_BACK: Final[str] = "GDN: vision back after {:.1f} s"
STATUSTEXT_WORKER_ADOPTED: Final[str] = "GDN: core restarted, vision kept"

#: ``gdnav`` exit codes: success, a failure, a bad configuration or arguments, a refused file, model or
#: port. systemd's unit restarts on none of 2 and 3 (``RestartPreventExitStatus=``): restarting cannot
#: fix them, and the navigator core stops with its vision worker's 2 or 3 for the same reason.
EXIT_OK: Final = 0
EXIT_FAILURE: Final = 1
EXIT_CONFIG: Final = 2
EXIT_RESOURCE: Final = 3

#: The navigator core's own flight data records, under ``fdr.dir`` (``daemon/core.py``).
CORE_FDR_SUBDIR: Final[str] = "core"

# --- SITL transport ---------------------------------------------------------------------------------
#: Magic prefix of a frame message on the SITL camera stream (see camera.stream).
FRAME_STREAM_MAGIC: Final[bytes] = b"GDNF"


class Provenance(str, Enum):
    """Where an estimate came from; one vocabulary for logs, FDR and MAVLink."""

    SATELLITE_ANCHORED = "satellite_anchored"
    VISUAL_PROPAGATED = "visual_propagated"
    DEAD_RECKONING = "dead_reckoning"
    NO_ESTIMATE = "no_estimate"

    @property
    def code(self) -> int:
        """Integer code sent as NAMED_VALUE_INT ``GDN_PROV``."""
        return _PROVENANCE_CODES[self]


_PROVENANCE_CODES: Final[dict[Provenance, int]] = {
    Provenance.NO_ESTIMATE: 0,
    Provenance.DEAD_RECKONING: 1,
    Provenance.VISUAL_PROPAGATED: 2,
    Provenance.SATELLITE_ANCHORED: 3,
}


class FdrHealthState(str, Enum):
    """What the flight data recorder can still do (status line, ``GDN_FDR``)."""

    #: Records and images (when on) are written.
    OK = "ok"
    #: Low free space or images dropped recently: images are sacrificed, records are still written.
    DEGRADED = "degraded"
    #: Records dropped recently (ENOSPC, I/O error, below the records' floor): the flight is not recorded.
    FAILING = "failing"

    @property
    def code(self) -> int:
        """Integer code sent as NAMED_VALUE_INT ``GDN_FDR``."""
        return _FDR_HEALTH_CODES[self]


_FDR_HEALTH_CODES: Final[dict[FdrHealthState, int]] = {
    FdrHealthState.OK: 0,
    FdrHealthState.DEGRADED: 1,
    FdrHealthState.FAILING: 2,
}


class LogEvent:
    """Structured-log event names (the seeds' names where a seed defines them)."""

    DAEMON_CONFIG: Final = "daemon.config"
    #: The area fixes find the autopilot's heading or height off the map's, or agreeing again.
    HEADING_HEIGHT_CHECK: Final = "c4.heading_height.changed"
    #: The nice value ``gdnav run`` runs at (``daemon.process_nice``): set, kept, or not permitted.
    DAEMON_PRIORITY: Final = "daemon.priority"
    DAEMON_READY: Final = "daemon.ready"
    #: The start-up beacon (``daemon.beacon``) began / handed the link to the daemon's tasks.
    DAEMON_BEACON_STARTED: Final = "daemon.beacon_started"
    DAEMON_BEACON_STOPPED: Final = "daemon.beacon_stopped"
    DAEMON_STOPPING: Final = "daemon.stopping"
    DAEMON_STOPPED: Final = "daemon.stopped"
    DAEMON_TASK_FAILED: Final = "daemon.task_failed"
    DAEMON_TASK_STUCK: Final = "daemon.task_stuck"
    #: SIGHUP, SIGUSR1 or SIGUSR2 arrived and was ignored (``daemon.signals``): the daemon flies on.
    DAEMON_SIGNAL_IGNORED: Final = "daemon.signal_ignored"
    #: A command ended on an exception no refusal maps (a bug): its traceback, at debug level.
    CLI_UNEXPECTED_ERROR: Final = "cli.unexpected_error"
    DAEMON_STATUS: Final = "daemon.status"
    #: The navigator core (``daemon/core.py``): started, its vision worker started, lost, back, killed
    #: for its silence, and a message from it refused.
    CORE_READY: Final = "core.ready"
    CORE_WORKER_STARTED: Final = "core.worker_started"
    CORE_WORKER_LOST: Final = "core.worker_lost"
    CORE_WORKER_BACK: Final = "core.worker_back"
    CORE_WORKER_KILLED: Final = "core.worker_killed"
    CORE_WORKER_BAD_MESSAGE: Final = "core.worker_bad_message"
    #: The worker exited 2 or 3 (a refused configuration or file): the core stops with its code.
    CORE_WORKER_REFUSED: Final = "core.worker_refused"
    #: A worker left running by the core's previous process, taken over at this core's start.
    CORE_WORKER_ADOPTED: Final = "core.worker_adopted"
    #: The worker at the rendezvous was started with another configuration or version: replaced.
    CORE_WORKER_STALE: Final = "core.worker_stale"
    #: Another user's process holds the worker's rendezvous: no adoption, a new worker is started.
    CORE_RENDEZVOUS_FOREIGN: Final = "core.rendezvous_foreign"
    CORE_STATUS: Final = "core.status"
    #: The vision worker's side: the core's handover taken, a message from the core refused, its core
    #: gone (it waits ``daemon.worker_orphan_s`` for the next), and taken over by a new core.
    WORKER_HANDOVER: Final = "worker.handover"
    WORKER_BAD_CORE_MESSAGE: Final = "worker.bad_core_message"
    WORKER_ORPHANED: Final = "worker.orphaned"
    WORKER_ADOPTED: Final = "worker.adopted"
    #: A connection at the rendezvous from another user's process, refused; the name held by another
    #: user at the worker's start (it runs without one).
    WORKER_FOREIGN_PEER: Final = "worker.foreign_peer"
    WORKER_NO_RENDEZVOUS: Final = "worker.no_rendezvous"
    CAMERA_CONNECTED: Final = "camera.connected"
    CAMERA_DISCONNECTED: Final = "camera.disconnected"
    CAMERA_FRAME_DROPPED: Final = "camera.frame_dropped"
    CAMERA_BAD_FRAME: Final = "camera.bad_frame"
    #: The camera's stamp lateness the time axis subtracts changed (clock.CameraStampOffset).
    CAMERA_STAMP_OFFSET: Final = "camera.stamp_offset"
    #: The autopilot's ground altitude at home disagrees with ``terrain.ground_alt_amsl_m`` (or agrees again).
    GROUND_ALT_DISAGREEMENT: Final = "daemon.ground_alt_disagreement"
    #: PX4's EKF2_AGP0_* parameters checked for GLOBAL_POSITION_SENSOR: the values and any problems.
    PX4_PARAMETERS: Final = "daemon.px4_parameters"
    PIPELINE_FRAME: Final = "pipeline.frame"
    PIPELINE_FIX: Final = "pipeline.fix"
    PIPELINE_FRAME_ERROR: Final = "pipeline.frame_error"
    PIPELINE_FRAME_INVALID: Final = "pipeline.frame_invalid"
    MAVLINK_CONNECTED: Final = "c8.mavlink.connected"
    MAVLINK_AUTOPILOT_SEEN: Final = "c8.mavlink.autopilot_seen"
    MAVLINK_LINK_LOST: Final = "c8.mavlink.link_lost"
    MAVLINK_SEND_ERROR: Final = "c8.mavlink.send_error"
    MAVLINK_LINK_RESTORED: Final = "c8.mavlink.link_restored"
    #: A listening link (udpin/tcpin) now writes to another address: the autopilot's valid HEARTBEAT came
    #: from there.
    MAVLINK_AUTOPILOT_ADDRESS: Final = "c8.mavlink.autopilot_address"
    #: Another address claims the autopilot's system and component ids while the autopilot's own is
    #: heard: its messages are ignored and counted (rate-limited, ``IMPOSTOR_REPORT_INTERVAL_S``).
    MAVLINK_IMPOSTOR: Final = "c8.mavlink.impostor"
    #: SET_GPS_GLOBAL_ORIGIN sent (the daemon's local frame offered to the autopilot).
    MAVLINK_ORIGIN_SENT: Final = "c8.mavlink.origin_sent"
    #: The frame VISION_POSITION_ESTIMATE is sent in changed (the autopilot reported its GPS_GLOBAL_ORIGIN).
    MAVLINK_VISION_FRAME: Final = "c8.mavlink.vision_frame"
    #: A position message (GLOBAL_POSITION_SENSOR, VISION_POSITION_ESTIMATE) is not sent for a state the
    #: daemon cannot back (``withheld`` true, with the reason), or is sent again (false). Once per change.
    MAVLINK_OUTPUT_WITHHELD: Final = "c8.mavlink.output_withheld"
    FDR_WRITE_ERROR: Final = "c13.fdr.write_error"
    FDR_SEGMENT_DELETED: Final = "c13.fdr.segment_deleted"
    #: A file named like a segment or an image that is not a regular file (FIFO, link, device): never opened.
    FDR_FILE_REFUSED: Final = "c13.fdr.file_refused"
    #: A frame image deleted (images budget or low free space; debug level).
    FDR_IMAGE_DELETED: Final = "c13.fdr.image_deleted"
    #: The recorder's health changed (ok / degraded / failing).
    FDR_HEALTH_CHANGED: Final = "c13.fdr.health_changed"
    PROVENANCE_CHANGED: Final = "c5.estimator.provenance_changed"
    ESTIMATOR_FIX_REJECTED: Final = "c5.estimator.fix_rejected"
    ESTIMATOR_INITIALISED: Final = "c5.estimator.initialised"
    #: Where the estimator started (F8: resumed, start point, or the whole map) and why.
    ESTIMATOR_PRIOR: Final = "c5.estimator.prior"
    #: A failed fix attempt counted against a start prior no map fix has confirmed, and the prior's sigma
    #: grown by it (``c5_estimator/prior_doubt.py``): the search widens until the map answers.
    PRIOR_DOUBTED: Final = "c5.estimator.prior_doubted"
    #: The first map fix accepted after the start prior was doubted: how far from the prior it was.
    PRIOR_REANCHORED: Final = "c5.estimator.prior_reanchored"
    RESUME_STATE_REFUSED: Final = "c5.resume_state.refused"
    RESUME_STATE_WRITE_FAILED: Final = "c5.resume_state.write_failed"
    ESTIMATOR_COVARIANCE_INFLATED: Final = "c5.estimator.covariance_inflated"
    ESTIMATOR_TIME_BACKWARDS: Final = "c5.estimator.time_backwards"
    ESTIMATOR_VO_REJECTED: Final = "c5.estimator.vo_rejected"
    ESTIMATOR_REACQUIRED: Final = "c5.estimator.reacquired"
    TIME_AXIS_REFUSED: Final = "c5.time_axis.refused"
    TIME_AXIS_REWOUND: Final = "c5.time_axis.rewound"
    #: The host's wall clock stepped against the daemon's (monotonic) clock; the daemon does not follow it.
    CLOCK_STEP: Final = "daemon.clock_step"
    #: Solved fixes arrive later than the time axis can still fuse them (``estimator.max_fix_delay_s``):
    #: logged (and sent as a STATUSTEXT) at the first of a run of them, with how late it was.
    FIXES_TOO_LATE: Final = "daemon.fixes_too_late"
    #: A map cell's pixels no longer match the CRC-32 the cache build recorded for it: never used.
    CACHE_TILE_CORRUPT: Final = "c6.cache.tile_corrupt"
    POSE_REJECTED: Final = "c4.pose.rejected"
    #: The fix-integrity rule refused a solved fix (reason, evidence).
    FIX_INTEGRITY_REFUSED: Final = "c4.integrity.refused"
    FIX_ATTITUDE_REFUSED: Final = "c4.attitude.refused"
    #: The VO ground-tilt check (``c1_vio/ground_tilt.py``) changed its verdict: ``refused`` is
    #: ``attitude_off`` or ``attitude_jump`` while it shows the autopilot's tilt off, null once it agrees.
    VO_ATTITUDE: Final = "c4.attitude.vo_verdict"
    VPR_READY: Final = "c2.vpr.ready"
    VPR_FAR_TOP1: Final = "c2.vpr.top1_distance_above_threshold"
    VPR_ERROR: Final = "c2.vpr.error"
    VPR_TOPK: Final = "c2.vpr.topk"
    VPR_CORPUS_WIDE: Final = "c2.vpr.corpus_wide_search"
    VPR_PRIOR_GATED: Final = "c2.vpr.prior_gated_search"
    #: Past ``vpr.corpus_wide_sigma_m`` on a map larger than the state's region: that region is swept.
    VPR_REACHABLE_SWEEP: Final = "c2.vpr.reachable_sweep"
    VPR_INDEX_BUILT: Final = "c10.cache.vpr_index_built"
    VPR_INDEX_UP_TO_DATE: Final = "c10.cache.vpr_index_up_to_date"
    #: ``gdnav cache features``: a strategy's precomputed tile features written (or already up to date).
    TILE_FEATURES_BUILT: Final = "c10.cache.tile_features_built"
    TILE_FEATURES_UP_TO_DATE: Final = "c10.cache.tile_features_up_to_date"
    #: The matcher uses the cache's precomputed tile features (which set, how many tiles).
    TILE_FEATURES_READY: Final = "c3.tile_features.ready"
    #: The cache's precomputed tile features are absent, of another extractor or damaged: extracted live.
    TILE_FEATURES_REFUSED: Final = "c3.tile_features.refused"
    #: One tile's precomputed features failed their CRC-32 on read: that tile is extracted live.
    TILE_FEATURES_CORRUPT: Final = "c3.tile_features.corrupt"
    #: The map's orientation fields for the area correlation were built, or were already up to date.
    MAP_FIELDS_BUILT: Final = "c10.cache.map_fields_built"
    MAP_FIELDS_UP_TO_DATE: Final = "c10.cache.map_fields_up_to_date"
    #: At start: the area correlation's map fields are used (with their calibration), or why not.
    MAP_FIELDS_READY: Final = "c6.map_fields.ready"
    MAP_FIELDS_REFUSED: Final = "c6.map_fields.refused"
    #: A cell of the map fields failed its CRC-32 on read: nodata for the rest of the run.
    MAP_FIELDS_CELL_CORRUPT: Final = "c6.map_fields.cell_corrupt"
    RERANK_DONE: Final = "c2_5.rerank.done"
    CACHE_OPENED: Final = "c6.cache.opened"
    CACHE_REFUSED: Final = "c6.cache.refused"
    #: A cache built before the mosaic's cell CRC table was recorded: computed at open, with the fix.
    CACHE_OLD_FORMAT: Final = "c6.cache.old_format"
    CACHE_BUILT: Final = "c10.cache.built"
    CACHE_UP_TO_DATE: Final = "c10.cache.up_to_date"
    #: The cache build's shards: on which engine, how many workers, how many shards and tiles are left.
    CACHE_BUILD_SHARDS: Final = "c10.cache.build_shards"
    #: The shards are done: wall time, the driver's share writing them, tiles per second.
    CACHE_BUILD_SHARDS_DONE: Final = "c10.cache.build_shards_done"
    #: An interrupted cache build found its journal: how many shards were done and are skipped.
    CACHE_BUILD_RESUMED: Final = "c10.cache.build_resumed"
    TILE_DOWNLOAD_STARTED: Final = "c11.download.started"
    TILE_DOWNLOAD_RETRY: Final = "c11.download.retry"
    TILE_DOWNLOAD_RATE_LIMITED: Final = "c11.download.rate_limited"
    TILE_DOWNLOAD_TILE_MISSING: Final = "c11.download.tile_missing"
    TILE_DOWNLOAD_TILE_FAILED: Final = "c11.download.tile_failed"
    TILE_DOWNLOAD_FATAL: Final = "c11.download.fatal"
    TILE_DOWNLOAD_DONE: Final = "c11.download.done"
    C3_READY: Final = "c3.matcher.ready"
    C3_AUTO_SELECTED: Final = "c3.matcher.auto_selected"
    C3_BACKBONE_ERROR: Final = "c3.matcher.backbone_error"
    C3_INSUFFICIENT_INLIERS: Final = "c3.matcher.insufficient_inliers"
    C3_RESIDUAL_ABOVE_THRESHOLD: Final = "c3.matcher.residual_above_threshold"
    C3_ZERO_INLIERS: Final = "c3.matcher.zero_inliers"
    C3_CANDIDATES: Final = "c3.matcher.candidates"
    C7_ENGINE_LOADED: Final = "c7.inference.engine_loaded"
    C7_PROVIDER_FALLBACK: Final = "c7.inference.provider_fallback"
    C7_WARMUP_SKIPPED: Final = "c7.inference.warmup_skipped"
    C7_WARMUP_FAILED: Final = "c7.inference.warmup_failed"
    #: The fault-injection test hook is armed (GDNAV_TEST_ORT_FAULT_FILE set): never in flight.
    C7_FAULT_HOOK_ARMED: Final = "c7.inference.fault_hook_armed"
    LIGHTGLUE_READY: Final = "helpers.lightglue.ready"


class IntegrityReason:
    """Why the fix-integrity rule refused a fix (``components/c4_pose/integrity.py``); recorded as
    ``no_fix_reason = "integrity:<reason>"`` and counted by reason in ``daemon.status``."""

    TOO_FEW_INLIERS: Final = "too_few_inliers"
    LOW_INLIER_RATIO: Final = "low_inlier_ratio"
    NARROW_SPREAD: Final = "narrow_spread"
    LOW_MATCH_CONFIDENCE: Final = "low_match_confidence"
    AMBIGUOUS_CANDIDATES: Final = "ambiguous_candidates"
    PRIOR_DISAGREEMENT: Final = "prior_disagreement"
    #: An area alignment's peak does not stand out of its disc (peak-to-sidelobe ratio), is too weak
    #: (normalised peak), or has a second place almost as strong.
    LOW_PSR: Final = "low_psr"
    LOW_PEAK: Final = "low_peak"
    AMBIGUOUS_PEAK: Final = "ambiguous_peak"
    #: The frame matches the map closely as a whole, but most of its patches do not fall into place: the
    #: geometry it was rectified with (the autopilot's tilt) is off.
    PATCHES_DISAGREE: Final = "patches_disagree"


class FdrKind:
    """Flight-data-recorder record kinds (the seeds' kinds where a seed defines them)."""

    CONFIG: Final = "daemon.config"
    FRAME: Final = "pipeline.frame"
    FRAME_ERROR: Final = "pipeline.frame_error"
    #: A frame refused by the time axis before any processing (future, stale, out of order).
    FRAME_REFUSED: Final = "pipeline.frame_refused"
    #: One absolute-fix attempt (VPR -> rerank -> C3 -> C4 -> C5), recorded when it finishes.
    FIX: Final = "pipeline.fix"
    #: One nav frame stored as a JPEG under ``<fdr dir>/images`` (every ``fdr.frame_jpeg_every_n``-th).
    FRAME_IMAGE: Final = "pipeline.frame_image"
    #: One estimate sent to the autopilot (the steady output stream).
    ESTIMATE_SENT: Final = "mavlink.estimate"
    #: The navigator core's vision worker: started, adopted (left running by the core's previous process),
    #: lost (how it ended), back, killed (``daemon/core.py``).
    CORE_WORKER: Final = "core.worker"
    #: The navigator core's counters once per status period: its worker, its output, its relays, the
    #: signals it survived.
    CORE_STATUS: Final = "core.status"
    #: The vision worker's side of its core: orphaned (the core gone; it waits for the next), adopted.
    WORKER_CORE: Final = "worker.core"
    PROVENANCE_CHANGED: Final = "estimator.provenance_changed"
    #: The daemon's counters once per status period (daemon.status_hz): frames, refusals, faults, link.
    STATUS: Final = "daemon.status"
    #: The start-up prior the estimator was initialised from (source, why, position, sigma).
    PRIOR: Final = "estimator.prior"
    #: The start prior doubted (its sigma grown by failed attempts on frames that should match) or, once,
    #: confirmed by the first map fix after that (``c5_estimator/prior_doubt.py``).
    PRIOR_DOUBT: Final = "estimator.prior_doubt"
    #: One journal unit of the estimator's time axis: the order of the pipeline halves, the clock and the
    #: IMU answers the estimator got (``c5_estimator.journal``; what ``gdnav replay`` plays back).
    ESTIMATOR_INPUT: Final = "estimator.input"
    MATCHER_FRAME_DONE: Final = "matcher.frame_done"
    MATCHER_BACKBONE_ERROR: Final = "matcher.backbone_error"
    MATCHER_INSUFFICIENT_INLIERS: Final = "matcher.insufficient_inliers"
    LINK_EVENT: Final = "mavlink.link_event"
    #: The recorder opened (first record of every daemon run): pid, start time, torn lines recovered.
    FDR_OPENED: Final = "fdr.opened"
    #: The recorder closed cleanly (last record of a run); a run without it ended in a crash.
    FDR_CLOSED: Final = "fdr.closed"
    #: The host's wall clock stepped against the daemon's clock (detected, recorded, not followed).
    CLOCK_STEP: Final = "daemon.clock_step"
    #: The camera's measured stamp lateness, each time the correction the time axis applies changes.
    CAMERA_STAMP_OFFSET: Final = "camera.stamp_offset"
    #: The autopilot's ground altitude started or stopped disagreeing with the daemon's.
    GROUND_ALT_CHECK: Final = "daemon.ground_alt_check"
    #: PX4's aux-global-position parameters read back and checked (``c8_mavlink.px4_params``).
    PX4_PARAMETERS: Final = "daemon.px4_parameters"
    #: A map tile failed its digest on read (corrupted after the cache was verified): masked, never used.
    TILE_CORRUPT: Final = "cache.tile_corrupt"
    #: At start: whether the learned matcher uses the cache's precomputed tile features, or why not.
    TILE_FEATURES: Final = "cache.tile_features"
    #: One tile's precomputed features failed their CRC-32 on read: never used again, extracted live.
    TILE_FEATURES_CORRUPT: Final = "cache.tile_features_corrupt"
    #: At start: whether the area correlation uses the cache's map fields (and their calibration), or why not.
    MAP_FIELDS: Final = "cache.map_fields"
    #: A cell of the map fields failed its CRC-32 on read: nodata for the rest of the run.
    MAP_FIELDS_CORRUPT: Final = "cache.map_fields_corrupt"
