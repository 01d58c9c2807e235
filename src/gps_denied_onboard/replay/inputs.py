"""What a replay reads: frames with the vehicle state at their exposure, a start prior, optional truth,
and (from an FDR) the estimator's journal.

Three sources, each turned into one :class:`ReplayInput`:

- :func:`from_fdr`: the daemon's own flight data recorder (one run). Frames are the recorded frame images
  (``fdr.frames_format: png`` with ``fdr.frame_jpeg_every_n: 1`` for an exact replay), each with the
  attitude and height it was tracked with (``pipeline.frame``); the prior is ``estimator.prior``; the
  journal is the run's ``estimator.input`` units; the config is the run's ``daemon.config``.
- :func:`from_csv`: an image directory plus a CSV with one row per image (file name, position,
  attitude, and a time or the image's EXIF time).
- :func:`from_tlog`: a MAVLink telemetry log (``.tlog`` or ``.bin``, read by pymavlink) plus a video or an
  image directory; attitude and height are interpolated from the log to each frame's time.

Every refusal is an :class:`ReplayInputError` naming the file and what was expected (``gdnav replay``
exits 2 for arguments, 3 for an input file it cannot use).
"""

from __future__ import annotations

import bisect
import contextlib
import csv
import dataclasses
import datetime as _dt
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from gps_denied_onboard.camera.types import Attitude, CameraCalibration, FrameTiming
from gps_denied_onboard.components.c5_estimator.prior import InitialPrior
from gps_denied_onboard.components.c5_estimator.wire import WireError, state_from_wire
from gps_denied_onboard.constants import FdrKind

#: Image file suffixes read from a directory (case-insensitive).
IMAGE_SUFFIXES: Final = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp"})
#: CSV column names accepted for each field (case-insensitive), first match wins.
CSV_COLUMNS: Final[dict[str, tuple[str, ...]]] = {
    "file": ("file", "filename", "image", "name"),
    "time": ("time_unix_s", "timestamp", "time"),
    "lat": ("lat_deg", "latitude", "lat"),
    "lon": ("lon_deg", "longitude", "lon"),
    "alt_amsl": ("alt_amsl_m", "altitude_amsl", "alt_amsl"),
    "alt_agl": ("alt_agl_m", "altitude_agl", "alt_agl"),
    "roll": ("roll_deg", "roll"),
    "pitch": ("pitch_deg", "pitch"),
    "yaw": ("yaw_deg", "heading_deg", "heading", "yaw"),
}


class ReplayInputError(ValueError):
    """An input cannot be used. ``resource``: True for a refused file (exit 3), False for bad arguments
    (exit 2)."""

    def __init__(self, message: str, *, resource: bool = True) -> None:
        super().__init__(message)
        self.resource = resource


@dataclass(frozen=True)
class ReplayFrame:
    """One frame to replay: ``load()`` gives the image exactly as the pipeline gets it."""

    seq: int
    exposure_time_unix_usec: int
    attitude: Attitude | None
    alt_agl_m: float | None
    load: Callable[[], np.ndarray] = field(repr=False, compare=False)
    name: str = ""
    #: How well its exposure time was known, as the daemon had it (None from logs without it).
    timing: FrameTiming | None = None


@dataclass(frozen=True)
class TruthSample:
    time_unix_s: float
    lat_deg: float
    lon_deg: float


