"""C7 contract: a loaded inference engine, run by name with named numpy tensors.

The types are defined in ``helpers.inference_contract`` (below the components, for the shared helpers
and the exporters that speak them too); this module is C7's public face for them.
"""

from __future__ import annotations

from gps_denied_onboard.helpers.inference_contract import (
    EngineLoadError,
    EngineSignature,
    InferenceError,
    InferenceRuntime,
    TensorSpec,
)

__all__ = ["EngineLoadError", "EngineSignature", "InferenceError", "InferenceRuntime", "TensorSpec"]
