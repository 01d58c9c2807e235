"""``gdnav models quantize``: INT8 copies of a family's exported models, next to the fp32 files.

Build-time only (``onnx`` and ``onnxruntime.quantization``; no torch). Inputs: a model directory of
``gdnav models export`` and a family; outputs ``<stem>.int8.onnx`` for its extractor and its LightGlue
matcher, each recorded in ``manifest.json`` like an export (own sha256, the fp32 entry's source and
signature) with ``params.precision = "int8"``, ``params.quantized_from`` (the fp32 file) and its sha256.

How each role is quantised:

* **matcher** (LightGlue, LighterGlue; MatMul-bound): ``dynamic`` (default): dynamic quantisation of
  the MatMul weights (int8, per output column), activations quantised per call (integer MatMuls);
  ``weight_only``: int8 weights in blocks of 32 (``MatMulNBits``), dequantised and multiplied in fp32.
  The dynamo export feeds each Linear's weight through a ``Transpose``, which hides the weight from the
  quantiser; those transposes of initializers are folded into transposed initializers first.
  Attention's activation-by-activation MatMuls stay fp32.
* **extractor** (DISK, ALIKED, XFeat; Conv-bound): static quantisation of the Convs (QDQ, int8 weights per
  output channel, uint8 activations with MinMax ranges) calibrated on real images at the frame size.
  Dynamic quantisation does not fit a Conv net: ONNX Runtime's ``ConvInteger`` is slower than fp32 Conv.

A quantised file is used only where ``gdnav models verify --precision int8`` passed it (see
``reference_check``). Rule: the fp32 entries are never changed; a re-run replaces the int8 files.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from gps_denied_onboard.helpers.model_manifest import (
    PRECISION_INT8,
    ModelDirError,
    ModelEntry,
    verify_model_dir,
    write_manifest,
)
from gps_denied_onboard.models.export import ExportError
from gps_denied_onboard.models.learned_export import (
    FAMILIES,
    ROLE_EXTRACTOR,
    ROLE_MATCHER,
    family_models,
)
from gps_denied_onboard.models.registry import sha256_file

#: Suffix of a quantised file's name: ``disk_lightglue.onnx`` -> ``disk_lightglue.int8.onnx``.
INT8_SUFFIX: Final[str] = ".int8.onnx"
#: Calibration input size of a dynamic-size extractor (H, W): the daemon's 640 px long side, 4:3.
CALIBRATION_HW: Final[tuple[int, int]] = (480, 640)
#: What each role's quantisation is called in ``params.quantization``.
MATCHER_METHODS: Final[dict[str, str]] = {
    "dynamic": "dynamic_matmul_int8_per_channel",
    "weight_only": "matmul_nbits_int8_block32_fp32_compute",
}
#: Block of a ``weight_only`` weight that shares one scale (the smallest ``MatMulNBits`` allows is 16).
WEIGHT_ONLY_BLOCK: Final[int] = 32
EXTRACTOR_METHOD: Final[str] = "static_qdq_conv_int8_per_channel_minmax"

#: Extractor params copied from the fp32 entry that describe the file's behaviour (not its bytes).
_DROP_PARAMS: Final[tuple[str, ...]] = ("data_file", "data_sha256")


def int8_name(fp32_file: str) -> str:
    """The quantised file's name for an fp32 model file."""
    stem = fp32_file[: -len(".onnx")] if fp32_file.endswith(".onnx") else fp32_file
    return stem + INT8_SUFFIX


