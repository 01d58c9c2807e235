"""One LightGlue run's wall time against the keypoint count, for each exported matcher.

    .venv/bin/python tools/lightglue_cost.py [--model-dir models] [--keypoints 512,1024,2048]

Each matcher file of ``gdnav models export`` (``*_lightglue.onnx``, ``xfeat_lighterglue.onnx``) is run
by ONNX Runtime (CPU provider, 2 intra-op threads, as the daemon does on this machine) on two sets of N
random keypoints in [-1, 1] with random unit descriptors, once to warm up and then ``--repeats`` times;
the best time is printed. Random inputs give LightGlue's full cost (its early exit and pruning are off
in the export), so the figure is what one candidate's match costs whatever the image. A one-off
measurement tool for ``docs/benchmarks.md``: the daemon does not use it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

MATCHERS = ("aliked_lightglue", "disk_lightglue", "xfeat_lighterglue")


def _feeds(session: ort.InferenceSession, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    feeds = {}
    for inp in session.get_inputs():
        if inp.name.startswith("kpts"):
            feeds[inp.name] = rng.uniform(-1.0, 1.0, (1, n, 2)).astype(np.float32)
        elif inp.name.startswith("desc"):
            dim = int(inp.shape[-1])
            desc = rng.standard_normal((1, n, dim)).astype(np.float32)
            feeds[inp.name] = desc / np.linalg.norm(desc, axis=-1, keepdims=True)
        else:
            raise SystemExit(f"{inp.name!r}: not a LightGlue-ONNX input (kpts0/1, desc0/1 expected)")
    return feeds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model-dir", type=Path, default=Path("models"), help="gdnav models export --out")
    parser.add_argument("--keypoints", default="512,1024,2048", help="comma-separated counts")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    counts = [int(k) for k in args.keypoints.split(",")]
    options = ort.SessionOptions()
    options.intra_op_num_threads = 2
    print(f"{'matcher':<20}" + "".join(f"{k:>10}" for k in counts) + "   (ms, best of repeats)")
    for name in MATCHERS:
        path = args.model_dir / f"{name}.onnx"
        if not path.is_file():
            print(f"{name:<20} not in {args.model_dir}")
            continue
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        cells = []
        for n in counts:
            feeds = _feeds(session, n, np.random.default_rng(0))
            session.run(None, feeds)
            best = float("inf")
            for _ in range(args.repeats):
                start = time.perf_counter()
                session.run(None, feeds)
                best = min(best, time.perf_counter() - start)
            cells.append(f"{best * 1e3:>10.0f}")
        print(f"{name:<20}" + "".join(cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
