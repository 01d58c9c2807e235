"""``gdnav match IMAGE_A IMAGE_B``: run a C3 strategy on two images through the daemon's own code.

IMAGE_A plays the nav frame (no attitude: not rectified), IMAGE_B the map chip of the single rerank
candidate; the strategy is built by the C3 registry exactly as the composition root builds it. Prints
the inlier count, the median residual, the homography A px -> B px and the time per stage; ``--json``
prints the same as one JSON object. Exit codes: 0 matched; 1 no match (too few inliers); 2 bad input
(missing or unreadable image, missing or refused model), one clear line on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np

from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher.base import NULL_FDR
from gps_denied_onboard.components.c3_matcher.errors import InsufficientInliersError
from gps_denied_onboard.components.c6_tiles.types import TileId

EXIT_OK: Final[int] = 0
EXIT_NO_MATCH: Final[int] = 1
EXIT_BAD_INPUT: Final[int] = 2
STRATEGIES: Final[tuple[str, ...]] = ("classical", "disk_lightglue", "aliked_lightglue", "xfeat", "xfeat_mnn")
#: Horizontal field of view given to IMAGE_A's calibration; unused without attitude (no rectification).
_NOMINAL_HFOV_DEG: Final[float] = 70.0


class MatchCliError(ValueError):
    """Bad input for ``gdnav match`` (reported as one line, exit 2)."""


class ImageChip:
    """In-memory ``TilePixelsHandle`` for an image that is not part of a tile cache.

    Pixel (x, y) is given the pseudo coordinates lon = (x + x0) * 1e-6, lat = -(y + y0) * 1e-6 deg with
    ``origin_px`` = (x0, y0): the matcher only uses them (and the tile id) to key its tile-feature cache,
    so chips cut at different origins of one image must be given their origins. Nothing here turns them
    into a position.
    """

    def __init__(
        self, image_bgr: np.ndarray, gsd_m_px: float = 1.0, origin_px: tuple[float, float] = (0.0, 0.0)
    ) -> None:
        view = image_bgr.view()
        view.setflags(write=False)
        self._pixels = view
        self._gsd = float(gsd_m_px)
        self._x0, self._y0 = float(origin_px[0]), float(origin_px[1])
        self._tile_id = TileId.of(0, -self._y0 * 1e-6, self._x0 * 1e-6)

    @property
    def tile_id(self) -> TileId:
        return self._tile_id

    @property
    def gsd_m_px(self) -> float:
        return self._gsd

    def pixels(self) -> np.ndarray:
        return self._pixels

    def chip_px_to_lonlat(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return (p[:, 0] + self._x0) * 1e-6, (p[:, 1] + self._y0) * -1e-6

    def lonlat_to_chip_px(self, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
        return np.column_stack(
            [np.asarray(lon_deg) / 1e-6 - self._x0, np.asarray(lat_deg) / -1e-6 - self._y0]
        )


@dataclass(frozen=True)
class PairMatch:
    """Outcome of matching A to B.

    ``correspondences``: (I, 4) float32 (x_a, y_a, x_b, y_b) original-image px of the RANSAC inliers;
    ``homography``: (3, 3) float64 A px -> B px (None without a match); ``rotation_deg``: rotation of A
    that gave the best result (counter-clockwise, image centre); ``timings_ms``: stage -> ms (summed
    over rotations).
    """

    strategy: str
    inliers: int
    residual_px: float
    homography: np.ndarray | None
    correspondences: np.ndarray
    rotation_deg: float
    timings_ms: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {
            "strategy": self.strategy,
            "inliers": self.inliers,
            "residual_px": None if math.isinf(self.residual_px) else round(self.residual_px, 4),
            "homography": None if self.homography is None else self.homography.tolist(),
            "rotation_deg": self.rotation_deg,
            "timings_ms": {k: round(v, 2) for k, v in self.timings_ms.items()},
        }


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 BGR of an image file; ``MatchCliError`` when missing or unreadable."""
    if not path.is_file():
        raise MatchCliError(f"{path}: image not found")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise MatchCliError(f"{path}: not an image OpenCV can read")
    return image


