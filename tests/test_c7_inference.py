"""C7 OnnxInferenceRuntime: real ONNX Runtime sessions on models the tests build themselves."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from structlog.testing import capture_logs

from gps_denied_onboard.components.c7_inference import (
    EngineLoadError,
    EngineSignature,
    InferenceError,
    InferenceRuntime,
    OnnxInferenceRuntime,
    TensorSpec,
    resolve_providers,
)
from gps_denied_onboard.components.c7_inference.onnx_runtime import ORT_FAULT_FILE_ENV, session_options
from gps_denied_onboard.constants import LogEvent
from gps_denied_onboard.helpers.onnx_signatures import (
    ALIKED_EXTRACTOR,
    DISK_EXTRACTOR,
    FUSED_PIPELINE,
    LIGHTGLUE_MATCHER,
    XFEAT_EXTRACTOR,
)
from onnx_builders import (
    build_disk_like_stub,
    build_fake_extractor,
    build_fake_lightglue,
    build_fused_pipeline,
    build_reshape_model,
    build_stub_model,
)

RESHAPE_SIGNATURE = EngineSignature(
    label="reshape",
    inputs=(TensorSpec("x", 2, "float32"),),
    outputs=(TensorSpec("y", 2, "float32"),),
)


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("c7_models")
    return {
        "disk": build_fake_extractor(d / "disk.onnx", dim=128, num_keypoints=64),
        "disk_f32": build_fake_extractor(
            d / "disk_f32.onnx", dim=128, num_keypoints=64, keypoint_dtype="float32"
        ),
        "xfeat_grey": build_fake_extractor(d / "xfeat.onnx", channels=1, dim=64, num_keypoints=32),
        "lightglue": build_fake_lightglue(d / "lg.onnx", 128),
        "fused": build_fused_pipeline(d / "fused.onnx"),
        "reshape": build_reshape_model(d / "reshape.onnx"),
    }


@pytest.fixture
def runtime() -> OnnxInferenceRuntime:
    return OnnxInferenceRuntime(intra_op_threads=1)


def test_runtime_satisfies_protocol(runtime: OnnxInferenceRuntime) -> None:
    """OnnxInferenceRuntime is an InferenceRuntime."""
    assert isinstance(runtime, InferenceRuntime)


def test_load_engine_matching_signature_returns_engine_on_cpu(runtime, models) -> None:
    """A model matching its signature loads; on this machine the provider in use is CPU."""
    engine_id = runtime.load_engine(str(models["disk"]), DISK_EXTRACTOR)
    assert engine_id.startswith("disk#")
    assert runtime.provider(engine_id) == "CPUExecutionProvider"
    info = runtime.engine_info(engine_id)
    assert info.path == str(models["disk"])
    assert [s.name for s in info.outputs] == ["keypoints", "scores", "descriptors"]
    assert info.outputs[2].shape == (1, None, 128)


def test_load_engine_logs_provider_inputs_outputs_and_time(runtime, models) -> None:
    """engine_loaded is logged once with path, provider, inputs, outputs and load_ms."""
    with capture_logs() as logs:
        runtime.load_engine(str(models["disk"]), DISK_EXTRACTOR)
    loaded = [e for e in logs if e["event"] == LogEvent.C7_ENGINE_LOADED]
    assert len(loaded) == 1
    event = loaded[0]
    assert event["path"] == str(models["disk"])
    assert event["provider"] == "CPUExecutionProvider"
    assert event["inputs"] == {"image": ["float32", [1, 3, None, None]]}
    assert set(event["outputs"]) == {"keypoints", "scores", "descriptors"}
    assert event["load_ms"] > 0
    assert event["intra_op_threads"] == 1


def test_session_options_default_no_spinning_and_configured_threads() -> None:
    """The CPU session options: threads as given, sequential, ALL optimisations, arena, no spin-waiting."""
    opts = session_options(2)
    assert opts.intra_op_num_threads == 2 and opts.inter_op_num_threads == 1
    assert opts.execution_mode == ort.ExecutionMode.ORT_SEQUENTIAL
    assert opts.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert opts.enable_cpu_mem_arena and opts.enable_mem_pattern
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert opts.get_session_config_entry("session.inter_op.allow_spinning") == "0"
    spinning = session_options(1, allow_spinning=True)
    assert spinning.get_session_config_entry("session.intra_op.allow_spinning") == "1"
    with pytest.raises(ValueError, match="intra_op_threads"):
        session_options(0)


def test_load_engine_reports_and_logs_its_session_options(models) -> None:
    """engine_info and engine_loaded name the session options the engine runs with."""
    rt = OnnxInferenceRuntime(intra_op_threads=2)
    with capture_logs() as logs:
        info = rt.engine_info(rt.load_engine(str(models["disk"]), DISK_EXTRACTOR))
    fields = dict(info.session_options)
    assert fields["intra_op_num_threads"] == "2"
    assert fields["session.intra_op.allow_spinning"] == "0"
    (event,) = [e for e in logs if e["event"] == LogEvent.C7_ENGINE_LOADED]
    assert event["session_options"] == fields
    spinning = OnnxInferenceRuntime(intra_op_threads=1, allow_spinning=True)
    info = spinning.engine_info(spinning.load_engine(str(models["disk"]), DISK_EXTRACTOR))
    assert dict(info.session_options)["session.intra_op.allow_spinning"] == "1"


def test_load_engine_warmup_runs_small_image(runtime, models) -> None:
    """The warm-up ran on a 1x3x64x64 dummy image (batch fixed at 1 by the model)."""
    info = runtime.engine_info(runtime.load_engine(str(models["disk"]), DISK_EXTRACTOR))
    assert info.warmup == "ok"
    assert dict(info.warmup_shapes) == {"image": (1, 3, 64, 64)}


def test_load_engine_warmup_keeps_static_channel_dim(runtime, models) -> None:
    """A grey (C=1) model is warmed up with one channel, not three."""
    info = runtime.engine_info(runtime.load_engine(str(models["xfeat_grey"]), XFEAT_EXTRACTOR))
    assert info.warmup == "ok"
    assert dict(info.warmup_shapes) == {"image": (1, 1, 64, 64)}


def test_load_engine_warmup_fused_pipeline_uses_even_batch(runtime, models) -> None:
    """The fused pipeline (2B images) warms up with a pair, so its Reshape to pairs succeeds."""
    info = runtime.engine_info(runtime.load_engine(str(models["fused"]), FUSED_PIPELINE))
    assert info.warmup == "ok"
    assert dict(info.warmup_shapes) == {"images": (2, 3, 64, 64)}


def test_load_engine_warmup_matcher_uses_consistent_counts(runtime, models) -> None:
    """The matcher warms up with kpts and desc sharing N."""
    info = runtime.engine_info(runtime.load_engine(str(models["lightglue"]), LIGHTGLUE_MATCHER))
    assert info.warmup == "ok"
    assert dict(info.warmup_shapes) == {
        "kpts0": (1, 8, 2),
        "kpts1": (1, 8, 2),
        "desc0": (1, 8, 128),
        "desc1": (1, 8, 128),
    }


def test_load_engine_warmup_skipped_for_unguessable_input(runtime, tmp_path) -> None:
    """A string input cannot be faked: the model loads, warm-up is skipped and says why."""
    path = build_stub_model(tmp_path / "s.onnx", [("text", "string", [1])], [("y", "float32", [1])])
    with capture_logs() as logs:
        info = runtime.engine_info(runtime.load_engine(str(path)))
    assert info.warmup.startswith("skipped: input 'text' has dtype str")
    assert any(e["event"] == LogEvent.C7_WARMUP_SKIPPED for e in logs)


def test_load_engine_warmup_failure_is_reported_not_fatal(runtime, models) -> None:
    """A model that rejects the dummy shape still loads; the failure is logged."""
    with capture_logs() as logs:
        engine_id = runtime.load_engine(str(models["reshape"]), RESHAPE_SIGNATURE)
    info = runtime.engine_info(engine_id)
    assert info.warmup.startswith("failed:")
    assert dict(info.warmup_shapes) == {"x": (1, 8)}
    assert any(e["event"] == LogEvent.C7_WARMUP_FAILED for e in logs)


def test_load_engine_warmup_disabled(models) -> None:
    """warmup=False runs no dummy pass."""
    rt = OnnxInferenceRuntime(intra_op_threads=1, warmup=False)
    info = rt.engine_info(rt.load_engine(str(models["disk"]), DISK_EXTRACTOR))
    assert info.warmup == "disabled"
    assert info.warmup_shapes == ()


@pytest.mark.parametrize("model", ["disk", "disk_f32"])
def test_load_engine_keypoints_int64_or_float32_accepted(runtime, models, model) -> None:
    """Both keypoint dtypes found in LightGlue-ONNX exports pass the extractor signature."""
    assert runtime.load_engine(str(models[model]), DISK_EXTRACTOR)


def test_load_engine_wrong_rank_and_dtype_names_file_and_mismatch(runtime, tmp_path) -> None:
    """descriptors rank 2 float16 -> EngineLoadError naming the file and the exact mismatch."""
    path = build_disk_like_stub(tmp_path / "bad.onnx", descriptors=("descriptors", "float16", [1, "N"]))
    with pytest.raises(EngineLoadError) as err:
        runtime.load_engine(str(path), DISK_EXTRACTOR)
    assert err.value.path == str(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ")
    assert "output 'descriptors': expected rank 3 float32, model has rank 2 float16" in message


def test_load_engine_wrong_output_name_is_missing_output(runtime, tmp_path) -> None:
    """An output named differently is reported missing, with the model's actual outputs listed."""
    path = build_disk_like_stub(tmp_path / "bad.onnx", descriptors=("desc", "float32", [1, "N", 128]))
    with pytest.raises(EngineLoadError, match=r"output 'descriptors': missing \(model outputs: \['desc'"):
        runtime.load_engine(str(path), DISK_EXTRACTOR)


