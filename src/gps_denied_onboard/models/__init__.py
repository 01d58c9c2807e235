"""Pretrained models: pinned weights (registry), ONNX export (build-time, needs torch), model manifest.

Importing this package never imports torch: ``aliked_torch`` (the network) is only imported by the
exporter and the tests.
"""

from gps_denied_onboard.helpers.model_manifest import (
    MANIFEST_NAME,
    ModelDirError,
    ModelEntry,
    ModelSource,
    read_manifest,
    verify_model_dir,
    write_manifest,
)
from gps_denied_onboard.models.export import (
    ALIKED_EXTRACTOR_SIGNATURE,
    ExportError,
    default_onnx_name,
    export_aliked_onnx,
)
from gps_denied_onboard.models.registry import (
    KNOWN_WEIGHTS,
    KnownWeights,
    WeightsError,
    WeightsFetchError,
    WeightsHashMismatchError,
    fetch_weights,
    import_weights,
    sha256_file,
)

__all__ = [
    "ALIKED_EXTRACTOR_SIGNATURE",
    "KNOWN_WEIGHTS",
    "MANIFEST_NAME",
    "ExportError",
    "KnownWeights",
    "ModelDirError",
    "ModelEntry",
    "ModelSource",
    "WeightsError",
    "WeightsFetchError",
    "WeightsHashMismatchError",
    "default_onnx_name",
    "export_aliked_onnx",
    "fetch_weights",
    "import_weights",
    "read_manifest",
    "sha256_file",
    "verify_model_dir",
    "write_manifest",
]
