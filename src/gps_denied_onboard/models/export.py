"""Export official ALIKED weights to an ONNX extractor (LightGlue-ONNX layout) and record it in the manifest.

Build-time only: needs the ``export`` extra (torch). torch is imported inside ``export_aliked_onnx`` so that
importing this module (e.g. for ``ALIKED_EXTRACTOR_SIGNATURE``) stays torch-free.

ONNX file, opset 17 (deformable convs are decomposed into ``GridSample``; no custom or opset-19 ops):

* input ``image``: ``(1, 3, H, W)`` float32 RGB in [0, 1]; H and W multiples of 32 and ``H*W >= top_k``
  (fixed when exported with ``height``/``width``, else dynamic axes ``height``/``width``);
* ``keypoints``: ``(1, N, 2)`` float32, pixel ``(x, y)`` of the input image, sub-pixel;
* ``scores``: ``(1, N)`` float32 in [0, 1];
* ``descriptors``: ``(1, N, D)`` float32, L2-normalised, D = 64 (t16) or 128 (n16); N = ``top_k``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from gps_denied_onboard.components.c7_inference.protocol import EngineSignature, TensorSpec
from gps_denied_onboard.helpers.model_manifest import ModelEntry, ModelSource, write_manifest
from gps_denied_onboard.models.registry import (
    KNOWN_WEIGHTS,
    WeightsError,
    WeightsHashMismatchError,
    sha256_file,
)

OPSET = 17
SIZE_MULTIPLE = 32  # mirrors aliked_torch.SIZE_MULTIPLE without importing torch
DESCRIPTOR_DIM = {"t16": 64, "n16": 128}
_DYNAMIC_PROBE_HW = (480, 640)  # trace size for dynamic exports

ALIKED_EXTRACTOR_SIGNATURE = EngineSignature(
    label="aliked extractor (LightGlue-ONNX layout)",
    inputs=(TensorSpec("image", 4, "float32"),),
    outputs=(
        TensorSpec("keypoints", 3, "float32"),
        TensorSpec("scores", 2, "float32"),
        TensorSpec("descriptors", 3, "float32"),
    ),
)


class ExportError(RuntimeError):
    """The export failed or its result does not load/run in ONNX Runtime."""

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path


def default_onnx_name(variant: str, top_k: int, height: int | None, width: int | None) -> str:
    """Conventional file name, e.g. ``aliked-t16-480x640-k1024.onnx`` or ``aliked-t16-dyn-k1024.onnx``."""
    size = f"{height}x{width}" if height is not None else "dyn"
    return f"aliked-{variant}-{size}-k{top_k}.onnx"


def _check_size(height: int | None, width: int | None, top_k: int) -> None:
    if (height is None) != (width is None):
        raise ValueError(f"give both height and width or neither (dynamic), got {height=} {width=}")
    if height is None or width is None:
        return
    if height <= 0 or width <= 0 or height % SIZE_MULTIPLE or width % SIZE_MULTIPLE:
        raise ValueError(
            f"height and width must be positive multiples of {SIZE_MULTIPLE}, got {height}x{width}"
        )
    if height * width < top_k:
        raise ValueError(f"top_k={top_k} exceeds the {height}x{width} pixels")


def _source_for(weights_path: Path, variant: str) -> ModelSource:
    """The pinned registry entry for these weights; refuses unknown or mismatched files."""
    entry = KNOWN_WEIGHTS.get(f"aliked-{variant}")
    if entry is None:
        raise ValueError(f"unknown ALIKED variant {variant!r}; valid: {sorted(DESCRIPTOR_DIM)}")
    if not weights_path.is_file():
        raise WeightsError("weights file not found", path=str(weights_path))
    actual = sha256_file(weights_path)
    if actual != entry.sha256:
        raise WeightsHashMismatchError(path=str(weights_path), expected=entry.sha256, actual=actual)
    return ModelSource(name=entry.name, sha256=entry.sha256, licence=entry.licence, url=entry.url)


def _fix_output_shapes(out_path: Path, top_k: int, dim: int) -> None:
    """Write the static output sizes into the graph (the tracer leaves N and D as symbolic names)."""
    import onnx

    model = onnx.load(str(out_path))
    static = {"keypoints": (1, top_k, 2), "scores": (1, top_k), "descriptors": (1, top_k, dim)}
    for output in model.graph.output:
        dims = output.type.tensor_type.shape.dim
        for axis, size in enumerate(static[output.name]):
            dims[axis].Clear()
            dims[axis].dim_value = size
    onnx.save(model, str(out_path))


def _check_onnx(out_path: Path, variant: str, top_k: int, height: int, width: int) -> None:
    """Load the file with the ONNX checker and an ORT CPU session; run once and check output shapes."""
    import numpy as np
    import onnx
    import onnxruntime as ort

    try:
        onnx.checker.check_model(str(out_path))
        session = ort.InferenceSession(str(out_path), providers=["CPUExecutionProvider"])
        image = np.random.default_rng(0).random((1, 3, height, width), dtype=np.float32)
        keypoints, scores, descriptors = session.run(None, {"image": image})
    except Exception as exc:  # any ONNX/ORT failure means the export is unusable
        raise ExportError(
            f"exported model does not load/run in ONNX Runtime CPU: {exc}", path=str(out_path)
        ) from exc
    expected = {
        "keypoints": (1, top_k, 2),
        "scores": (1, top_k),
        "descriptors": (1, top_k, DESCRIPTOR_DIM[variant]),
    }
    got = {"keypoints": keypoints.shape, "scores": scores.shape, "descriptors": descriptors.shape}
    if got != expected:
        raise ExportError(f"output shapes {got} differ from {expected}", path=str(out_path))


def export_aliked_onnx(
    weights_path: str | Path,
    out_path: str | Path,
    *,
    variant: str = "t16",
    top_k: int = 1024,
    height: int | None = None,
    width: int | None = None,
    manifest: bool = True,
) -> Path:
    """Export pinned ALIKED weights to an ONNX extractor, verify it in ORT CPU, record it in the manifest.

    Args:
        weights_path: official ``aliked-<variant>.pth``; its sha256 must equal the registry pin.
        out_path: ONNX file to write; its directory is the model directory (created if needed). Must be
            outside the git tree (weights-derived files are never committed).
        variant: ``"t16"`` or ``"n16"``.
        top_k: fixed number of keypoints N.
        height, width: fixed input size (multiples of 32), or both None for dynamic height/width.
        manifest: also add/replace the file's entry in ``<dir>/manifest.json``.

    Returns:
        ``out_path``.

    Raises:
        ValueError: bad variant/size/top_k. WeightsError / WeightsHashMismatchError: weights missing or not
        pinned. ExportError: the ONNX file fails to load or run in ONNX Runtime.
    """
    weights = Path(weights_path)
    out = Path(out_path)
    if top_k <= 0:
        raise ValueError(f"top_k must be positive, got {top_k}")
    _check_size(height, width, top_k)
    source = _source_for(weights, variant)  # validated before torch is imported: cheap, clear failures

    import torch

    from gps_denied_onboard.models.aliked_torch import load_aliked

    model = load_aliked(weights, variant, top_k=top_k)
    trace_hw = (height, width) if height is not None and width is not None else _DYNAMIC_PROBE_HW
    dummy = torch.rand(1, 3, *trace_hw)
    dynamic_axes = None if height is not None else {"image": {2: "height", 3: "width"}}
    out.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of dynamo, which needs onnxscript; it is the one
        # that is available here and it handles the GridSample/TopK graph well.
        warnings.simplefilter("ignore", category=DeprecationWarning)
        warnings.simplefilter("ignore", category=torch.jit.TracerWarning)
        # "Only steps=1 can be constant folded" comes from the flip of the (H, W) shape: harmless.
        warnings.filterwarnings("ignore", message="Constant folding", category=UserWarning)
        torch.onnx.export(
            model,
            (dummy,),
            str(out),
            dynamo=False,
            opset_version=OPSET,
            input_names=["image"],
            output_names=["keypoints", "scores", "descriptors"],
            dynamic_axes=dynamic_axes,
            do_constant_folding=True,
        )
    _fix_output_shapes(out, top_k, DESCRIPTOR_DIM[variant])
    _check_onnx(out, variant, top_k, *trace_hw)
    if manifest:
        write_manifest(
            out.parent,
            ModelEntry(
                file=out.name,
                sha256=sha256_file(out),
                source=source,
                signature=ALIKED_EXTRACTOR_SIGNATURE,
                params={
                    "variant": variant,
                    "top_k": top_k,
                    "height": height,
                    "width": width,
                    "opset": OPSET,
                    "torch": torch.__version__,
                },
            ),
        )
    return out