class _StageTimer:
    """Accumulates wall time per stage name, ms."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}

    def wrap(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.ms[stage] = self.ms.get(stage, 0.0) + (time.perf_counter() - t0) * 1e3

        return timed


class _TimedRansac:
    """The real ``RansacFilter`` with its ``filter`` timed (what the matcher calls)."""

    def __init__(self, inner: Any, timer: _StageTimer) -> None:
        self._inner = inner
        self.filter = timer.wrap("ransac", inner.filter)


def build_matcher(strategy: str, model_dir: Path | None, min_inliers: int, timer: _StageTimer) -> Any:
    """The strategy exactly as the daemon builds it: ``matcher.model_dir`` resolved by the composition
    root (the family's extractor and its LightGlue from a verified ``gdnav models export`` directory),
    then the C3 registry, with timed stages."""
    from gps_denied_onboard.config import ConfigError, config_from_mapping
    from gps_denied_onboard.helpers.ransac_filter import RansacFilter
    from gps_denied_onboard.runtime_root.compose import StartupError, create_matcher, resolve_matcher

    if strategy != "classical" and model_dir is None:
        raise MatchCliError(f"--strategy {strategy} needs --model-dir (see 'gdnav models export')")
    matcher_cfg: dict[str, Any] = {"strategy": strategy, "min_inliers_threshold": min_inliers}
    if model_dir is not None:
        matcher_cfg["model_dir"] = str(model_dir)
    try:
        config = resolve_matcher(config_from_mapping({"matcher": matcher_cfg}, source="gdnav match"))
        ransac = RansacFilter(
            confidence=config.matcher.ransac_confidence, max_iters=config.matcher.ransac_max_iters
        )
        matcher = create_matcher(config, {"c282_ransac_filter": _TimedRansac(ransac, timer)}, NULL_FDR)
    except (ConfigError, StartupError) as exc:
        raise MatchCliError(str(exc)) from exc
    for hook, stage in (
        ("extract_query", "extract_a"),
        ("extract_tile", "extract_b"),
        ("match_features", "match"),
    ):
        setattr(matcher, hook, timer.wrap(stage, getattr(matcher, hook)))
    return matcher


def rotate_keep_all(image: np.ndarray, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Image rotated counter-clockwise about its centre on a canvas holding all of it (black fill),
    and the (2, 3) affine rotated px -> original px."""
    h, w = image.shape[:2]
    fwd = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), angle_deg, 1.0)
    c, s = abs(fwd[0, 0]), abs(fwd[0, 1])
    new_w, new_h = round(w * c + h * s), round(w * s + h * c)
    fwd[0, 2] += (new_w - w) / 2.0
    fwd[1, 2] += (new_h - h) / 2.0
    rotated = cv2.warpAffine(image, fwd, (new_w, new_h), flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0))
    return rotated, cv2.invertAffineTransform(fwd)


def match_pair(
    matcher: Any,
    image_a: np.ndarray,
    image_b: np.ndarray,
    rotations: int,
    timer: _StageTimer,
    origin_px: tuple[float, float] = (0.0, 0.0),
) -> PairMatch:
    """Match A (tried at ``rotations`` evenly spaced angles) to B; the best by inlier count wins.
    ``origin_px``: where B was cut from a larger image (see ``ImageChip``): one matcher given several
    chips must be told they differ, since it caches a chip's features by its id."""
    from gps_denied_onboard.helpers.ransac_filter import RansacFilter

    chip = ImageChip(image_b, origin_px=origin_px)
    best: tuple[int, float, np.ndarray, float] | None = None
    t_total = time.perf_counter()
    for k in range(rotations):
        angle = 360.0 * k / rotations
        query, back = (image_a, None) if angle == 0.0 else rotate_keep_all(image_a, angle)
        frame = NavCameraFrame(uuid.uuid4(), k, 0, query, None, None, time.monotonic_ns())
        calib = CameraCalibration.from_hfov(query.shape[1], query.shape[0], _NOMINAL_HFOV_DEG)
        rerank = RerankResult(frame.frame_id, [RerankCandidate(chip.tile_id, chip, -1, 0.0)], 0)
        try:
            result = matcher.match(frame, rerank, calib)
        except InsufficientInliersError as exc:
            if best is None:
                best = (exc.best_inlier_count, math.inf, np.empty((0, 4), np.float32), angle)
            continue
        cand = result.best
        corr = np.array(cand.inlier_correspondences, dtype=np.float32, copy=True)
        if back is not None:
            corr[:, :2] = cv2.transform(corr[:, None, :2], back)[:, 0]
        if best is None or not best[2].shape[0] or cand.inlier_count > best[0]:
            best = (cand.inlier_count, cand.per_candidate_residual_px, corr, angle)
    timer.ms["total"] = (time.perf_counter() - t_total) * 1e3
    if best is None:  # rotations >= 1 always gives one attempt; kept for type narrowing
        raise MatchCliError("no rotation was tried")
    n, residual, corr, angle = best
    homography = None
    if corr.shape[0] >= 4:
        # The inliers are already consistent; refit on them alone for the A px -> B px homography.
        homography = RansacFilter().filter(corr, threshold_px=3.0).homography
    return PairMatch(
        strategy=matcher.label,
        inliers=int(n),
        residual_px=float(residual),
        homography=homography,
        correspondences=corr,
        rotation_deg=angle,
        timings_ms=dict(timer.ms),
    )


