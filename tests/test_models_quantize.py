"""``gdnav models quantize``: int8 files beside the fp32 exports, their manifest entries, their refusals.

The real-model test quantises the registry fixture's XFeat export (copied: the session's directory stays
fp32 for the other tests) in a real ``gdnav`` process, calibrated on the NAIP series.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from conftest import shared_path
from gps_denied_onboard.helpers.model_manifest import ModelEntry, ModelSource, write_manifest
from gps_denied_onboard.helpers.onnx_signatures import extractor_signature
from gps_denied_onboard.models import read_manifest, sha256_file, verify_model_dir
from gps_denied_onboard.models.learned_export import family_models, family_models_at
from gps_denied_onboard.models.quantize import fold_initializer_transposes, int8_name
from gps_denied_onboard.models.verification import VERIFICATION_NAME, family_verified
from onnx_builders import build_fake_extractor
from registry_models_fixture import registry_models  # noqa: F401 - session fixture

NAIP_SUBDIR = ("data", "naip_timeseries", "naip")
SIGNATURE = extractor_signature("xfeat", channels=3, descriptor_dim=64)


def _gdnav(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "gps_denied_onboard.cli", "models", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=cwd)


def _ops(path: Path) -> Counter[str]:
    return Counter(n.op_type for n in onnx.load(str(path), load_external_data=False).graph.node)


def test_fold_initializer_transposes_keeps_the_output_and_exposes_the_weight(tmp_path: Path) -> None:
    """A Linear as the dynamo exporter writes it (MatMul(x, Transpose(W))): folded, W^T is an initializer
    the quantiser can see, no Transpose is left, and the output is unchanged."""
    rng = np.random.default_rng(0)
    weight = rng.standard_normal((8, 16)).astype(np.float32)  # (out, in), as torch stores it
    graph = helper.make_graph(
        [
            helper.make_node("Transpose", ["w"], ["w_t"], perm=[1, 0]),
            helper.make_node("MatMul", ["x", "w_t"], ["y"]),
        ],
        "linear",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [None, 16])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, 8])],
        [numpy_helper.from_array(weight, "w")],
    )
    src = tmp_path / "linear.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8), src)
    dst = tmp_path / "folded.onnx"

    assert fold_initializer_transposes(src, dst) == 1

    model = onnx.load(str(dst))
    assert [n.op_type for n in model.graph.node] == ["MatMul"]
    assert {i.name for i in model.graph.initializer} == {"w.T"}  # named after the weight it came from
    x = rng.standard_normal((5, 16)).astype(np.float32)
    y = ort.InferenceSession(str(dst), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    np.testing.assert_allclose(y, x @ weight.T, rtol=1e-5, atol=1e-5)


def test_int8_entries_do_not_replace_the_fp32_family(tmp_path: Path) -> None:
    """``family_models`` keeps returning the fp32 pair when int8 entries are added; the int8 pair (or a
    mixed one, where only one role is quantised) is asked for by precision; a verification of the int8
    files does not verify the fp32 ones."""
    source = ModelSource("fake-xfeat", "0" * 64, "Apache-2.0", "https://example.invalid/xfeat")
    for name in ("x.onnx", "lg.onnx", "x.int8.onnx"):
        (tmp_path / name).write_bytes(name.encode())

    def entry(file: str, role: str, **extra: str) -> ModelEntry:
        params = {"family": "xfeat", "role": role, **extra}
        return ModelEntry(file, sha256_file(tmp_path / file), source, SIGNATURE, params)

    fp32_x, fp32_lg = entry("x.onnx", "extractor"), entry("lg.onnx", "matcher")
    int8_x = entry("x.int8.onnx", "extractor", precision="int8", quantized_from="x.onnx")
    for e in (fp32_x, fp32_lg, int8_x):
        write_manifest(tmp_path, e)
    entries = verify_model_dir(tmp_path)

    assert [e.file for e in family_models(entries, "xfeat") or ()] == ["x.onnx", "lg.onnx"]
    assert family_models(entries, "xfeat", "int8") is None  # no int8 matcher
    assert [e.file for e in family_models_at(entries, "xfeat", "int8") or ()] == ["x.int8.onnx", "lg.onnx"]

    record = {
        "passed": True,
        "precision": "int8",
        "extractor": {"file": "x.int8.onnx", "sha256": int8_x.sha256},
        "matcher": {"file": "lg.onnx", "sha256": fp32_lg.sha256},
    }
    (tmp_path / VERIFICATION_NAME).write_text(json.dumps({"format": 1, "families": {"xfeat.int8": record}}))
    int8_pair = family_models_at(entries, "xfeat", "int8")
    assert int8_pair is not None
    assert family_verified(tmp_path, "xfeat", *int8_pair, precision="int8")
    assert not family_verified(tmp_path, "xfeat", fp32_x, fp32_lg)


def _pair(share: float):  # type: ignore[no-untyped-def]
    from gps_denied_onboard.models.reference_check import PairFigures

    return PairFigures(4096, 1.0, 0.0, 0.0, 500, 500, share, share, 500, 0.9, 1.0, 1.0, 1.0, 1.0)


def test_int8_check_passes_at_its_own_floor_and_is_recorded_under_its_own_key(tmp_path: Path) -> None:
    """96 % identical matches pass the int8 floor (95 %), not the fp32 one (99 %); the int8 record goes
    under ``<family>.int8`` and leaves the fp32 record of the family as it was."""
    from gps_denied_onboard.models.reference_check import FamilyCheck, record_verification

    fp32 = FamilyCheck("xfeat", "x.onnx", "a" * 64, "lg.onnx", "b" * 64, (_pair(1.0),))
    int8 = FamilyCheck("xfeat", "x.int8.onnx", "c" * 64, "lg.int8.onnx", "d" * 64, (_pair(0.96),), "int8")
    assert int8.passed and int8.min_share == 0.95
    assert not dataclasses.replace(int8, precision="fp32").passed
    assert not dataclasses.replace(int8, pairs=(_pair(0.94),)).passed

    record_verification(tmp_path, [fp32])
    record_verification(tmp_path, [int8])

    families = json.loads((tmp_path / VERIFICATION_NAME).read_text())["families"]
    assert set(families) == {"xfeat", "xfeat.int8"}
    assert families["xfeat"]["extractor"]["file"] == "x.onnx"
    assert families["xfeat.int8"]["matcher"]["file"] == "lg.int8.onnx"
    assert families["xfeat.int8"]["min_identical_share"] == 0.95
    assert families["xfeat.int8"]["precision"] == "int8"


def test_quantize_refuses_a_missing_directory(tmp_path: Path) -> None:
    """A model directory that does not exist: exit 2, one line naming it."""
    res = _gdnav("quantize", "--dir", str(tmp_path / "nowhere"), cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0
    assert "nowhere: not a directory" in res.stderr and "Traceback" not in res.stderr


def test_quantize_refuses_an_unknown_family(tmp_path: Path) -> None:
    """``--family nonesuch``: exit 2, one line listing the families."""
    res = _gdnav("quantize", "--dir", str(tmp_path), "--family", "nonesuch", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0
    assert "unknown model family 'nonesuch'; expected one of disk, aliked, xfeat" in res.stderr


def test_quantize_refuses_a_directory_without_manifest(tmp_path: Path) -> None:
    """A directory with no manifest: exit 3 (a refused model directory), one line."""
    res = _gdnav("quantize", "--dir", str(tmp_path), cwd=tmp_path)
    assert res.returncode == 3, res.stderr
    assert res.stderr.strip().count("\n") == 0
    assert "no model manifest" in res.stderr


def test_quantize_refuses_a_family_that_is_not_exported(tmp_path: Path) -> None:
    """``--family disk`` in a directory that holds another model only: exit 3, one line."""
    extractor = build_fake_extractor(tmp_path / "x.onnx")
    source = ModelSource("fake", "0" * 64, "MIT", "https://example.invalid/fake")
    write_manifest(tmp_path, ModelEntry(extractor.name, sha256_file(extractor), source, SIGNATURE))
    res = _gdnav("quantize", "--dir", str(tmp_path), "--family", "disk", "--role", "matcher", cwd=tmp_path)
    assert res.returncode == 3, res.stderr
    assert res.stderr.strip().count("\n") == 0
    assert "no fp32 disk extractor + matcher in the manifest" in res.stderr


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.timeout(900)
def test_quantize_writes_int8_files_and_manifest_entries(registry_models, tmp_path: Path) -> None:  # noqa: F811
    """The real XFeat export quantised in a real ``gdnav`` process: both int8 files are written beside the
    fp32 ones (which stay as they were), each with a manifest entry that verifies, says int8 and names
    the fp32 file and its sha256; the matcher's MatMuls run as integer MatMuls (the folded weights) and
    the extractor's Convs through Quantize/DequantizeLinear; both load and run in ONNX Runtime; ``verify
    --precision int8`` checks that pair, records it under ``xfeat.int8`` and exits by its 95 % floor."""
    naip = shared_path(*NAIP_SUBDIR)
    source_dir = registry_models("xfeat")
    model_dir = tmp_path / "models"
    model_dir.mkdir()
    fp32 = family_models(read_manifest(source_dir), "xfeat")
    assert fp32 is not None
    for entry in fp32:
        for name in (entry.file, entry.params.get("data_file")):
            if name:
                shutil.copy2(source_dir / str(name), model_dir / str(name))
        write_manifest(model_dir, entry)

    res = _gdnav("quantize", "--dir", str(model_dir), "--calibration-dir", str(naip), cwd=tmp_path)

    assert res.returncode == 0, res.stderr
    entries = verify_model_dir(model_dir)
    assert family_models(entries, "xfeat") == fp32  # the fp32 entries are untouched
    int8 = family_models(entries, "xfeat", "int8")
    assert int8 is not None
    for new, old in zip(int8, fp32, strict=True):
        assert new.file == int8_name(old.file)
        assert new.params["precision"] == "int8"
        assert new.params["quantized_from"] == old.file
        assert new.params["quantized_from_sha256"] == old.sha256
        assert new.params["role"] == old.params["role"] and new.params["family"] == "xfeat"
        assert new.sha256 == sha256_file(model_dir / new.file)
        assert new.source == old.source and new.signature == old.signature
        assert "data_file" not in new.params
    extractor, matcher = int8
    assert extractor.params["calibration_tensors"] > 0
    assert _ops(model_dir / matcher.file)["MatMulInteger"] >= 50
    ext_ops = _ops(model_dir / extractor.file)
    assert ext_ops["QuantizeLinear"] > 0 and ext_ops["DequantizeLinear"] > 0

    image = np.random.default_rng(0).random((1, 3, 480, 640), dtype=np.float32)
    kpts, _, desc = ort.InferenceSession(str(model_dir / extractor.file)).run(None, {"image": image})
    assert kpts.shape[1] > 100 and desc.shape[2] == 64
    lg = ort.InferenceSession(str(model_dir / matcher.file))
    feeds = {"kpts0": kpts / 320.0 - 1.0, "kpts1": kpts / 320.0 - 1.0, "desc0": desc, "desc1": desc}
    matches, _ = lg.run(None, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()})
    assert len(matches) > 0.5 * kpts.shape[1]  # an image against itself matches most keypoints

    res = _gdnav(
        "verify", "--dir", str(model_dir), "--precision", "int8", "--naip-dir", str(naip), cwd=tmp_path
    )
    record = json.loads((model_dir / VERIFICATION_NAME).read_text())["families"]["xfeat.int8"]
    assert (record["extractor"]["file"], record["matcher"]["file"]) == (extractor.file, matcher.file)
    assert record["min_identical_share"] == 0.95
    assert res.returncode == (0 if record["passed"] else 3), res.stderr
    assert record["passed"] or "refused: int8 xfeat differ from the PyTorch reference" in res.stderr


def test_vlad_xfeat_takes_the_fp32_extractor_when_an_int8_one_is_listed_first(tmp_path: Path) -> None:
    """``vlad_xfeat``'s vocabulary was learned on the fp32 descriptors: an int8 XFeat extractor listed
    before the fp32 one (a re-export appends the fp32 entry last) is not the one it takes."""
    from gps_denied_onboard.components.c2_vpr.learned_local import find_xfeat_extractor

    source = ModelSource("fake-xfeat", "0" * 64, "Apache-2.0", "https://example.invalid/xfeat")
    for name, extra in (("x.int8.onnx", {"precision": "int8"}), ("x.onnx", {})):
        (tmp_path / name).write_bytes(name.encode())
        params = {"family": "xfeat", "role": "extractor", **extra}
        write_manifest(tmp_path, ModelEntry(name, sha256_file(tmp_path / name), source, SIGNATURE, params))
    assert [e.file for e in read_manifest(tmp_path)] == ["x.int8.onnx", "x.onnx"]
    assert find_xfeat_extractor(tmp_path) == tmp_path / "x.onnx"
