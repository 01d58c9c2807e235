"""``gdnav models`` and ``gdnav match`` end to end, as subprocesses (exit codes, output, real files)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import aliked_fixture
from conftest import shared_path

#: The session-scoped export fixture, made visible to this module's tests.
aliked_t16_onnx = aliked_fixture.aliked_t16_onnx

# Until the lead hooks ``register`` into ``gdnav``'s parser, build the same sub-parsers standalone.
_ENTRY = (
    "import argparse, sys\n"
    "from gps_denied_onboard import cli_match, cli_models\n"
    "p = argparse.ArgumentParser(prog='gdnav')\n"
    "s = p.add_subparsers(dest='command', required=True)\n"
    "cli_models.register(s); cli_match.register(s)\n"
    "a = p.parse_args(sys.argv[1:]); sys.exit(a.func(a))\n"
)


def _gdnav(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _ENTRY, *args], capture_output=True, text=True, timeout=240, check=False
    )


def _no_traceback(result: subprocess.CompletedProcess[str]) -> None:
    assert "Traceback" not in result.stderr, result.stderr


# ------------------------------------------------------------------------------------------- models


def test_models_import_export_verify_end_to_end(tmp_path: Path) -> None:
    """import copies the pinned weights, export writes an ONNX + manifest, verify accepts it."""
    weights = shared_path("models", "aliked")
    pytest.importorskip("torch")
    dest = tmp_path / "weights"
    out = tmp_path / "onnx"
    imported = _gdnav("models", "import", "--from", str(weights), "--dest", str(dest))
    assert imported.returncode == 0, imported.stderr
    assert (dest / "aliked-t16.pth").is_file()
    exported = _gdnav(
        "models", "export", "--weights-dir", str(dest), "--out", str(out),
        "--top-k", "256", "--height", "128", "--width", "160",
    )  # fmt: skip
    assert exported.returncode == 0, exported.stderr
    assert (out / "aliked-t16-128x160-k256.onnx").is_file()
    verified = _gdnav("models", "verify", "--dir", str(out))
    assert verified.returncode == 0, verified.stderr
    assert "aliked-t16-128x160-k256.onnx" in verified.stdout and "BSD-3-Clause" in verified.stdout
    # A changed model file is then refused with exit 2 and the file named.
    (out / "aliked-t16-128x160-k256.onnx").write_bytes(b"tampered")
    refused = _gdnav("models", "verify", "--dir", str(out))
    assert refused.returncode == 2 and "aliked-t16-128x160-k256.onnx" in refused.stderr
    _no_traceback(refused)


def test_models_export_missing_weights_exits_2(tmp_path: Path) -> None:
    """Export without the weights file fails with exit 2 and says how to get them."""
    result = _gdnav("models", "export", "--weights-dir", str(tmp_path), "--out", str(tmp_path / "o"))
    assert result.returncode == 2
    assert "aliked-t16.pth" in result.stderr and "models import" in result.stderr
    _no_traceback(result)


def test_models_export_bad_size_exits_2(tmp_path: Path) -> None:
    """A size that is not a multiple of 32 is bad input (exit 2), not a traceback."""
    weights = shared_path("models", "aliked")
    result = _gdnav(
        "models", "export", "--weights-dir", str(weights), "--out", str(tmp_path),
        "--height", "100", "--width", "160",
    )  # fmt: skip
    assert result.returncode == 2 and "multiples of 32" in result.stderr
    _no_traceback(result)


def test_models_import_sha_mismatch_exits_2(tmp_path: Path) -> None:
    """A file named like the weights but with other bytes is refused (exit 2)."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "aliked-t16.pth").write_bytes(b"not the weights")
    result = _gdnav("models", "import", "--from", str(src), "--dest", str(tmp_path / "d"))
    assert result.returncode == 2 and "sha256" in result.stderr
    _no_traceback(result)


def test_models_fetch_unreachable_exits_2(tmp_path: Path) -> None:
    """fetch from an unreachable (local, closed-port) mirror fails with exit 2 and a clear message."""
    result = _gdnav(
        "models", "fetch", "--dest", str(tmp_path), "--name", "aliked-t16",
        "--mirror", "http://127.0.0.1:9", "--timeout", "5",
    )  # fmt: skip
    assert result.returncode == 2
    assert "cannot download aliked-t16" in result.stderr and "import" in result.stderr
    assert not (tmp_path / "aliked-t16.pth").exists()
    _no_traceback(result)


def test_models_verify_missing_dir_exits_2(tmp_path: Path) -> None:
    """verify on a folder that does not exist is exit 2 with the path named."""
    result = _gdnav("models", "verify", "--dir", str(tmp_path / "none"))
    assert result.returncode == 2 and "does not exist" in result.stderr
    _no_traceback(result)


def test_models_help_exits_0() -> None:
    """Each models subcommand has --help."""
    for sub in ("import", "fetch", "export", "verify"):
        result = _gdnav("models", sub, "--help")
        assert result.returncode == 0 and "usage:" in result.stdout


