"""``gdnav models export`` from the registry packages: DISK, ALIKED and XFeat extractors with their LightGlue.

Each *family* is an extractor and the LightGlue matcher trained on its descriptors, in the LightGlue-ONNX
separate layout that ``helpers.lightglue_runtime`` and the C3 strategies read:

=========  ====================================  ===========================================
family     extractor (``image`` -> kpts/scores/desc)  matcher (``kpts0/1``, ``desc0/1`` -> matches)
=========  ====================================  ===========================================
disk       ``disk-k2048.onnx`` (dynamic H/W, x16)     ``disk_lightglue.onnx`` (+ ``.onnx.data``)
aliked     ``aliked-n16-480x640-k2048.onnx`` (fixed)  ``aliked_lightglue.onnx`` (+ ``.onnx.data``)
xfeat      ``xfeat-k2048.onnx`` (dynamic H/W, x32)    ``xfeat_lighterglue.onnx`` (+ ``.onnx.data``)
=========  ====================================  ===========================================

The weights are the pinned files of ``registry.PACKAGE_WEIGHTS`` (refused when their sha256 differs); the
torch modules are built in ``models.learned_torch``. Every file is loaded back through the daemon's own
C7 runtime with its signature before it is recorded in ``manifest.json`` with its sha256 (and that of its
external weights), the source weights' name, sha256 and licence, and the export parameters
(``params.family`` / ``params.role`` say which file is which).

Importing this module does not import torch (compose uses ``family_models``).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from gps_denied_onboard.helpers.inference_contract import EngineSignature
from gps_denied_onboard.helpers.model_manifest import (
    PRECISION_FP32,
    ModelEntry,
    ModelSource,
    entry_precision,
    write_manifest,
)
from gps_denied_onboard.helpers.onnx_signatures import extractor_signature, lightglue_matcher_signature
from gps_denied_onboard.models.export import ExportError, export_aliked_onnx
from gps_denied_onboard.models.package_weights import package_weights_path
from gps_denied_onboard.models.registry import PACKAGE_WEIGHTS, sha256_file

#: Families in the order ``matcher.strategy: auto`` prefers them (the seed's default first).
FAMILIES: Final[tuple[str, ...]] = ("disk", "aliked", "xfeat")
#: Keypoints per image (the issue's measurements used 2048).
DEFAULT_TOP_K: Final[int] = 2048
#: ALIKED is exact only at a fixed input size (``models.export``): the frame size of the profiles.
ALIKED_INPUT_HW: Final[tuple[int, int]] = (480, 640)
#: Opsets: the legacy exporter for the extractors, the dynamo exporter for LightGlue.
EXTRACTOR_OPSET: Final[int] = 17
MATCHER_OPSET: Final[int] = 18
ROLE_EXTRACTOR: Final[str] = "extractor"
ROLE_MATCHER: Final[str] = "matcher"
#: C3 strategy that runs each family.
FAMILY_STRATEGY: Final[dict[str, str]] = {
    "disk": "disk_lightglue",
    "aliked": "aliked_lightglue",
    "xfeat": "xfeat",
}


@dataclass(frozen=True)
class FamilySpec:
    """What one family exports: weights names (``PACKAGE_WEIGHTS`` keys), file names, signatures."""

    family: str
    extractor_weights: str
    matcher_weights: str
    extractor_file: str
    matcher_file: str
    extractor_signature: EngineSignature
    matcher_signature: EngineSignature
    descriptor_dim: int


def family_spec(family: str, top_k: int = DEFAULT_TOP_K) -> FamilySpec:
    """The export spec of ``family``; ``ValueError`` naming the valid ones."""
    h, w = ALIKED_INPUT_HW
    table = {
        "disk": FamilySpec(
            "disk",
            "disk-depth",
            "disk-lightglue",
            f"disk-k{top_k}.onnx",
            "disk_lightglue.onnx",
            extractor_signature("disk", channels=3, descriptor_dim=128),
            lightglue_matcher_signature(128, label="disk_lightglue"),
            128,
        ),
        "aliked": FamilySpec(
            "aliked",
            "aliked-n16-package",
            "aliked-lightglue",
            f"aliked-n16-{h}x{w}-k{top_k}.onnx",
            "aliked_lightglue.onnx",
            extractor_signature("aliked", channels=3, descriptor_dim=128),
            lightglue_matcher_signature(128, label="aliked_lightglue"),
            128,
        ),
        "xfeat": FamilySpec(
            "xfeat",
            "xfeat",
            "xfeat-lighterglue",
            f"xfeat-k{top_k}.onnx",
            "xfeat_lighterglue.onnx",
            extractor_signature("xfeat", channels=3, descriptor_dim=64),
            lightglue_matcher_signature(64, label="xfeat_lighterglue"),
            64,
        ),
    }
    if family not in table:
        raise ValueError(f"unknown model family {family!r}; valid: {', '.join(FAMILIES)}")
    return table[family]


def family_models(
    entries: Iterable[ModelEntry], family: str, precision: str = PRECISION_FP32
) -> tuple[ModelEntry, ModelEntry] | None:
    """(extractor, matcher) entries of ``family`` at ``precision`` in a manifest, or None when either is
    missing (``gdnav models quantize`` adds int8 entries beside the fp32 ones)."""
    found: dict[str, ModelEntry] = {}
    for entry in entries:
        if (
            entry.params.get("family") == family
            and entry.params.get("role") in (ROLE_EXTRACTOR, ROLE_MATCHER)
            and entry_precision(entry) == precision
        ):
            found[str(entry.params["role"])] = entry
    if ROLE_EXTRACTOR in found and ROLE_MATCHER in found:
        return found[ROLE_EXTRACTOR], found[ROLE_MATCHER]
    return None


def family_models_at(
    entries: Sequence[ModelEntry], family: str, precision: str
) -> tuple[ModelEntry, ModelEntry] | None:
    """(extractor, matcher) of ``family``, each at ``precision`` where the manifest has it and fp32
    otherwise (a family may have only its matcher quantised); None when the fp32 pair is missing, or
    when neither file exists at ``precision``."""
    fp32 = family_models(entries, family)
    if fp32 is None or precision == PRECISION_FP32:
        return fp32
    picked = []
    for fp32_entry in fp32:
        role = fp32_entry.params["role"]
        other = next(
            (
                e
                for e in entries
                if e.params.get("family") == family
                and e.params.get("role") == role
                and entry_precision(e) == precision
            ),
            None,
        )
        picked.append(other or fp32_entry)
    if all(entry_precision(e) == PRECISION_FP32 for e in picked):
        return None
    return picked[0], picked[1]


def _source(name: str) -> ModelSource:
    w = PACKAGE_WEIGHTS[name]
    return ModelSource(name=w.name, sha256=w.sha256, licence=w.licence, url=w.url)


def _versions() -> dict[str, Any]:
    import kornia
    import torch

    return {"torch": torch.__version__, "kornia": kornia.__version__}


def _check_loads(path: Path, signature: EngineSignature) -> None:
    """Load through the daemon's C7 runtime (signature check + warm-up), or ``ExportError``."""
    from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
    from gps_denied_onboard.components.c7_inference.protocol import EngineLoadError

    runtime = OnnxInferenceRuntime(intra_op_threads=1, providers=["CPUExecutionProvider"])
    try:
        runtime.load_engine(str(path), signature)
    except EngineLoadError as exc:
        raise ExportError(f"exported model is refused by the runtime: {exc}", path=str(path)) from exc