@dataclass
class ReplayInput:
    source: str
    frames: list[ReplayFrame]
    prior: InitialPrior | None
    #: Truth, in time order (empty when unknown).
    truth: list[TruthSample] = field(default_factory=list)
    #: The recorded ``estimator.input`` units (FDR only), in recording order.
    journal: list[dict[str, Any]] = field(default_factory=list)
    #: The recorded per-frame records (FDR only), by frame seq: what the replay is compared with.
    recorded_frames: dict[int, dict[str, Any]] = field(default_factory=dict)
    #: The daemon's config as recorded (FDR only).
    recorded_config: dict[str, Any] | None = None
    #: sha256 of the map cache's manifest as recorded at the run's start (FDR only; None: not recorded).
    recorded_cache_manifest_sha256: str | None = None
    #: A calibration the source brings (EXIF), or None: the config's.
    calibration: CameraCalibration | None = None
    #: Ground height AMSL the source implies (None: the config's ``terrain.ground_alt_amsl_m``).
    ground_alt_amsl_m: float | None = None
    #: Why an exact replay is not possible (FDR only; empty: it is).
    not_exact: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def truth_at(self, t_unix_s: float) -> tuple[float, float]:
        """Truth linearly interpolated in time (held at the ends)."""
        ts = [s.time_unix_s for s in self.truth]
        i = bisect.bisect_left(ts, t_unix_s)
        if i <= 0:
            return self.truth[0].lat_deg, self.truth[0].lon_deg
        if i >= len(ts):
            return self.truth[-1].lat_deg, self.truth[-1].lon_deg
        a, b = self.truth[i - 1], self.truth[i]
        w = (t_unix_s - a.time_unix_s) / max(b.time_unix_s - a.time_unix_s, 1e-9)
        return a.lat_deg + w * (b.lat_deg - a.lat_deg), a.lon_deg + w * (b.lon_deg - a.lon_deg)


def _read_image(path: Path, scale: float) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        import cv2

        try:
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        except cv2.error as exc:  # e.g. more pixels than OpenCV's decoder limit
            why = " ".join(str(exc).split())
            raise ReplayInputError(f"{path}: not an image OpenCV can read ({why})") from exc
        if img is None or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
            raise ReplayInputError(f"{path}: not an image OpenCV can read")
        if img.dtype == np.uint16:
            img = np.right_shift(img, 8).astype(np.uint8)
        elif img.dtype != np.uint8:
            raise ReplayInputError(f"{path}: {img.dtype} pixels; expected 8- or 16-bit")
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        if scale != 1.0:
            img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(img)

    return load


# -- the daemon's FDR ----------------------------------------------------------------------------------


#: FDR kinds a replay reads (``fdr.opened`` marks where a run starts).
_FDR_KINDS: Final = (
    FdrKind.FDR_OPENED,
    FdrKind.CONFIG,
    FdrKind.PRIOR,
    FdrKind.FRAME,
    FdrKind.FRAME_IMAGE,
    FdrKind.ESTIMATOR_INPUT,
)


def from_fdr(path: Path, *, run: int | None = None) -> ReplayInput:
    """One run of the FDR at ``path`` (default: the last run that tracked frames). A record whose fields
    are not what the daemon writes (damage, or another program's file) is a ``ReplayInputError``."""
    try:
        return _from_fdr(path, run=run)
    except ReplayInputError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
        what = " ".join(f"{type(exc).__name__}: {exc}".split())[:200]
        raise ReplayInputError(f"{path}: a record is not what the daemon writes ({what})") from exc


