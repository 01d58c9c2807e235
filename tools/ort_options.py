"""ONNX Runtime's CPU session options, side by side: wall and CPU time of each exported model per variant.

    .venv/bin/python tools/ort_options.py --image FRAME.png [--model-dir models] [--models xfeat,lighterglue]
        [--keypoints 2048] [--repeats 15] [--gap-ms 50] [--json OUT]

Every variant's session is created up front, then the variants run in turn, one run each per round
(round robin), so a machine whose load changes during the measurement changes every variant alike. Each
run is preceded by ``--gap-ms`` of sleep, as the daemon's fix thread waits between frames; a variant's
CPU time is the process's CPU time (all threads, ``time.process_time``) from the start of its run to the
start of the next variant's, so the spinning of ONNX Runtime's idle worker threads after a run counts.

Inputs: an extractor gets ``--image`` resized to its fixed input size or, for a dynamic-size export, to
640 x 480 (the rectified query's size class) and to 640 x 640 (a 512 px chip at the daemon's 640 px long
side); a matcher gets two sets of N random keypoints
with random unit descriptors (its early exit is off in the export, so this is its full cost).

The variants start from the runtime's defaults (``c7_inference.onnx_runtime.session_options``) and change
one option each. A one-off measurement tool for ``docs/benchmarks.md``: the daemon does not use it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnxruntime as ort
from onnx_cost import _keypoint_feeds  # tools/ is this script's own folder on sys.path

#: Variant name -> how it changes the defaults (applied to a fresh ``SessionOptions``).
Variant = Callable[[ort.SessionOptions], None]


def _set(**fields: Any) -> Variant:
    def apply(o: ort.SessionOptions) -> None:
        for k, v in fields.items():
            setattr(o, k, v)

    return apply


def _entry(key: str, value: str) -> Variant:
    def apply(o: ort.SessionOptions) -> None:
        o.add_session_config_entry(key, value)

    return apply


def _both(*parts: Variant) -> Variant:
    def apply(o: ort.SessionOptions) -> None:
        for p in parts:
            p(o)

    return apply


def _baseline(threads: int) -> Variant:
    """What ``OnnxInferenceRuntime`` set before this tool (2026-11-27): the reference row."""
    return _set(
        intra_op_num_threads=threads,
        inter_op_num_threads=1,
        execution_mode=ort.ExecutionMode.ORT_SEQUENTIAL,
        graph_optimization_level=ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
    )


VARIANTS: dict[str, Variant] = {
    "baseline: 2 threads, ALL, arena, mem pattern, spinning": _baseline(2),
    "1 intra-op thread": _both(_baseline(2), _set(intra_op_num_threads=1)),
    "no spinning (allow_spinning=0)": _both(_baseline(2), _entry("session.intra_op.allow_spinning", "0")),
    "1 thread, no spinning": _both(
        _baseline(2), _set(intra_op_num_threads=1), _entry("session.intra_op.allow_spinning", "0")
    ),
    "graph opt EXTENDED": _both(
        _baseline(2), _set(graph_optimization_level=ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED)
    ),
    "graph opt BASIC": _both(
        _baseline(2), _set(graph_optimization_level=ort.GraphOptimizationLevel.ORT_ENABLE_BASIC)
    ),
    "graph opt DISABLED": _both(
        _baseline(2), _set(graph_optimization_level=ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    ),
    "no CPU memory arena": _both(_baseline(2), _set(enable_cpu_mem_arena=False)),
    "no memory pattern": _both(_baseline(2), _set(enable_mem_pattern=False)),
    "parallel execution, 2 inter-op": _both(
        _baseline(2), _set(execution_mode=ort.ExecutionMode.ORT_PARALLEL, inter_op_num_threads=2)
    ),
}


def _image_feeds(session: ort.InferenceSession, image_bgr: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    (inp,) = session.get_inputs()
    out = {}
    fixed = isinstance(inp.shape[2], int) and isinstance(inp.shape[3], int)
    sizes = [(int(inp.shape[3]), int(inp.shape[2]))] if fixed else [(640, 480), (640, 640)]
    for w, h in sizes:
        rgb = cv2.cvtColor(cv2.resize(image_bgr, (w, h), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
        tensor = (rgb.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
        if inp.shape[1] == 1:
            tensor = tensor.mean(axis=1, keepdims=True)
        out[f"{w}x{h}"] = {inp.name: np.ascontiguousarray(tensor)}
    return out


def measure(
    path: Path,
    cases: Callable[[ort.InferenceSession], dict[str, dict[str, np.ndarray]]],
    repeats: int,
    gap_s: float,
    variants: dict[str, Variant],
) -> list[dict[str, Any]]:
    """One row per (case, variant): wall p50 / min and CPU p50, ms; the first variant is the reference."""
    sessions = {}
    for name, variant in variants.items():
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        variant(opts)
        sessions[name] = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    rows = []
    for case, feeds in cases(next(iter(sessions.values()))).items():
        for s in sessions.values():
            s.run(None, feeds)  # warm-up
        wall: dict[str, list[float]] = {n: [] for n in sessions}
        cpu: dict[str, list[float]] = {n: [] for n in sessions}
        for _ in range(repeats):
            for name, s in sessions.items():
                time.sleep(gap_s)
                c0 = time.process_time()
                t0 = time.perf_counter()
                s.run(None, feeds)
                wall[name].append((time.perf_counter() - t0) * 1e3)
                time.sleep(gap_s)  # the idle threads' spinning after the run is this run's CPU
                cpu[name].append((time.process_time() - c0) * 1e3)
        base = statistics.median(wall[next(iter(sessions))])
        base_cpu = statistics.median(cpu[next(iter(sessions))])
        for name in sessions:
            p50 = statistics.median(wall[name])
            c50 = statistics.median(cpu[name])
            rows.append(
                {
                    "model": path.name,
                    "input": case,
                    "variant": name,
                    "wall_p50_ms": round(p50, 1),
                    "wall_min_ms": round(min(wall[name]), 1),
                    "cpu_p50_ms": round(c50, 1),
                    "wall_ratio": round(p50 / base, 3),
                    "cpu_ratio": round(c50 / base_cpu, 3),
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model-dir", type=Path, default=Path("models"))
    ap.add_argument("--image", type=Path, required=True)
    ap.add_argument("--models", default="xfeat,lighterglue", help="file-name prefixes, comma-separated")
    ap.add_argument("--keypoints", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--gap-ms", type=float, default=50.0)
    ap.add_argument("--variants", default="", help="numbers of the variants to run (0 first), e.g. 0,1,2")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    names = list(VARIANTS)
    picked = [names[int(i)] for i in args.variants.split(",")] if args.variants else names
    variants = {n: VARIANTS[n] for n in picked}
    image = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
    if image is None:
        ap.error(f"--image {args.image}: not a readable image")
    wanted = args.models.split(",")
    files = sorted(p for p in args.model_dir.glob("*.onnx") if any(p.name.startswith(w) for w in wanted))
    if not files:
        ap.error(f"no model in {args.model_dir} starts with any of {wanted}")
    load0 = os.getloadavg()
    rows: list[dict[str, Any]] = []
    for path in files:
        matcher = path.name.endswith("glue.onnx")
        if matcher:
            rows += measure(
                path,
                lambda s: {f"{args.keypoints} kpts": _keypoint_feeds(s, args.keypoints)},
                args.repeats,
                args.gap_ms / 1e3,
                variants,
            )
        else:
            rows += measure(path, lambda s: _image_feeds(s, image), args.repeats, args.gap_ms / 1e3, variants)
    load1 = os.getloadavg()
    print(
        f"onnxruntime {ort.__version__}, {os.cpu_count()} CPUs, load {load0} -> {load1}, "
        f"{args.repeats} rounds, {args.gap_ms:.0f} ms gaps"
    )
    print("| model | input | variant | wall p50 (min) ms | CPU p50 ms | wall / baseline | CPU / baseline |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['model']} | {r['input']} | {r['variant']} | {r['wall_p50_ms']} ({r['wall_min_ms']}) | "
            f"{r['cpu_p50_ms']} | {r['wall_ratio']:.2f} | {r['cpu_ratio']:.2f} |"
        )
    if args.json is not None:
        args.json.write_text(json.dumps({"load": [load0, load1], "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
