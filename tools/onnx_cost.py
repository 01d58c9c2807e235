"""Wall time of one run of each exported model, per execution provider, side by side in one process.

    .venv/bin/python tools/onnx_cost.py --image FRAME.png [--model-dir models]
        [--providers cpu,cuda] [--keypoints 512,1024,2048] [--repeats 5] [--int8]

For every model file of ``gdnav models export`` in ``--model-dir``:
- an extractor (``disk-*``, ``aliked-*``, ``xfeat-*``) is run on ``--image``, resized to its fixed input
  size or, for a dynamic-size export, to 640 x 480 (the daemon's ``matcher.input_long_side_px``);
- a matcher (``*_lightglue.onnx``, ``xfeat_lighterglue.onnx``) on two sets of N random keypoints in
  [-1, 1] with random unit descriptors (its early exit and pruning are off in the export, so random
  inputs give its full cost whatever the image).

Each is run once per provider to warm up (CUDA: three times, for its kernel selection), then
``--repeats`` times; the best wall time of ``session.run`` is printed, outputs copied to the host
included, as the daemon sees it. A provider ONNX Runtime does not offer here, or that refuses the
model, is printed as such in its cell, never replaced by another. The last columns are each provider's
time over the first's, measured in the same run.

``--int8`` adds a second table, on the first provider: every int8 file of ``gdnav models quantize``
beside the fp32 file it came from (``params.quantized_from``), on the same inputs, their runs interleaved
(fp32, int8, fp32, ...) so that a load that changes during the run weighs on both alike; the ratio is
int8 over fp32.

Only ``onnxruntime``, ``numpy`` and OpenCV are imported, so the script runs on a machine that has
``onnxruntime-gpu`` and not the project's environment. A one-off measurement tool for
``docs/benchmarks.md``: the daemon does not use it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

PROVIDERS = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
}
#: Size given to a dynamic-size extractor (width, height): a 4:3 frame at the daemon's 640 px long side.
DYNAMIC_SIZE = (640, 480)


def _session(path: Path, provider: str, threads: int) -> ort.InferenceSession | str:
    """A session that runs on ``provider`` alone (CPU as ONNX Runtime's own fallback for the few
    operators a GPU provider leaves), or why there is none."""
    if provider not in ort.get_available_providers():
        return f"{provider} not in this onnxruntime ({ort.__version__})"
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    chain = [provider] if provider == "CPUExecutionProvider" else [provider, "CPUExecutionProvider"]
    try:
        session = ort.InferenceSession(str(path), options, providers=chain)
    except Exception as exc:  # the provider's own message says what it lacks
        return f"{provider} refused: {type(exc).__name__}: {str(exc)[:200]}"
    if session.get_providers()[0] != provider:
        return f"{provider} not loaded (ran on {session.get_providers()[0]})"
    return session


def _image_feed(session: ort.InferenceSession, image_bgr: np.ndarray) -> dict[str, np.ndarray]:
    (inp,) = session.get_inputs()
    height, width = inp.shape[2], inp.shape[3]
    size = (width, height) if isinstance(width, int) and isinstance(height, int) else DYNAMIC_SIZE
    rgb = cv2.cvtColor(cv2.resize(image_bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
    return {inp.name: (rgb.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]}


def _keypoint_feeds(session: ort.InferenceSession, n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    feeds = {}
    for inp in session.get_inputs():
        if inp.name.startswith("kpts"):
            feeds[inp.name] = rng.uniform(-1.0, 1.0, (1, n, 2)).astype(np.float32)
        elif inp.name.startswith("desc"):
            desc = rng.standard_normal((1, n, int(inp.shape[-1]))).astype(np.float32)
            feeds[inp.name] = desc / np.linalg.norm(desc, axis=-1, keepdims=True)
        else:
            raise SystemExit(f"{inp.name!r}: not a LightGlue-ONNX input (kpts0/1, desc0/1 expected)")
    return feeds


def _best_ms(session: ort.InferenceSession, feeds: dict[str, np.ndarray], warmup: int, repeats: int) -> float:
    for _ in range(warmup):
        session.run(None, feeds)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        session.run(None, feeds)
        best = min(best, time.perf_counter() - start)
    return best * 1e3


def _best_pair_ms(
    sessions: tuple[ort.InferenceSession, ort.InferenceSession], feeds: dict[str, np.ndarray], repeats: int
) -> tuple[float, float]:
    """Best wall time of each of two sessions on the same feeds, runs interleaved, ms."""
    for session in sessions:
        session.run(None, feeds)
    best = [float("inf"), float("inf")]
    for _ in range(repeats):
        for i, session in enumerate(sessions):
            start = time.perf_counter()
            session.run(None, feeds)
            best[i] = min(best[i], time.perf_counter() - start)
    return best[0] * 1e3, best[1] * 1e3


def _int8_rows(
    model_dir: Path,
    manifest: dict,
    provider: str,
    image: np.ndarray,
    counts: list[int],
    args: argparse.Namespace,
) -> list[list[str]]:
    """Rows (int8 file, input, fp32 ms, int8 ms, int8 / fp32) for every int8 file of the manifest."""
    rows = []
    for entry in manifest["models"]:
        params = entry.get("params", {})
        if params.get("precision") != "int8":
            continue
        pair = [_session(model_dir / params["quantized_from"], provider, args.threads)]
        pair.append(_session(model_dir / entry["file"], provider, args.threads))
        matcher = params.get("role") == "matcher"
        for case in [f"{n} kpts" for n in counts] if matcher else ["image"]:
            failed = next((s for s in pair if isinstance(s, str)), None)
            if failed is not None:
                rows.append([entry["file"], case, failed, "—", "—"])
                continue
            sessions = (pair[0], pair[1])
            feeds = (
                _keypoint_feeds(sessions[0], int(case.split()[0]))
                if matcher
                else _image_feed(sessions[0], image)
            )
            fp32_ms, int8_ms = _best_pair_ms(sessions, feeds, args.repeats)  # type: ignore[arg-type]
            rows.append([entry["file"], case, f"{fp32_ms:.1f}", f"{int8_ms:.1f}", f"{int8_ms / fp32_ms:.3f}"])
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model-dir", type=Path, default=Path("models"), help="gdnav models export --out")
    parser.add_argument("--image", type=Path, required=True, help="a real frame or map chip (any size)")
    parser.add_argument("--providers", default="cpu", help=f"comma-separated, of {sorted(PROVIDERS)}")
    parser.add_argument("--keypoints", default="512,1024,2048", help="matcher keypoint counts")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, help="CPU intra-op threads (the daemon's 2)")
    parser.add_argument(
        "--int8", action="store_true", help="also time each int8 file against its fp32 file, interleaved"
    )
    parser.add_argument("--int8-only", action="store_true", help="only the int8 table (implies --int8)")
    args = parser.parse_args(argv)

    unknown = [p for p in args.providers.split(",") if p not in PROVIDERS]
    if unknown:
        parser.error(f"--providers: {unknown} not among {sorted(PROVIDERS)}")
    providers = [PROVIDERS[p] for p in args.providers.split(",")]
    image = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
    if image is None:
        parser.error(f"--image {args.image}: not a readable image")
    if any(p != "CPUExecutionProvider" for p in providers) and hasattr(ort, "preload_dlls"):
        # onnxruntime-gpu finds CUDA and cuDNN in PyTorch's or the nvidia-* wheels' folders this way.
        ort.preload_dlls()
    counts = [int(k) for k in args.keypoints.split(",")]
    manifest = json.loads((args.model_dir / "manifest.json").read_text())
    files = [] if args.int8_only else sorted(m["file"] for m in manifest["models"])

    # (model, input) -> provider -> best ms, or why that provider did not run it.
    cells_of: dict[tuple[str, str], dict[str, float | str]] = {}
    for name in files:
        matcher = name.endswith("glue.onnx")
        cases = [f"{n} kpts" for n in counts] if matcher else ["image"]
        for provider in providers:
            session = _session(args.model_dir / name, provider, args.threads)
            warmup = 1 if provider == "CPUExecutionProvider" else 3
            for case in cases:
                cell = cells_of.setdefault((name, case), {})
                if isinstance(session, str):
                    cell[provider] = session
                    continue
                if matcher:
                    feeds = _keypoint_feeds(session, int(case.split()[0]))
                else:
                    feeds = _image_feed(session, image)
                cell[provider] = _best_ms(session, feeds, warmup, args.repeats)

    print(f"onnxruntime {ort.__version__}; available: {ort.get_available_providers()}")
    print(f"ms, best of {args.repeats}; image {args.image.name}; CPU threads {args.threads}")
    short = {p: p.removesuffix("ExecutionProvider") for p in providers}
    header = ["model", "input"] + [short[p] for p in providers]
    header += [f"{short[p]} / {short[providers[0]]}" for p in providers[1:]]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for (name, case), cells in cells_of.items():
        out = [name, case]
        for p in providers:
            value = cells.get(p, "—")
            out.append(f"{value:.1f}" if isinstance(value, float) else str(value))
        first = cells.get(providers[0])
        for p in providers[1:]:
            value = cells.get(p)
            ratio = isinstance(first, float) and isinstance(value, float)
            out.append(f"{value / first:.3f}" if ratio else "—")
        print("| " + " | ".join(out) + " |")
    if args.int8 or args.int8_only:
        rows = _int8_rows(args.model_dir, manifest, providers[0], image, counts, args)
        print(f"\nint8 vs fp32 on {short[providers[0]]}, runs interleaved, ms, best of {args.repeats}")
        print("| int8 model | input | fp32 | int8 | int8 / fp32 |")
        print("|---|---|---|---|---|")
        for row in rows:
            print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