def _from_fdr(path: Path, *, run: int | None) -> ReplayInput:
    from gps_denied_onboard.components.c13_fdr.reader import FdrReader, FdrReadError, split_runs

    reader = FdrReader(path)
    try:
        # Only the kinds a replay uses (the estimate stream and status records are most of a recorder).
        runs = split_runs(reader.records(*_FDR_KINDS))
    except FdrReadError as exc:
        raise ReplayInputError(str(exc)) from exc
    if not runs:
        raise ReplayInputError(f"{path}: no FDR records")
    with_frames = [i for i, r in enumerate(runs) if any(x.get("kind") == FdrKind.FRAME for x in r)]
    if run is None:
        if not with_frames:
            raise ReplayInputError(f"{path}: no run tracked any frame (no pipeline.frame records)")
        run = with_frames[-1]
    if not 0 <= run < len(runs):
        raise ReplayInputError(f"--run {run}: the FDR has runs 0..{len(runs) - 1}", resource=False)
    recs = runs[run]
    fdr_dir = path if path.is_dir() else path.parent
    frames_rec = [r for r in recs if r.get("kind") == FdrKind.FRAME]
    if frames_rec and "attitude_rad" not in frames_rec[0]:
        raise ReplayInputError(
            f"{path}: run {run} was recorded without per-frame attitude (a daemon older than gdnav replay); "
            "it cannot be replayed"
        )
    images = {int(r["exposure_time_unix_usec"]): r for r in recs if r.get("kind") == FdrKind.FRAME_IMAGE}
    config_rec = next((r for r in recs if r.get("kind") == FdrKind.CONFIG), None)
    prior_rec = next((r for r in recs if r.get("kind") == FdrKind.PRIOR), None)
    # In unit order (``n``): each record is written after the axis' lock is released.
    journal = sorted(
        (r for r in recs if r.get("kind") == FdrKind.ESTIMATOR_INPUT), key=lambda r: int(r.get("n", 0))
    )
    not_exact: list[str] = []
    frames: list[ReplayFrame] = []
    missing = lossy = 0
    for r in frames_rec:
        t = int(r["exposure_time_unix_usec"])
        img = images.get(t)
        if img is None or not (fdr_dir / str(img["file"])).is_file():
            missing += 1
            continue
        if not str(img["file"]).endswith(".png"):
            lossy += 1
        att = r.get("attitude_rad")
        frames.append(
            ReplayFrame(
                int(r["frame_seq"]),
                t,
                Attitude(*(float(v) for v in att)) if att is not None else None,
                float(r["alt_agl_m"]) if r.get("alt_agl_m") is not None else None,
                _read_image(fdr_dir / str(img["file"]), 1.0),
                str(img["file"]),
                _frame_timing(r.get("timing")),
            )
        )
    if not frames:
        raise ReplayInputError(
            f"{path}: run {run} has {len(frames_rec)} tracked frames and none of their images; record them "
            "with fdr.frame_jpeg_every_n (and fdr.frames_format: png for an exact replay)"
        )
    notes: list[str] = []
    if missing:
        # An exact replay still runs up to the first unit whose frame has no image (a run killed between a
        # frame's record and its image loses the last one; the images budget deletes the oldest).
        notes.append(f"{missing} of {len(frames_rec)} tracked frames have no image in the FDR")
    first_track = next((u for u in journal if u.get("unit") == "track"), None)
    have = {f.exposure_time_unix_usec for f in frames}
    if first_track is not None and int(first_track["time_unix_usec"]) not in have:
        not_exact.append("the run's first frame has no image (deleted by the images budget or low disk)")
    if lossy:
        not_exact.append(f"{lossy} frame images are JPEG (lossy); fdr.frames_format: png is needed")
    if not journal:
        not_exact.append("no estimator.input journal (recorded by a daemon older than gdnav replay)")
    if config_rec is None:
        not_exact.append("no daemon.config record in this run")
    prior = None
    if prior_rec is not None:
        prior = InitialPrior(
            float(prior_rec["lat_deg"]),
            float(prior_rec["lon_deg"]),
            float(prior_rec["sigma_m"]),
            str(prior_rec.get("source", "fdr")),
            str(prior_rec.get("why", "")),
            confirmed=bool(prior_rec.get("confirmed", False)),  # as the run started (issue 37)
        )
        if prior_rec.get("handover") is not None:  # a vision worker that started from its core's filter
            try:
                handover = state_from_wire(prior_rec["handover"]).checkpoint
            except WireError as exc:
                raise ReplayInputError(f"{path}: run {run}: the prior's handover state: {exc}") from exc
            prior = dataclasses.replace(prior, handover=handover)
    t_first = frames[0].exposure_time_unix_usec
    first = next(r for r in frames_rec if int(r["exposure_time_unix_usec"]) == t_first)
    skipped = frames_rec[: frames_rec.index(first)]
    if any(r.get("lat_deg") is not None for r in skipped):
        # The run was estimating before its first frame with an image, and the vehicle has moved on from
        # where the start prior put it (measured: 490 m after 63 frames; the replay then held a 30 m sigma
        # 490 m off and refused every right fix against it). Start from what the run estimated there.
        # (A run that had no estimate yet started from the start prior at or after this frame.)
        if first.get("lat_deg") is None or first.get("horiz_sigma_m") is None:
            raise ReplayInputError(
                f"{path}: run {run}'s first {len(skipped)} tracked frames have no image and the run had "
                f"no estimate at the first that has one (frame {first['frame_seq']}): there is no start "
                "prior to replay from"
            )
        prior = InitialPrior(
            float(first["lat_deg"]),
            float(first["lon_deg"]),
            float(first["horiz_sigma_m"]),
            "fdr_estimate",
            f"the run's estimate at frame {first['frame_seq']}, the first with an image",
            confirmed=True,  # the run's own estimate, as a resumed one is (c5_estimator/prior.py)
        )
        notes.append(
            f"the replay starts at frame {first['frame_seq']} from the run's estimate there "
            f"(sigma {float(first['horiz_sigma_m']):.1f} m), not from the run's start prior"
        )
    return ReplayInput(
        source=f"fdr:{path}#run{run}",
        frames=frames,
        prior=prior,
        journal=journal,
        recorded_frames={int(r["frame_seq"]): r for r in frames_rec},
        recorded_config=dict(config_rec["config"]) if config_rec is not None else None,
        recorded_cache_manifest_sha256=config_rec.get("cache_manifest_sha256")
        if config_rec is not None
        else None,
        not_exact=not_exact,
        notes=notes,
    )