def test_load_engine_wrong_input_dtype_is_rejected(runtime, tmp_path) -> None:
    """A uint8 image input does not match the float32 extractor signature."""
    path = build_disk_like_stub(tmp_path / "bad.onnx", image=("image", "uint8", [1, 3, "H", "W"]))
    with pytest.raises(
        EngineLoadError, match="input 'image': expected rank 4 float32, model has rank 4 uint8"
    ):
        runtime.load_engine(str(path), DISK_EXTRACTOR)


def test_load_engine_fixed_dim_mismatch_is_rejected(runtime, tmp_path) -> None:
    """256-d descriptors are refused by the DISK (D=128) signature."""
    path = build_disk_like_stub(tmp_path / "bad.onnx", descriptors=("descriptors", "float32", [1, "N", 256]))
    with pytest.raises(EngineLoadError, match="output 'descriptors': dim 2 expected 128, model has 256"):
        runtime.load_engine(str(path), DISK_EXTRACTOR)


def test_load_engine_unfed_model_input_is_rejected(runtime, tmp_path) -> None:
    """A model that needs an input the signature does not feed is refused."""
    path = build_disk_like_stub(tmp_path / "bad.onnx", extra_inputs=[("mask", "float32", [1, "H", "W"])])
    with pytest.raises(
        EngineLoadError, match="input 'mask': required by the model but not in signature 'disk'"
    ):
        runtime.load_engine(str(path), DISK_EXTRACTOR)