def draw_matches(image_a: np.ndarray, image_b: np.ndarray, corr: np.ndarray, out: Path) -> None:
    """Side-by-side A | B with one line per inlier correspondence, written to ``out``."""
    h = max(image_a.shape[0], image_b.shape[0])
    canvas = np.zeros((h, image_a.shape[1] + image_b.shape[1], 3), dtype=np.uint8)
    canvas[: image_a.shape[0], : image_a.shape[1]] = image_a
    canvas[: image_b.shape[0], image_a.shape[1] :] = image_b
    rng = np.random.default_rng(0)
    for xa, ya, xb, yb in corr.astype(np.float64):
        colour = tuple(int(c) for c in rng.integers(64, 256, 3))
        pa = (round(xa), round(ya))
        pb = (round(xb + image_a.shape[1]), round(yb))
        cv2.line(canvas, pa, pb, colour, 1, cv2.LINE_AA)
        cv2.circle(canvas, pa, 2, colour, -1)
        cv2.circle(canvas, pb, 2, colour, -1)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), canvas):
        raise MatchCliError(f"{out}: cannot write the image (unknown extension or unwritable folder)")


def _cmd_match(args: argparse.Namespace) -> int:
    from gps_denied_onboard.logging_setup import configure_logging

    # Logs go to stderr and only warnings: stdout carries the result (one JSON object with --json).
    configure_logging("warning", json=False)
    try:
        if args.rotations < 1:
            raise MatchCliError(f"--rotations must be >= 1, got {args.rotations}")
        if args.min_inliers < 4:
            raise MatchCliError(f"--min-inliers must be >= 4 (a homography needs 4), got {args.min_inliers}")
        image_a = read_image(Path(args.image_a))
        image_b = read_image(Path(args.image_b))
        timer = _StageTimer()
        model_dir = Path(args.model_dir) if args.model_dir else None
        matcher = build_matcher(args.strategy, model_dir, args.min_inliers, timer)
        timer.ms.clear()  # model loading is not a per-match stage
        result = match_pair(matcher, image_a, image_b, args.rotations, timer)
        if args.out:
            draw_matches(image_a, image_b, result.correspondences, Path(args.out))
    except MatchCliError as exc:
        print(f"gdnav match: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.json:
        print(json.dumps(result.to_json()))
    else:
        print(f"strategy     {result.strategy}")
        print(f"inliers      {result.inliers}")
        print(f"residual_px  {result.residual_px:.3f}")
        print(f"rotation_deg {result.rotation_deg:g} (best of {args.rotations})")
        h = "none" if result.homography is None else np.array2string(result.homography, precision=5)
        print(f"homography   A px -> B px\n{h}")
        print("timings_ms   " + ", ".join(f"{k}={v:.1f}" for k, v in result.timings_ms.items()))
        if args.out:
            print(f"matches      {args.out}")
    return EXIT_OK if result.inliers >= args.min_inliers else EXIT_NO_MATCH


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    """Add ``match`` to ``gdnav``'s subcommands; returns its parser."""
    match = subparsers.add_parser(
        "match",
        help="match two images with a C3 strategy (diagnostics)",
        description="Match IMAGE_A (as the nav frame) to IMAGE_B (as the map chip) with the daemon's C3 "
        "strategy code; print inliers, median residual, homography A->B and per-stage timings.",
    )
    match.add_argument("image_a", metavar="IMAGE_A", help="query image (plays the nav frame)")
    match.add_argument("image_b", metavar="IMAGE_B", help="reference image (plays the map chip)")
    match.add_argument("--strategy", choices=STRATEGIES, default="classical", help="C3 strategy (classical)")
    match.add_argument(
        "--model-dir", default=None, metavar="DIR", help="model directory (learned strategies)"
    )
    match.add_argument(
        "--rotations", type=int, default=1, metavar="K", help="try K evenly spaced rotations of A (1)"
    )
    match.add_argument("--min-inliers", type=int, default=8, metavar="N", help="inliers for a match (8)")
    match.add_argument("--out", default=None, metavar="PNG", help="draw the inlier matches side by side")
    match.add_argument("--json", action="store_true", help="print one JSON object")
    match.set_defaults(func=_cmd_match)
    return match