# -- image directory + CSV -----------------------------------------------------------------------------


def _column(header: Sequence[str], name: str) -> str | None:
    lower = {h.strip().lower(): h for h in header}
    return next((lower[c] for c in CSV_COLUMNS[name] if c in lower), None)


def _parse_time(raw: str, where: str) -> float:
    raw = raw.strip()
    try:
        t_s = float(raw)
    except ValueError:
        pass
    else:
        if not math.isfinite(t_s):
            raise ReplayInputError(f"{where}: time {raw[:40]!r} is not a finite number of seconds")
        return t_s
    try:
        t = _dt.datetime.fromisoformat(raw.replace("Z", "+00:00"))
    except ValueError as exc:
        raise ReplayInputError(f"{where}: time {raw!r} is neither Unix seconds nor ISO 8601") from exc
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.timezone.utc)
    return t.timestamp()


def exif_time_unix_s(path: Path) -> float | None:
    """The image's EXIF DateTimeOriginal (+ SubSecTimeOriginal, + OffsetTimeOriginal when present; read
    as UTC when the zone is not recorded: a replay only needs the intervals), or None."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif().get_ifd(0x8769)
    except OSError:
        return None
    raw = exif.get(36867)  # DateTimeOriginal
    if not raw:
        return None
    try:
        t = _dt.datetime.strptime(str(raw).strip(), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    offset = exif.get(36881)  # OffsetTimeOriginal, "+09:00"
    tz = _dt.timezone.utc
    if offset:
        with contextlib.suppress(ValueError):
            tz = _dt.datetime.strptime(str(offset).strip(), "%z").tzinfo or tz  # type: ignore[assignment]
    sub = str(exif.get(37521) or "").strip()  # SubSecTimeOriginal
    frac = float(f"0.{sub}") if sub.isdigit() else 0.0
    return t.replace(tzinfo=tz).timestamp() + frac


def calibration_from_exif(path: Path, *, scale: float = 1.0) -> CameraCalibration:
    """A pinhole calibration from the image's EXIF: fx = FocalLength (mm) x FocalPlaneXResolution (px per
    unit), fy likewise, the principal point at the centre, no distortion. Not a calibration (no
    distortion model, nominal focal length): good enough for VO, stated as such in the report."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            width, height = im.size
            exif = im.getexif().get_ifd(0x8769)
    except OSError as exc:
        raise ReplayInputError(f"{path}: cannot read its EXIF: {exc}") from exc
    focal_mm = exif.get(37386)  # FocalLength
    xres, yres, unit = exif.get(41486), exif.get(41487), exif.get(41488)  # FocalPlane X/Y resolution, unit
    mm_per_unit = {2: 25.4, 3: 10.0, 4: 1.0}.get(int(unit) if unit is not None else 2)
    if not focal_mm or not xres or mm_per_unit is None:
        raise ReplayInputError(
            f"{path}: EXIF has no FocalLength/FocalPlaneXResolution to derive a calibration from; "
            "pass --calibration FILE"
        )
    fx = float(focal_mm) * float(xres) / mm_per_unit * scale
    fy = float(focal_mm) * float(yres or xres) / mm_per_unit * scale
    w, h = round(width * scale), round(height * scale)
    return CameraCalibration(w, h, fx, fy, (w - 1) / 2.0, (h - 1) / 2.0, ())


