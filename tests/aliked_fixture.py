"""Session fixture: the ALIKED T16 ONNX extractor exported once from ../shared/models/aliked.

Import the fixture into a test module (``from aliked_fixture import aliked_t16_onnx``). The export
(torch, build-time only) goes to a pytest temporary directory, never into the repository.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import SHARED

#: Recommended export: 384x512 (H x W), top-k 1024 (see tests/test_c3_aliked.py for the numbers).
EXPORT_HEIGHT, EXPORT_WIDTH, EXPORT_TOP_K = 384, 512, 1024
WEIGHTS_DIR = SHARED / "models" / "aliked"


@pytest.fixture(scope="session")
def aliked_t16_onnx(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Path of ``aliked-t16-384x512-k1024.onnx`` in a session temp model dir (with its manifest)."""
    weights = WEIGHTS_DIR / "aliked-t16.pth"
    if not weights.is_file():
        pytest.skip(f"ALIKED weights not available: {weights}")
    torch = pytest.importorskip("torch", reason="exporting ALIKED needs torch (build-time extra)")
    from gps_denied_onboard.models import default_onnx_name, export_aliked_onnx

    torch.set_num_threads(1)  # 2 shared CPU cores
    model_dir = tmp_path_factory.mktemp("aliked_models")
    name = default_onnx_name("t16", EXPORT_TOP_K, EXPORT_HEIGHT, EXPORT_WIDTH)
    return export_aliked_onnx(
        weights,
        model_dir / name,
        variant="t16",
        top_k=EXPORT_TOP_K,
        height=EXPORT_HEIGHT,
        width=EXPORT_WIDTH,
    )
