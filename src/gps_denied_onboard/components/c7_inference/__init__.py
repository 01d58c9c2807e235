"""C7 inference: the ``InferenceRuntime`` contract and its ONNX Runtime implementation."""

from gps_denied_onboard.components.c7_inference.onnx_runtime import (
    PROVIDER_PREFERENCE,
    EngineInfo,
    OnnxInferenceRuntime,
    check_signature,
    resolve_providers,
)
from gps_denied_onboard.components.c7_inference.protocol import (
    EngineLoadError,
    EngineSignature,
    InferenceError,
    InferenceRuntime,
    TensorSpec,
)

__all__ = [
    "PROVIDER_PREFERENCE",
    "EngineInfo",
    "EngineLoadError",
    "EngineSignature",
    "InferenceError",
    "InferenceRuntime",
    "OnnxInferenceRuntime",
    "TensorSpec",
    "check_signature",
    "resolve_providers",
]