def from_csv(
    images_dir: Path,
    csv_path: Path,
    *,
    ground_alt_amsl_m: float | None,
    image_scale: float = 1.0,
    prior_sigma_m: float,
) -> ReplayInput:
    """An image directory and a CSV with one row per image (columns: ``CSV_COLUMNS``). Heights: an
    ``alt_agl_m`` column, or ``alt_amsl`` minus ``ground_alt_amsl_m``. Times: a time column, or each
    image's EXIF DateTimeOriginal. The CSV's positions are the truth; its first row, with
    ``prior_sigma_m``, is the start prior (the operator's start point)."""
    if not images_dir.is_dir():
        raise ReplayInputError(f"{images_dir}: not a directory of images", resource=False)
    try:
        text = csv_path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ReplayInputError(f"{csv_path}: cannot be read as UTF-8 text: {exc}") from exc
    try:
        reader = csv.DictReader(text.splitlines())
        header = reader.fieldnames or []
        records = list(reader)
    except csv.Error as exc:  # e.g. a field over the csv module's limit
        raise ReplayInputError(f"{csv_path}: not readable as CSV: {exc}") from exc
    cols = {k: _column(header, k) for k in CSV_COLUMNS}
    for need in ("file", "lat", "lon"):
        if cols[need] is None:
            raise ReplayInputError(
                f"{csv_path}: no {need} column (expected one of {', '.join(CSV_COLUMNS[need])}); "
                f"header is {', '.join(header) or 'empty'}"
            )
    if cols["alt_agl"] is None and (cols["alt_amsl"] is None or ground_alt_amsl_m is None):
        raise ReplayInputError(
            f"{csv_path}: no height above ground: give an alt_agl_m column, or an altitude_amsl column and "
            "--ground-alt-amsl M",
            resource=cols["alt_amsl"] is None,
        )
    rows: list[tuple[float, ReplayFrame, TruthSample]] = []
    notes: list[str] = []
    exif_times = 0
    for lineno, row in enumerate(records, start=2):
        where = f"{csv_path}:{lineno}"

        def num(key: str, *, row: Mapping[str, str] = row, where: str = where) -> float | None:
            col = cols[key]
            if col is None or not str(row.get(col) or "").strip():
                return None
            try:
                v = float(str(row[col]))
            except ValueError as exc:
                raise ReplayInputError(f"{where}: {col} {row[col]!r} is not a number") from exc
            if not math.isfinite(v):
                raise ReplayInputError(f"{where}: {col} is not finite")
            return v

        name = str(row.get(cols["file"] or "") or "").strip()
        path = images_dir / name
        try:
            found = bool(name) and path.is_file()
        except OSError:  # e.g. a name longer than the file system allows
            found = False
        if not found:
            raise ReplayInputError(f"{where}: image {name[:80]!r} not found in {images_dir}")
        lat, lon = num("lat"), num("lon")
        if lat is None or lon is None or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise ReplayInputError(f"{where}: latitude/longitude missing or out of range")
        if cols["time"] is not None and str(row.get(cols["time"]) or "").strip():
            t_s = _parse_time(str(row[cols["time"]]), where)
        else:
            exif_t = exif_time_unix_s(path)
            if exif_t is None:
                raise ReplayInputError(f"{where}: no time column and {name} has no EXIF DateTimeOriginal")
            t_s = exif_t
            exif_times += 1
        agl = num("alt_agl")
        if agl is None:
            amsl = num("alt_amsl")
            agl = None if amsl is None or ground_alt_amsl_m is None else amsl - ground_alt_amsl_m
        roll, pitch, yaw = num("roll"), num("pitch"), num("yaw")
        att = (
            Attitude(math.radians(roll), math.radians(pitch), math.radians(yaw))
            if roll is not None and pitch is not None and yaw is not None
            else None
        )
        t_usec = round(t_s * 1e6)
        frame = ReplayFrame(0, t_usec, att, agl, _read_image(path, image_scale), name)
        rows.append((t_s, frame, TruthSample(t_s, lat, lon)))
    if not rows:
        raise ReplayInputError(f"{csv_path}: no rows")
    rows.sort(key=lambda r: r[0])
    if exif_times:
        notes.append(
            f"{exif_times} frame times from EXIF DateTimeOriginal (1 s resolution, time zone not recorded)"
        )
    frames = [
        ReplayFrame(i, f.exposure_time_unix_usec, f.attitude, f.alt_agl_m, f.load, f.name)
        for i, (_, f, _) in enumerate(rows)
    ]
    first = rows[0][2]
    return ReplayInput(
        source=f"csv:{csv_path}",
        frames=frames,
        prior=InitialPrior(
            first.lat_deg,
            first.lon_deg,
            prior_sigma_m,
            "csv_first_row",
            "the CSV's first position (start point)",
        ),
        truth=[r[2] for r in rows],
        ground_alt_amsl_m=ground_alt_amsl_m,
        notes=notes,
    )