def _export_extractor_legacy(module: Any, out: Path, probe_hw: tuple[int, int]) -> None:
    import torch

    dummy = torch.rand(1, 3, *probe_hw)
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated, but it is the one that traces the fixed-top-k
        # extractors with dynamic H/W; its tracer warnings are about Python ints it records as shapes.
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            (dummy,),
            str(out),
            dynamo=False,
            opset_version=EXTRACTOR_OPSET,
            input_names=["image"],
            output_names=["keypoints", "scores", "descriptors"],
            dynamic_axes={
                "image": {2: "height", 3: "width"},
                "keypoints": {1: "n"},
                "scores": {1: "n"},
                "descriptors": {1: "n"},
            },
            do_constant_folding=True,
        )


def _export_matcher(module: Any, out: Path, dim: int) -> None:
    import contextlib
    import io

    import torch
    from torch.export import Dim

    n0, n1 = Dim("n0", min=2, max=16384), Dim("n1", min=2, max=16384)
    k0, k1 = torch.rand(1, 512, 2) * 2 - 1, torch.rand(1, 480, 2) * 2 - 1
    d0 = torch.nn.functional.normalize(torch.randn(1, 512, dim), dim=-1)
    d1 = torch.nn.functional.normalize(torch.randn(1, 480, dim), dim=-1)
    for stale in (out, out.with_name(out.name + ".data")):
        stale.unlink(missing_ok=True)
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            (k0, k1, d0, d1),
            str(out),
            dynamo=True,
            opset_version=MATCHER_OPSET,
            input_names=["kpts0", "kpts1", "desc0", "desc1"],
            output_names=["matches0", "mscores0"],
            dynamic_shapes={"kpts0": {1: n0}, "kpts1": {1: n1}, "desc0": {1: n0}, "desc1": {1: n1}},
            external_data=True,
        )