def test_load_engine_reports_every_mismatch(runtime, tmp_path) -> None:
    """Several mismatches are all listed, not only the first."""
    path = build_disk_like_stub(
        tmp_path / "bad.onnx", scores=None, keypoints=("keypoints", "float16", [1, "N", 2])
    )
    with pytest.raises(EngineLoadError) as err:
        runtime.load_engine(str(path), DISK_EXTRACTOR)
    assert "output 'keypoints': expected rank 3 int64|float32, model has rank 3 float16" in str(err.value)
    assert "output 'scores': missing" in str(err.value)


def test_load_engine_extra_model_outputs_accepted(runtime, tmp_path) -> None:
    """Outputs beyond the signature are fine."""
    path = build_disk_like_stub(
        tmp_path / "ok.onnx", extra_outputs=[("heatmap", "float32", [1, 1, "H", "W"])]
    )
    engine_id = runtime.load_engine(str(path), DISK_EXTRACTOR)
    assert "heatmap" in runtime.run(engine_id, {"image": np.zeros((1, 3, 16, 16), np.float32)})


def test_load_engine_matcher_as_extractor_rejected(runtime, models) -> None:
    """Loading the matcher where the extractor is expected names the missing input."""
    with pytest.raises(EngineLoadError, match="input 'image': missing"):
        runtime.load_engine(str(models["lightglue"]), ALIKED_EXTRACTOR)