# -- MAVLink telemetry log -----------------------------------------------------------------------------


@dataclass
class _Series:
    t: list[float] = field(default_factory=list)
    v: list[tuple[float, ...]] = field(default_factory=list)

    def at(self, t_s: float, max_gap_s: float) -> tuple[float, ...] | None:
        """Linear interpolation between the samples around ``t_s`` (None beyond ``max_gap_s`` of one)."""
        i = bisect.bisect_left(self.t, t_s)
        if i < len(self.t) and self.t[i] == t_s:
            return self.v[i]
        if i == 0 or i >= len(self.t):
            j = 0 if i == 0 else len(self.t) - 1
            return self.v[j] if self.t and abs(self.t[j] - t_s) <= max_gap_s else None
        t0, t1 = self.t[i - 1], self.t[i]
        if t1 - t0 > 2 * max_gap_s:
            return None
        w = (t_s - t0) / (t1 - t0)
        return tuple(a + w * (b - a) for a, b in zip(self.v[i - 1], self.v[i], strict=True))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class TelemetryLog:
    """What a replay takes from a MAVLink log, on the Unix time axis (s)."""

    attitude: _Series
    position: _Series  # lat_deg, lon_deg, relative_alt_m
    start_unix_s: float
    end_unix_s: float
    home: tuple[float, float] | None


#: Messages read from a MAVLink telemetry log (.tlog).
_TLOG_TYPES: Final = ("ATTITUDE", "GLOBAL_POSITION_INT", "SYSTEM_TIME", "HOME_POSITION")
#: Messages read from an ArduPilot DataFlash log (.bin): attitude and position.
_BIN_TYPES: Final = ("ATT", "POS")