def _entry(out: Path, name: str, signature: EngineSignature, params: dict[str, Any]) -> ModelEntry:
    data = out.with_name(out.name + ".data")
    if data.is_file():
        params = {**params, "data_file": data.name, "data_sha256": sha256_file(data)}
    return ModelEntry(
        file=out.name, sha256=sha256_file(out), source=_source(name), signature=signature, params=params
    )


def export_family(
    family: str, out_dir: str | Path, *, top_k: int = DEFAULT_TOP_K, manifest: bool = True
) -> tuple[ModelEntry, ModelEntry]:
    """Export ``family``'s extractor and LightGlue matcher into ``out_dir``; returns their entries.

    Raises ``WeightsError``/``WeightsHashMismatchError`` (weights not installed or not the pinned files),
    ``ExportError`` (a file the runtime refuses), ``ValueError`` (unknown family, bad ``top_k``),
    ``ImportError`` (the export extra is missing).
    """
    if top_k <= 0:
        raise ValueError(f"top_k must be positive, got {top_k}")
    spec = family_spec(family, top_k)
    out_root = Path(out_dir)
    ext_weights = package_weights_path(spec.extractor_weights)
    lg_weights = package_weights_path(spec.matcher_weights)

    import torch

    from gps_denied_onboard.models import learned_torch as lt

    out_root.mkdir(parents=True, exist_ok=True)
    versions = _versions()
    common = {"family": family, "package": PACKAGE_WEIGHTS[spec.extractor_weights].package, **versions}
    ext_out = out_root / spec.extractor_file
    with torch.no_grad():
        if family == "disk":
            _export_extractor_legacy(
                lt.DiskExtractor(lt.load_disk(ext_weights), top_k).eval(), ext_out, (480, 640)
            )
            ext_params: dict[str, Any] = {"top_k": top_k, "side_multiple": 16, "opset": EXTRACTOR_OPSET}
        elif family == "xfeat":
            net = lt.load_xfeat_net(ext_weights)
            _export_extractor_legacy(lt.XFeatExtractor(net, top_k).eval(), ext_out, (480, 640))
            ext_params = {"top_k": top_k, "side_multiple": 32, "opset": EXTRACTOR_OPSET}
        else:
            h, w = ALIKED_INPUT_HW
            export_aliked_onnx(
                ext_weights, ext_out, variant="n16", top_k=top_k, height=h, width=w, manifest=False
            )
            ext_params = {"variant": "n16", "top_k": top_k, "height": h, "width": w, "opset": EXTRACTOR_OPSET}
    _check_loads(ext_out, spec.extractor_signature)
    ext_entry = _entry(
        ext_out,
        spec.extractor_weights,
        spec.extractor_signature,
        {**common, "role": ROLE_EXTRACTOR, **ext_params},
    )

    lg_out = out_root / spec.matcher_file
    matcher = lt.LightGlueMatcher(lt.load_lightglue(lg_weights, family)).eval()
    _export_matcher(matcher, lg_out, spec.descriptor_dim)
    _check_loads(lg_out, spec.matcher_signature)
    lg_entry = _entry(
        lg_out,
        spec.matcher_weights,
        spec.matcher_signature,
        {
            **common,
            "package": PACKAGE_WEIGHTS[spec.matcher_weights].package,
            "role": ROLE_MATCHER,
            "opset": MATCHER_OPSET,
            "pruning": False,
            "early_stop": False,
            "filter_threshold": lt.LIGHTGLUE_FILTER_THRESHOLD,
            "descriptor_dim": spec.descriptor_dim,
        },
    )
    if manifest:
        write_manifest(out_root, ext_entry)
        write_manifest(out_root, lg_entry)
    return ext_entry, lg_entry


def export_registry_models(
    out_dir: str | Path,
    families: Sequence[str] = FAMILIES,
    *,
    top_k: int = DEFAULT_TOP_K,
    report: Callable[[str], None] | None = None,
) -> list[ModelEntry]:
    """Export every family in ``families`` (see ``export_family``); ``report`` gets one line per file."""
    entries: list[ModelEntry] = []
    for family in families:
        family_spec(family, top_k)  # unknown names fail before any work
    for family in families:
        t0 = time.perf_counter()
        pair = export_family(family, out_dir, top_k=top_k)
        entries.extend(pair)
        if report is not None:
            for entry in pair:
                report(
                    f"exported {Path(out_dir) / entry.file} ({entry.params['role']}, "
                    f"from {entry.source.name}, "
                    f"{entry.source.licence}, sha256 {entry.sha256[:12]})"
                )
            report(f"  {family}: {time.perf_counter() - t0:.1f} s")
    return entries