def fold_initializer_transposes(src: Path, dst: Path) -> int:
    """Copy ``src`` to ``dst`` (self-contained) with every ``Transpose`` of an initializer replaced by the
    transposed initializer, named ``<weight>.T`` (so that the quantiser sees the MatMul weights, and they
    keep their module names); returns how many were folded."""
    import onnx
    from onnx import numpy_helper

    try:
        model = onnx.load(str(src))
    except (onnx.checker.ValidationError, OSError, ValueError) as exc:  # e.g. weights behind a symlink
        raise ExportError(f"cannot read the model: {exc}", path=str(src)) from exc
    graph = model.graph
    inits = {init.name: init for init in graph.initializer}
    outputs = {o.name for o in graph.output}
    renamed: dict[str, str] = {}
    kept = []
    for node in graph.node:
        if node.op_type == "Transpose" and node.input[0] in inits:
            weight = numpy_helper.to_array(inits[node.input[0]])
            perm = next((list(a.ints) for a in node.attribute if a.name == "perm"), None)
            transposed = np.ascontiguousarray(weight.transpose(perm) if perm else weight.T)
            name = node.output[0]
            if name not in outputs:
                name = f"{node.input[0]}.T"
                while name in inits:
                    name += "_"
                renamed[node.output[0]] = name
            init = numpy_helper.from_array(transposed, name)
            inits[name] = init
            graph.initializer.append(init)
            continue
        kept.append(node)
    for node in kept:
        for i, name in enumerate(node.input):
            if name in renamed:
                node.input[i] = renamed[name]
    del graph.node[:]
    graph.node.extend(kept)
    used = {name for node in graph.node for name in node.input} | outputs
    live = [init for init in graph.initializer if init.name in used]
    del graph.initializer[:]
    graph.initializer.extend(live)
    onnx.save(model, str(dst), save_as_external_data=True, location=dst.name + ".data")
    return len(renamed)