def read_telemetry_log(path: Path) -> TelemetryLog:
    """Attitude and position from a ``.tlog`` (ATTITUDE, GLOBAL_POSITION_INT, HOME_POSITION) or a DataFlash
    ``.bin`` (ATT, POS) log, on the Unix time axis: a .tlog message's ``time_boot_ms`` mapped through
    SYSTEM_TIME when the log has it, else the log's receive timestamps; a .bin message's time from
    pymavlink's log clock (GPS week/ms when the log has a GPS time, else time since boot)."""
    from pymavlink import mavutil

    if not path.is_file():
        raise ReplayInputError(f"{path}: telemetry log not found")
    try:
        conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
    except Exception as exc:  # pymavlink raises plain Exceptions for unreadable logs
        raise ReplayInputError(f"{path}: pymavlink cannot open it: {exc}") from exc
    att_raw: list[tuple[float, int | None, tuple[float, ...]]] = []
    pos_raw: list[tuple[float, int | None, tuple[float, ...]]] = []
    offsets: list[float] = []
    home = None
    times: list[float] = []
    try:
        while True:
            msg = conn.recv_match(type=[*_TLOG_TYPES, *_BIN_TYPES])
            if msg is None:
                break
            ts = float(getattr(msg, "_timestamp", 0.0) or 0.0)
            times.append(ts)
            mtype = msg.get_type()
            boot = getattr(msg, "time_boot_ms", None)
            if mtype == "SYSTEM_TIME" and msg.time_unix_usec > 0 and msg.time_boot_ms > 0:
                offsets.append(msg.time_unix_usec / 1e6 - msg.time_boot_ms / 1e3)
            elif mtype == "ATTITUDE":
                att_raw.append((ts, boot, (msg.roll, msg.pitch, msg.yaw)))
            elif mtype == "GLOBAL_POSITION_INT":
                pos_raw.append((ts, boot, (msg.lat / 1e7, msg.lon / 1e7, msg.relative_alt / 1e3)))
            elif mtype == "HOME_POSITION":
                home = (msg.latitude / 1e7, msg.longitude / 1e7)
            elif mtype == "ATT":  # DataFlash (.bin): degrees; time from pymavlink's log clock
                att_raw.append(
                    (ts, None, (math.radians(msg.Roll), math.radians(msg.Pitch), math.radians(msg.Yaw)))
                )
            elif mtype == "POS":  # DataFlash: degrees, height above home in m
                pos_raw.append((ts, None, (float(msg.Lat), float(msg.Lng), float(msg.RelHomeAlt))))
    finally:
        conn.close()
    if not att_raw or not pos_raw:
        raise ReplayInputError(
            f"{path}: needs ATTITUDE and GLOBAL_POSITION_INT messages (ATT and POS in a .bin log); "
            f"found {len(att_raw)} and {len(pos_raw)}"
        )
    offset = float(np.median(offsets)) if offsets else None

    def series(raw: list[tuple[float, int | None, tuple[float, ...]]]) -> _Series:
        s = _Series()
        for ts, boot, v in sorted(
            raw, key=lambda r: (r[1] / 1e3 + offset) if (offset is not None and r[1] is not None) else r[0]
        ):
            t = boot / 1e3 + offset if (offset is not None and boot is not None) else ts
            if s.t and t <= s.t[-1]:
                continue
            s.t.append(t)
            s.v.append(v)
        return s

    att, pos = series(att_raw), series(pos_raw)
    return TelemetryLog(att, pos, min(att.t[0], pos.t[0]), max(att.t[-1], pos.t[-1]), home)


