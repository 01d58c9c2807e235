"""ALIKED weights -> ONNX: registry pins, manifest, the network (torch) and ONNX parity on real images."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import urllib.error
from pathlib import Path

import cv2
import numpy as np
import pytest

from gps_denied_onboard.models import (
    KNOWN_WEIGHTS,
    ModelDirError,
    ModelEntry,
    ModelSource,
    WeightsError,
    WeightsFetchError,
    WeightsHashMismatchError,
    export_aliked_onnx,
    fetch_weights,
    import_weights,
    sha256_file,
    verify_model_dir,
    write_manifest,
)
from gps_denied_onboard.models.export import ALIKED_EXTRACTOR_SIGNATURE

SHARED = Path(__file__).resolve().parents[2] / "shared"
WEIGHTS_DIR = SHARED / "models" / "aliked"
GEOVISION_PNG = SHARED / "data" / "geovision_india" / "sat_patch_0000.png"
NAIP_TIF = SHARED / "data" / "naip_timeseries" / "naip" / "m_4709963_se_14_1_20180716.tif"

needs_weights = pytest.mark.skipif(not WEIGHTS_DIR.is_dir(), reason="needs ../shared/models/aliked")


def _weights(variant: str) -> Path:
    return WEIGHTS_DIR / f"aliked-{variant}.pth"


def _rgb_crop(path: Path, height: int, width: int, top: int = 0, left: int = 0) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB crop of a PNG or of the first three bands of a GeoTIFF (read-only)."""
    if path.suffix == ".tif":
        import rasterio
        from rasterio.windows import Window

        with rasterio.open(path) as dataset:
            bands = dataset.read((1, 2, 3), window=Window(left, top, width, height))
        return np.ascontiguousarray(bands.transpose(1, 2, 0))
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(bgr[top : top + height, left : left + width, ::-1])


def _to_input(rgb: np.ndarray) -> np.ndarray:
    return (rgb.transpose(2, 0, 1)[None] / 255.0).astype(np.float32)


# ----------------------------------------------------------------------------------- registry (no torch)


def test_models_import_does_not_import_torch():
    """Importing the models package (as the daemon does) must not pull torch in."""
    code = "import sys, gps_denied_onboard.models; print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


@needs_weights
def test_registry_pins_match_shared_weights():
    """The pinned sha256 values are those of the official files."""
    for weights in KNOWN_WEIGHTS.values():
        assert sha256_file(WEIGHTS_DIR / weights.filename) == weights.sha256
        assert weights.licence == "BSD-3-Clause"
        assert weights.url.startswith("https://raw.githubusercontent.com/Shiaoming/ALIKED/")


@needs_weights
def test_import_weights_copies_pinned_files(tmp_path):
    """Files whose sha256 matches the pin are copied and verified."""
    imported = import_weights(WEIGHTS_DIR, tmp_path / "models")
    assert sorted(p.name for p in imported) == ["aliked-n16.pth", "aliked-t16.pth"]
    for path in imported:
        assert sha256_file(path) == KNOWN_WEIGHTS[path.stem].sha256