# -------------------------------------------------------------------------------------------- match


SHIFT_XY = (37, 23)


@pytest.fixture(scope="module")
def crop_pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two overlapping 480x640 crops of a real satellite patch (B = A shifted by SHIFT_XY), as PNGs."""
    patch = cv2.imread(str(shared_path("data", "geovision_india", "sat_patch_0000.png")), cv2.IMREAD_COLOR)
    folder = tmp_path_factory.mktemp("match")
    sx, sy = SHIFT_XY
    a, b = folder / "a.png", folder / "b.png"
    cv2.imwrite(str(a), patch[100:580, 100:740])
    cv2.imwrite(str(b), patch[100 + sy : 580 + sy, 100 + sx : 740 + sx])
    return a, b


def _assert_shift_homography(h: list[list[float]]) -> None:
    corners = np.array([[[0.0, 0.0]], [[639.0, 0.0]], [[0.0, 479.0]], [[639.0, 479.0]]])
    mapped = cv2.perspectiveTransform(corners, np.asarray(h, dtype=np.float64))[:, 0]
    error = np.linalg.norm(mapped - (corners[:, 0] - SHIFT_XY), axis=1)
    assert error.max() < 2.0, f"corner errors {error}"


def test_match_json_aliked_recovers_shift(
    crop_pair: tuple[Path, Path], aliked_t16_onnx: Path, tmp_path: Path
) -> None:
    """match --json with ALIKED: many inliers, homography = the true shift, timings and a PNG."""
    out = tmp_path / "matches.png"
    result = _gdnav(
        "match", str(crop_pair[0]), str(crop_pair[1]), "--strategy", "aliked_lightglue",
        "--model-dir", str(aliked_t16_onnx.parent), "--json", "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    print(f"\ngdnav match aliked: {data}")
    assert data["strategy"] == "aliked_lightglue" and data["inliers"] > 100
    assert data["residual_px"] < 2.0
    assert {"extract_a", "extract_b", "match", "ransac", "total"} <= set(data["timings_ms"])
    _assert_shift_homography(data["homography"])
    assert cv2.imread(str(out)).shape == (480, 1280, 3)


def test_match_json_classical_with_rotations(crop_pair: tuple[Path, Path]) -> None:
    """Classical with --rotations 4: SIFT matches at every angle; the result is in original A px."""
    result = _gdnav("match", str(crop_pair[0]), str(crop_pair[1]), "--rotations", "4", "--json")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["strategy"] == "classical" and data["inliers"] > 100
    assert data["rotation_deg"] in (0.0, 90.0, 180.0, 270.0)
    _assert_shift_homography(data["homography"])


def test_match_rotated_image_found_by_rotations(
    crop_pair: tuple[Path, Path], aliked_t16_onnx: Path, tmp_path: Path
) -> None:
    """A rotated by 90 deg is matched by ALIKED only through --rotations; the angle is reported."""
    rotated = tmp_path / "a_rot.png"
    cv2.imwrite(str(rotated), cv2.rotate(cv2.imread(str(crop_pair[0])), cv2.ROTATE_90_CLOCKWISE))
    result = _gdnav(
        "match", str(rotated), str(crop_pair[1]), "--strategy", "aliked_lightglue",
        "--model-dir", str(aliked_t16_onnx.parent), "--rotations", "4", "--json",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["rotation_deg"] == 90.0 and data["inliers"] > 50


def test_match_missing_image_exits_2(crop_pair: tuple[Path, Path], tmp_path: Path) -> None:
    """A missing image is exit 2 with one clear line."""
    result = _gdnav("match", str(tmp_path / "none.png"), str(crop_pair[1]))
    assert result.returncode == 2 and "none.png: image not found" in result.stderr
    _no_traceback(result)


def test_match_unreadable_image_exits_2(crop_pair: tuple[Path, Path], tmp_path: Path) -> None:
    """A file that is not an image is exit 2."""
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not a png")
    result = _gdnav("match", str(crop_pair[0]), str(junk))
    assert result.returncode == 2 and "junk.png" in result.stderr
    _no_traceback(result)


def test_match_aliked_without_model_exits_2(crop_pair: tuple[Path, Path], tmp_path: Path) -> None:
    """ALIKED without --model-dir, or with a folder lacking a manifest, is exit 2."""
    no_dir = _gdnav("match", str(crop_pair[0]), str(crop_pair[1]), "--strategy", "aliked_lightglue")
    assert no_dir.returncode == 2 and "--model-dir" in no_dir.stderr
    empty = _gdnav(
        "match", str(crop_pair[0]), str(crop_pair[1]), "--strategy", "aliked_lightglue",
        "--model-dir", str(tmp_path),
    )  # fmt: skip
    assert empty.returncode == 2 and "manifest" in empty.stderr
    _no_traceback(empty)