def from_tlog(
    log_path: Path,
    *,
    images_dir: Path | None,
    video: Path | None,
    frame_times_csv: Path | None,
    video_start_unix_s: float | None,
    image_scale: float,
    prior_sigma_m: float,
    max_state_gap_s: float = 0.5,
) -> ReplayInput:
    """A telemetry log plus frames. Frame times: a video's own timestamps from ``video_start_unix_s``
    (default: the log's first message); an image directory's from ``frame_times_csv`` (file,
    time_unix_s) or from EXIF. The log's GLOBAL_POSITION_INT is the truth and gives the prior (its
    position at the first frame, ``prior_sigma_m``); HOME_POSITION is not used for it (the log's
    position at the first frame is closer)."""
    if (images_dir is None) == (video is None):
        raise ReplayInputError(
            "a telemetry log needs exactly one of --images DIR or --video FILE", resource=False
        )
    tlog = read_telemetry_log(log_path)
    timed: list[tuple[float, str, Callable[[], np.ndarray]]] = []
    notes: list[str] = []
    if video is not None:
        timed = _video_frames(
            video, video_start_unix_s if video_start_unix_s is not None else tlog.start_unix_s, image_scale
        )
    else:
        assert images_dir is not None
        if not images_dir.is_dir():
            raise ReplayInputError(f"{images_dir}: not a directory of images", resource=False)
        files = sorted(p for p in images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise ReplayInputError(f"{images_dir}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        given: dict[str, float] = {}
        if frame_times_csv is not None:
            try:
                rows = list(csv.DictReader(frame_times_csv.read_text(encoding="utf-8-sig").splitlines()))
            except (OSError, UnicodeDecodeError, csv.Error) as exc:
                raise ReplayInputError(f"{frame_times_csv}: cannot be read: {exc}") from exc
            for i, row in enumerate(rows, start=2):
                fcol, tcol = _column(list(row), "file"), _column(list(row), "time")
                if fcol is None or tcol is None:
                    raise ReplayInputError(f"{frame_times_csv}: needs a file and a time_unix_s column")
                given[str(row[fcol]).strip()] = _parse_time(str(row[tcol]), f"{frame_times_csv}:{i}")
        for p in files:
            t = given.get(p.name) if given else exif_time_unix_s(p)
            if t is None:
                raise ReplayInputError(
                    f"{p}: no time for this image "
                    f"({'not in ' + str(frame_times_csv) if given else 'no EXIF time'})"
                )
            timed.append((t, p.name, _read_image(p, image_scale)))
    timed.sort(key=lambda r: r[0])
    frames: list[ReplayFrame] = []
    outside = 0
    for t, name, load in timed:
        if not tlog.start_unix_s <= t <= tlog.end_unix_s:
            outside += 1
            continue
        a = tlog.attitude.at(t, max_state_gap_s)
        pos = tlog.position.at(t, max_state_gap_s)
        att = None
        if a is not None:
            att = Attitude(a[0], a[1], _wrap(a[2]))
        frames.append(
            ReplayFrame(len(frames), round(t * 1e6), att, pos[2] if pos is not None else None, load, name)
        )
    if outside:
        notes.append(f"{outside} frames outside the log's time span were left out")
    if not frames:
        raise ReplayInputError(
            f"{log_path}: no frame falls inside the log's time span "
            f"({tlog.start_unix_s:.3f}..{tlog.end_unix_s:.3f} Unix s)"
        )
    truth = [TruthSample(t, v[0], v[1]) for t, v in zip(tlog.position.t, tlog.position.v, strict=True)]
    first = tlog.position.at(frames[0].exposure_time_unix_usec / 1e6, max_state_gap_s) or tlog.position.v[0]
    return ReplayInput(
        source=f"tlog:{log_path}",
        frames=frames,
        prior=InitialPrior(
            first[0],
            first[1],
            prior_sigma_m,
            "tlog_position",
            "the log's GLOBAL_POSITION_INT at the first frame",
        ),
        truth=truth,
        notes=notes,
    )


class _VideoReader:
    """Decodes a video's frames on demand, in order (a seek only when asked out of order)."""

    def __init__(self, video: Path, scale: float) -> None:
        import cv2

        self._cap = cv2.VideoCapture(str(video))
        self._next = 0
        self._scale = scale
        self.path = video

    def opened(self) -> bool:
        return bool(self._cap.isOpened())

    def get(self, i: int) -> np.ndarray:
        import cv2

        if i != self._next:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        ok, img = self._cap.read()
        self._next = i + 1
        if not ok:
            raise ReplayInputError(f"{self.path}: frame {i} cannot be decoded")
        if self._scale != 1.0:
            img = cv2.resize(img, None, fx=self._scale, fy=self._scale, interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(img)


def _video_frames(
    video: Path, start_unix_s: float, scale: float
) -> list[tuple[float, str, Callable[[], np.ndarray]]]:
    """The frames of ``video`` stamped ``start + index / fps`` (decoded when the replay gets to them)."""
    import cv2

    if not video.is_file():
        raise ReplayInputError(f"{video}: video not found")
    reader = _VideoReader(video, scale)
    if not reader.opened():
        raise ReplayInputError(f"{video}: OpenCV cannot open this video")
    fps = float(reader._cap.get(cv2.CAP_PROP_FPS) or 0.0)
    count = int(reader._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    if fps <= 0 or count <= 0:
        raise ReplayInputError(f"{video}: the video reports no frame rate or frame count")

    def loader(i: int) -> Callable[[], np.ndarray]:
        def load() -> np.ndarray:
            return reader.get(i)

        return load

    return [(start_unix_s + i / fps, f"{video.name}#{i}", loader(i)) for i in range(count)]


def _frame_timing(fields: object) -> FrameTiming | None:
    """A ``pipeline.frame`` record's ``timing`` (``FrameTiming`` as the daemon had it), or None when the
    record has none or it is malformed."""
    if not isinstance(fields, dict):
        return None
    try:
        rate = fields["down_rate_cam_rad_s"]
        return FrameTiming(
            (float(rate[0]), float(rate[1])),
            float(fields["stamp_offset_s"]),
            float(fields["sigma_s"]),
            float(fields.get("ahrs_sigma_rad", 0.0)),
        )
    except (KeyError, TypeError, ValueError, IndexError):
        return None