def test_import_weights_refuses_sha_mismatch(tmp_path):
    """A file named like the official weights but with other bytes is refused and not copied."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "aliked-t16.pth").write_bytes(b"not the official weights")
    dest = tmp_path / "dest"
    with pytest.raises(WeightsHashMismatchError) as info:
        import_weights(src, dest)
    assert info.value.expected == KNOWN_WEIGHTS["aliked-t16"].sha256
    assert not (dest / "aliked-t16.pth").exists()


def test_import_weights_missing_file_raises(tmp_path):
    """Asking for weights that are not in the source directory names the missing file."""
    with pytest.raises(WeightsError, match=r"aliked-n16\.pth"):
        import_weights(tmp_path, tmp_path / "dest", names=["aliked-n16"])


def test_fetch_weights_offline_fails_with_clear_message(tmp_path):
    """Without network the error names the URL and tells how to import the files instead."""

    def offline(url, timeout):
        raise urllib.error.URLError("[Errno -3] Temporary failure in name resolution")

    with pytest.raises(WeightsFetchError, match="import_weights") as info:
        fetch_weights(tmp_path, ["aliked-t16"], urlopen=offline)
    assert info.value.path == KNOWN_WEIGHTS["aliked-t16"].url
    assert list(tmp_path.iterdir()) == []


def test_fetch_weights_refuses_sha_mismatch(tmp_path):
    """Downloaded bytes that are not the pinned file are discarded."""
    with pytest.raises(WeightsHashMismatchError):
        fetch_weights(tmp_path, ["aliked-t16"], urlopen=lambda url, timeout: io.BytesIO(b"tampered"))
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------- manifest (no torch)


def _fake_model_dir(tmp_path: Path) -> Path:
    model_dir = tmp_path / "models"
    model_dir.mkdir()
    model = model_dir / "extractor.onnx"
    model.write_bytes(b"fake onnx bytes")
    pin = KNOWN_WEIGHTS["aliked-t16"]
    source = ModelSource(name=pin.name, sha256=pin.sha256, licence=pin.licence, url=pin.url)
    write_manifest(
        model_dir,
        ModelEntry(model.name, sha256_file(model), source, ALIKED_EXTRACTOR_SIGNATURE, {"top_k": 8}),
    )
    return model_dir


def test_verify_model_dir_accepts_written_manifest(tmp_path):
    """A manifest written by write_manifest verifies and round-trips the signature."""
    entries = verify_model_dir(_fake_model_dir(tmp_path))
    assert len(entries) == 1
    assert entries[0].signature == ALIKED_EXTRACTOR_SIGNATURE
    assert entries[0].source.licence == "BSD-3-Clause"
    assert entries[0].created


def test_verify_model_dir_detects_modified_file(tmp_path):
    """A model file changed after export is refused, naming the file."""
    model_dir = _fake_model_dir(tmp_path)
    (model_dir / "extractor.onnx").write_bytes(b"changed")
    with pytest.raises(ModelDirError, match=r"extractor\.onnx"):
        verify_model_dir(model_dir)


def test_verify_model_dir_detects_unpinned_source(tmp_path):
    """A manifest claiming known weights with another sha256 is refused."""
    model_dir = _fake_model_dir(tmp_path)
    manifest = model_dir / "manifest.json"
    data = json.loads(manifest.read_text())
    data["models"][0]["source"]["sha256"] = "0" * 64
    manifest.write_text(json.dumps(data))
    with pytest.raises(ModelDirError, match="pinned"):
        verify_model_dir(model_dir)


def test_verify_model_dir_without_manifest_raises(tmp_path):
    """A directory without manifest.json is refused with a clear message."""
    with pytest.raises(ModelDirError, match="no model manifest"):
        verify_model_dir(tmp_path)


def test_export_refuses_size_not_multiple_of_32(tmp_path):
    """Sizes the encoder cannot pool exactly are refused before any work."""
    with pytest.raises(ValueError, match="multiples of 32"):
        export_aliked_onnx(_weights("t16"), tmp_path / "m.onnx", height=470, width=640)


def test_export_refuses_unpinned_weights(tmp_path):
    """Weights that are not the pinned file are refused before export."""
    fake = tmp_path / "aliked-t16.pth"
    fake.write_bytes(b"x")
    with pytest.raises(WeightsHashMismatchError):
        export_aliked_onnx(fake, tmp_path / "m.onnx", variant="t16", height=480, width=640)


# ------------------------------------------------------------------------------------- network (torch)


def _naive_deform_conv(x, offset, weight):
    """Direct DCN (torchvision semantics: bilinear, zero outside the image) for a small input."""
    _, channels, height, width = x.shape
    out = np.zeros((1, weight.shape[0], height, width))

    def sample(c, py, px):
        if py <= -1 or py >= height or px <= -1 or px >= width:
            return 0.0
        y0, x0 = int(np.floor(py)), int(np.floor(px))
        total = 0.0
        for yy, xx in ((y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1)):
            if 0 <= yy < height and 0 <= xx < width:
                total += (1 - abs(py - yy)) * (1 - abs(px - xx)) * x[0, c, yy, xx]
        return total

    for y in range(height):
        for xi in range(width):
            for k in range(9):
                py = y + k // 3 - 1 + offset[0, 2 * k, y, xi]
                px = xi + k % 3 - 1 + offset[0, 2 * k + 1, y, xi]
                vals = np.array([sample(c, py, px) for c in range(channels)])
                out[0, :, y, xi] += weight[:, :, k // 3, k % 3] @ vals
    return out


def test_deform_conv_matches_direct_definition():
    """The grid_sample decomposition equals the direct DCN sum, including taps outside the image."""
    torch = pytest.importorskip("torch")
    from gps_denied_onboard.models.aliked_torch import deform_conv2d_3x3

    torch.set_num_threads(1)
    rng = np.random.default_rng(3)
    x = rng.standard_normal((1, 2, 5, 6))
    offset = rng.uniform(-2.5, 2.5, (1, 18, 5, 6))
    weight = rng.standard_normal((3, 2, 3, 3))
    expected = _naive_deform_conv(x, offset, weight)
    got = deform_conv2d_3x3(*(torch.from_numpy(a).float() for a in (x, offset, weight))).numpy()
    assert np.abs(got - expected).max() < 1e-4


@needs_weights
@pytest.mark.parametrize("variant", ["t16", "n16"])
def test_aliked_state_dict_loads_strict(variant):
    """Every official tensor has a place in the network and none is missing (strict=True)."""
    pytest.importorskip("torch")
    from gps_denied_onboard.models.aliked_torch import load_aliked

    model = load_aliked(_weights(variant), variant)
    assert model.desc_head.agg_weights.shape[-1] == {"t16": 64, "n16": 128}[variant]


@needs_weights
def test_aliked_wrong_variant_weights_raise():
    """n16 weights loaded as t16 fail loudly instead of half-loading."""
    pytest.importorskip("torch")
    from gps_denied_onboard.models.aliked_torch import load_aliked

    with pytest.raises(RuntimeError, match="not ALIKED-t16 weights"):
        load_aliked(_weights("n16"), "t16")


# ------------------------------------------------------------------------- ONNX parity on real images


def _torch_extract(variant: str, image: np.ndarray, top_k: int) -> tuple[np.ndarray, ...]:
    import torch

    from gps_denied_onboard.models.aliked_torch import load_aliked

    torch.set_num_threads(1)
    model = load_aliked(_weights(variant), variant, top_k=top_k)
    with torch.no_grad():
        return tuple(t.numpy()[0] for t in model(torch.from_numpy(image)))


def _onnx_extract(path: Path, image: np.ndarray) -> tuple[np.ndarray, ...]:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    return tuple(a[0] for a in session.run(None, {"image": image}))


def _assert_parity(torch_out, onnx_out) -> None:
    """Same keypoint set; order equal except swaps of near-tied scores; values within float tolerance."""
    tk, ts, td = torch_out
    ok, os_, od = onnx_out
    distance = np.linalg.norm(tk[:, None, :] - ok[None, :, :], axis=-1)
    nearest = distance.argmin(axis=1)
    matched = distance.min(axis=1) < 1e-3
    # The dense maps differ by ~1e-5 between the two runtimes, so two keypoints whose scores are closer
    # than that may swap ranks (or, rarely, trade places at the top-k boundary).
    assert matched.mean() >= 0.995, f"only {matched.sum()}/{len(tk)} torch keypoints found in the ONNX output"
    assert len(np.unique(nearest[matched])) == matched.sum()
    assert (nearest == np.arange(len(tk))).mean() >= 0.98
    assert np.abs(tk[matched] - ok[nearest[matched]]).max() < 1e-3
    assert np.abs(ts[matched] - os_[nearest[matched]]).max() < 1e-3
    assert np.abs(td[matched] - od[nearest[matched]]).max() < 1e-3
    np.testing.assert_allclose(np.linalg.norm(od, axis=1), 1.0, atol=1e-4)


@pytest.fixture(scope="module")
def t16_fixed_dir(tmp_path_factory):
    """T16 exported at 480x640, top_k=1024, into a temporary model directory."""
    pytest.importorskip("torch")
    if not WEIGHTS_DIR.is_dir():
        pytest.skip("needs ../shared/models/aliked")
    model_dir = tmp_path_factory.mktemp("aliked_models")
    export_aliked_onnx(
        _weights("t16"), model_dir / "t16.onnx", variant="t16", top_k=1024, height=480, width=640
    )
    return model_dir


@pytest.mark.realdata
@pytest.mark.parametrize("image_path", [GEOVISION_PNG, NAIP_TIF], ids=["geovision", "naip"])
def test_aliked_onnx_matches_torch_on_real_images(t16_fixed_dir, image_path):
    """ONNX Runtime CPU reproduces the torch keypoints, scores and descriptors of T16 on real imagery."""
    if not image_path.exists():
        pytest.skip(f"needs {image_path}")
    image = _to_input(_rgb_crop(image_path, 480, 640))
    torch_out = _torch_extract("t16", image, top_k=1024)
    onnx_out = _onnx_extract(t16_fixed_dir / "t16.onnx", image)
    assert onnx_out[0].shape == (1024, 2) and onnx_out[2].shape == (1024, 64)
    _assert_parity(torch_out, onnx_out)


def test_aliked_export_manifest_verifies(t16_fixed_dir):
    """The exported file is recorded with its sha256, source pin, licence and signature."""
    (entry,) = verify_model_dir(t16_fixed_dir)
    assert entry.file == "t16.onnx"
    assert entry.source.sha256 == KNOWN_WEIGHTS["aliked-t16"].sha256
    assert entry.params["top_k"] == 1024 and entry.params["height"] == 480


@pytest.mark.realdata
@pytest.mark.slow
def test_aliked_n16_dynamic_onnx_matches_torch_at_other_size(tmp_path):
    """N16 exported with dynamic H/W (traced at 480x640) matches torch at 384x512."""
    pytest.importorskip("torch")
    if not (WEIGHTS_DIR.is_dir() and GEOVISION_PNG.exists()):
        pytest.skip("needs ../shared weights and imagery")
    path = export_aliked_onnx(_weights("n16"), tmp_path / "n16.onnx", variant="n16", top_k=512)
    image = _to_input(_rgb_crop(GEOVISION_PNG, 384, 512, top=300, left=200))
    torch_out = _torch_extract("n16", image, top_k=512)
    onnx_out = _onnx_extract(path, image)
    assert onnx_out[2].shape == (512, 128)
    _assert_parity(torch_out, onnx_out)


@pytest.mark.realdata
def test_aliked_matches_recover_known_shift(t16_fixed_dir):
    """Two overlapping crops shifted by (37, 23) px: mutual-NN matches + RANSAC recover the shift."""
    if not GEOVISION_PNG.exists():
        pytest.skip(f"needs {GEOVISION_PNG}")
    shift_x, shift_y = 37, 23
    first = _to_input(_rgb_crop(GEOVISION_PNG, 480, 640, top=100, left=100))
    second = _to_input(_rgb_crop(GEOVISION_PNG, 480, 640, top=100 + shift_y, left=100 + shift_x))
    k1, _, d1 = _onnx_extract(t16_fixed_dir / "t16.onnx", first)
    k2, _, d2 = _onnx_extract(t16_fixed_dir / "t16.onnx", second)
    similarity = d1 @ d2.T
    forward, backward = similarity.argmax(axis=1), similarity.argmax(axis=0)
    mutual = np.flatnonzero(backward[forward] == np.arange(len(k1)))
    assert len(mutual) >= 100
    homography, inliers = cv2.findHomography(k1[mutual], k2[forward[mutual]], cv2.RANSAC, 2.0)
    assert homography is not None and inliers.sum() >= 100
    # A point p in the first crop is at p - shift in the second.
    corners = np.array([[[0.0, 0.0]], [[639.0, 0.0]], [[0.0, 479.0]], [[639.0, 479.0]]])
    mapped = cv2.perspectiveTransform(corners, homography)[:, 0]
    error = np.linalg.norm(mapped - (corners[:, 0] - [shift_x, shift_y]), axis=1)
    assert error.max() < 1.5, f"corner errors {error} px"


def test_aliked_onnx_signature_has_static_outputs(t16_fixed_dir):
    """The file has the LightGlue-ONNX extractor names, a fixed input size and static N and D."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(t16_fixed_dir / "t16.onnx"), providers=["CPUExecutionProvider"])
    assert [(i.name, i.shape, i.type) for i in session.get_inputs()] == [
        ("image", [1, 3, 480, 640], "tensor(float)")
    ]
    assert [(o.name, o.shape) for o in session.get_outputs()] == [
        ("keypoints", [1, 1024, 2]),
        ("scores", [1, 1024]),
        ("descriptors", [1, 1024, 64]),
    ]