def quantize_matcher(src: Path, dst: Path, method: str = "dynamic") -> None:
    """Int8 quantisation of a LightGlue-ONNX matcher's MatMul weights (see the module docstring)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    if method not in MATCHER_METHODS:
        raise ValueError(f"unknown matcher method {method!r}; valid: {', '.join(MATCHER_METHODS)}")
    with tempfile.TemporaryDirectory(prefix="gdnav-quantize-") as tmp:
        folded = Path(tmp) / "folded.onnx"
        fold_initializer_transposes(src, folded)
        if method == "weight_only":
            import logging

            import onnx
            from onnxruntime.quantization.matmul_nbits_quantizer import MatMulNBitsQuantizer

            # it logs a line per node at INFO
            logging.getLogger("onnxruntime.quantization.matmul_nbits_quantizer").setLevel(logging.WARNING)

            quantizer = MatMulNBitsQuantizer(
                onnx.load(str(folded)),
                bits=8,
                block_size=WEIGHT_ONLY_BLOCK,
                is_symmetric=True,
                accuracy_level=0,  # fp32 multiply: int8 activations cost LightGlue too many matches
            )
            quantizer.process()
            quantizer.model.save_model_to_file(str(dst), use_external_data_format=False)
            return
        quantize_dynamic(
            str(folded),
            str(dst),
            op_types_to_quantize=["MatMul"],
            per_channel=True,
            weight_type=QuantType.QInt8,
        )


def _calibration_tensors(
    images_rgb: Sequence[np.ndarray], hw: tuple[int, int], letterboxed: bool
) -> list[np.ndarray]:
    """(1, 3, H, W) float32 [0, 1] tensors: the top-left and centre H x W crops of each image (resized
    up first when smaller); ``letterboxed``: through ALIKED's own letterbox instead."""
    import cv2

    h, w = hw
    tensors = []
    for rgb in images_rgb:
        if letterboxed:
            from gps_denied_onboard.components.c3_matcher.aliked_lightglue import letterbox

            tensors.append(letterbox(np.ascontiguousarray(rgb[..., ::-1]), hw).tensor)
            continue
        if rgb.shape[0] < h or rgb.shape[1] < w:
            scale = max(h / rgb.shape[0], w / rgb.shape[1])
            size = (int(np.ceil(rgb.shape[1] * scale)), int(np.ceil(rgb.shape[0] * scale)))
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        rows, cols = rgb.shape[0] - h, rgb.shape[1] - w
        for r, c in ((0, 0), (rows // 2, cols // 2)):
            crop = rgb[r : r + h, c : c + w]
            tensors.append(np.ascontiguousarray((crop.transpose(2, 0, 1)[None] / 255.0).astype(np.float32)))
    return tensors


def quantize_extractor(src: Path, dst: Path, calibration: Sequence[np.ndarray]) -> None:
    """Static QDQ int8 quantisation of an extractor's Convs, calibrated on ``calibration`` tensors."""
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    class _Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self._feeds = iter([{"image": t} for t in calibration])

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self._feeds, None)

    quantize_static(
        str(src),
        str(dst),
        _Reader(),
        quant_format=QuantFormat.QDQ,
        op_types_to_quantize=["Conv"],
        per_channel=True,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        calibrate_method=CalibrationMethod.MinMax,
    )


def _int8_entry(root: Path, fp32: ModelEntry, file: str, method: str, extra: dict[str, Any]) -> ModelEntry:
    params = {k: v for k, v in fp32.params.items() if k not in _DROP_PARAMS}
    params.update(
        precision=PRECISION_INT8,
        quantization=method,
        quantized_from=fp32.file,
        quantized_from_sha256=fp32.sha256,
        **extra,
    )
    return ModelEntry(
        file=file,
        sha256=sha256_file(root / file),
        source=fp32.source,
        signature=fp32.signature,
        params=params,
    )


def _check_loads(path: Path, entry: ModelEntry) -> None:
    from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
    from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError

    runtime = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    try:
        runtime.load_engine(str(path), entry.signature)
    except EngineLoadError as exc:
        raise ExportError(f"quantised model is refused by the runtime: {exc}", path=str(path)) from exc


def quantize_family(
    model_dir: str | Path,
    family: str,
    calibration_rgb: Sequence[np.ndarray],
    *,
    roles: Sequence[str] = (ROLE_EXTRACTOR, ROLE_MATCHER),
    matcher_method: str = "dynamic",
    report: Callable[[str], None] | None = None,
) -> list[ModelEntry]:
    """Write int8 copies of ``family``'s fp32 ``roles`` into ``model_dir`` and its manifest; returns the
    new entries. ``calibration_rgb``: (H, W, 3) uint8 RGB images for the extractor's calibration;
    ``matcher_method``: a key of ``MATCHER_METHODS``.

    Raises ``ModelDirError`` (directory or manifest wrong, family not exported), ``ValueError`` (unknown
    family or role, no calibration image), ``ExportError`` (a result the runtime refuses), ``ImportError``
    (``onnx`` missing).
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown model family {family!r}; valid: {', '.join(FAMILIES)}")
    unknown = [r for r in roles if r not in (ROLE_EXTRACTOR, ROLE_MATCHER)]
    if unknown:
        raise ValueError(f"unknown role(s) {unknown}; valid: {ROLE_EXTRACTOR}, {ROLE_MATCHER}")
    if matcher_method not in MATCHER_METHODS:
        raise ValueError(f"unknown matcher method {matcher_method!r}; valid: {', '.join(MATCHER_METHODS)}")
    root = Path(model_dir)
    entries = verify_model_dir(root)
    found = family_models(entries, family)
    if found is None:
        raise ModelDirError(
            f"no fp32 {family} extractor + matcher in the manifest (run gdnav models export --family "
            f"{family} --out {root})",
            path=str(root),
        )
    extractor, matcher = found
    written: list[ModelEntry] = []
    if ROLE_EXTRACTOR in roles:
        if not calibration_rgb:
            raise ValueError("no calibration image for the extractor's static quantisation")
        fixed = "height" in extractor.params and "width" in extractor.params
        hw = (int(extractor.params["height"]), int(extractor.params["width"])) if fixed else CALIBRATION_HW
        tensors = _calibration_tensors(calibration_rgb, hw, letterboxed=fixed)
        name = int8_name(extractor.file)
        quantize_extractor(root / extractor.file, root / name, tensors)
        entry = _int8_entry(root, extractor, name, EXTRACTOR_METHOD, {"calibration_tensors": len(tensors)})
        _check_loads(root / name, entry)
        written.append(entry)
    if ROLE_MATCHER in roles:
        name = int8_name(matcher.file)
        quantize_matcher(root / matcher.file, root / name, matcher_method)
        entry = _int8_entry(root, matcher, name, MATCHER_METHODS[matcher_method], {})
        _check_loads(root / name, entry)
        written.append(entry)
    for entry in written:
        write_manifest(root, entry)
        if report is not None:
            report(
                f"quantised {root / entry.file} ({entry.params['role']}, {entry.params['quantization']}, "
                f"from {entry.params['quantized_from']}, sha256 {entry.sha256[:12]})"
            )
    return written