def test_load_engine_missing_file(runtime, tmp_path) -> None:
    """A missing model file is an EngineLoadError naming the path."""
    path = tmp_path / "nope.onnx"
    with pytest.raises(EngineLoadError, match="model file not found") as err:
        runtime.load_engine(str(path), DISK_EXTRACTOR)
    assert err.value.path == str(path)


def test_load_engine_directory_path(runtime, tmp_path) -> None:
    """A directory is not a model file."""
    with pytest.raises(EngineLoadError, match="is a directory"):
        runtime.load_engine(str(tmp_path), DISK_EXTRACTOR)


def test_load_engine_corrupt_file_chained(runtime, tmp_path) -> None:
    """Random bytes are refused with the ORT error chained."""
    path = tmp_path / "corrupt.onnx"
    path.write_bytes(np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(EngineLoadError, match="cannot create an ONNX Runtime session") as err:
        runtime.load_engine(str(path), DISK_EXTRACTOR)
    assert err.value.path == str(path)
    assert err.value.__cause__ is not None


def test_run_outputs_follow_dynamic_image_size(runtime, models) -> None:
    """N depends on H, W: a small image yields fewer keypoints; dtypes and ranks as declared."""
    engine_id = runtime.load_engine(str(models["disk"]), DISK_EXTRACTOR)
    rng = np.random.default_rng(0)
    small = runtime.run(engine_id, {"image": rng.random((1, 3, 24, 20), dtype=np.float32)})
    large = runtime.run(engine_id, {"image": rng.random((1, 3, 96, 128), dtype=np.float32)})
    assert small["keypoints"].shape == (1, 20, 2)  # 5 x 4 grid cells, under the cap of 64
    assert large["keypoints"].shape == (1, 64, 2)
    assert small["keypoints"].dtype == np.int64
    assert large["descriptors"].shape == (1, 64, 128)
    assert large["scores"].dtype == np.float32


def test_run_runtime_error_raises_inference_error_chained(runtime, models) -> None:
    """An ORT failure during run becomes InferenceError with the cause chained."""
    engine_id = runtime.load_engine(str(models["reshape"]), RESHAPE_SIGNATURE)
    ok = runtime.run(engine_id, {"x": np.arange(6, dtype=np.float32)[None]})
    assert ok["y"].shape == (2, 3)
    with pytest.raises(
        InferenceError,
        match=r"engine 'reshape#\d+' \(.*reshape\.onnx\) failed on inputs \{'x': 'float32\[1, 5\]'\}",
    ) as err:
        runtime.run(engine_id, {"x": np.arange(5, dtype=np.float32)[None]})
    assert err.value.__cause__ is not None


def test_run_wrong_dtype_raises_inference_error(runtime, models) -> None:
    """A float64 feed is reported as InferenceError, not a raw ORT exception."""
    engine_id = runtime.load_engine(str(models["reshape"]), RESHAPE_SIGNATURE)
    with pytest.raises(InferenceError, match="float64"):
        runtime.run(engine_id, {"x": np.zeros((1, 6), np.float64)})


def test_run_missing_input_raises_inference_error(runtime, models) -> None:
    """Missing inputs are named."""
    engine_id = runtime.load_engine(str(models["lightglue"]), LIGHTGLUE_MATCHER)
    with pytest.raises(InferenceError, match=r"missing inputs \['desc1', 'kpts1'\]"):
        runtime.run(
            engine_id, {"kpts0": np.zeros((1, 2, 2), np.float32), "desc0": np.zeros((1, 2, 128), np.float32)}
        )


def test_run_unknown_engine_id_raises_inference_error(runtime) -> None:
    """An engine id that was never loaded is an InferenceError."""
    with pytest.raises(InferenceError, match="unknown engine id 'ghost'"):
        runtime.run("ghost", {})
    with pytest.raises(InferenceError):
        runtime.provider("ghost")


def test_engine_ids_unique_per_load(runtime, models) -> None:
    """Loading the same file twice gives two engines."""
    a = runtime.load_engine(str(models["disk"]), DISK_EXTRACTOR)
    b = runtime.load_engine(str(models["disk"]), DISK_EXTRACTOR)
    assert a != b


def test_run_concurrent_callers_get_their_own_results(runtime, models) -> None:
    """Calls from several threads on one engine are serialised and each gets its own outputs."""
    engine_id = runtime.load_engine(str(models["reshape"]), RESHAPE_SIGNATURE)
    results: dict[int, np.ndarray] = {}

    def call(i: int) -> None:
        x = np.full((1, 30), float(i), np.float32)
        results[i] = runtime.run(engine_id, {"x": x})["y"]

    threads = [threading.Thread(target=call, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(np.all(results[i] == i) for i in range(6))


def test_resolve_providers_prefers_trt_cuda_cpu_filtered_by_availability() -> None:
    """Default order is TensorRT -> CUDA -> CPU with unavailable ones dropped (CPU only here)."""
    import onnxruntime as ort

    available = set(ort.get_available_providers())
    expected = tuple(
        p
        for p in ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")
        if p in available
    )
    assert resolve_providers() == expected
    assert "AzureExecutionProvider" not in resolve_providers()


def test_resolve_providers_none_available_raises() -> None:
    """Asking only for providers this build lacks is a clear error."""
    with pytest.raises(ValueError, match="none of the execution providers"):
        OnnxInferenceRuntime(providers=["NoSuchExecutionProvider"])


def test_fault_hook_makes_onnx_runtime_itself_refuse_runs_then_recover(
    models, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The SITL's ORT fault: with the hook's file holding 2, the next two runs raise ONNX Runtime's own
    Fail from inside the real session (chained into InferenceError), the file is consumed, and the same
    session answers correctly afterwards. Without the variable nothing is injected."""
    fault_file = tmp_path / "ort_fault"
    monkeypatch.setenv(ORT_FAULT_FILE_ENV, str(fault_file))
    with capture_logs() as logs:
        runtime = OnnxInferenceRuntime(intra_op_threads=1)
    assert any(e["event"] == LogEvent.C7_FAULT_HOOK_ARMED for e in logs)
    engine_id = runtime.load_engine(str(models["reshape"]), RESHAPE_SIGNATURE)
    feed = {"x": np.arange(6, dtype=np.float32)[None]}
    assert runtime.run(engine_id, feed)["y"].shape == (2, 3)
    fault_file.write_text("2")
    for left in ("1", None):
        with pytest.raises(InferenceError, match="terminate flag") as err:
            runtime.run(engine_id, feed)
        assert type(err.value.__cause__).__module__.startswith("onnxruntime"), type(err.value.__cause__)
        assert (fault_file.read_text() if fault_file.exists() else None) == left
    np.testing.assert_array_equal(
        runtime.run(engine_id, feed)["y"], np.arange(6, dtype=np.float32).reshape(2, 3)
    )
    monkeypatch.delenv(ORT_FAULT_FILE_ENV)
    unarmed = OnnxInferenceRuntime(intra_op_threads=1)
    fault_file.write_text("1")
    engine_id = unarmed.load_engine(str(models["reshape"]), RESHAPE_SIGNATURE)
    assert unarmed.run(engine_id, feed)["y"].shape == (2, 3)
    assert fault_file.exists()
