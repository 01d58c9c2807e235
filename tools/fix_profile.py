"""Where a fix's time goes: the fix path, stage by stage, on a recorded flight, on this machine.

    .venv/bin/python tools/fix_profile.py --fdr DIR [--set KEY.PATH=VALUE ...] [--frames N]
        [--json OUT] [--cprofile OUT.prof]

Replays the FDR frame by frame (``gdnav replay --sequential``: each frame tracked, then localised) with
the config it was recorded with plus ``--set``, and times every call of the functions that own a stage of
``NavigationPipeline.localise``: C2 VPR, C2.5 rerank and the footprint chip's cut, C3's rectification,
query and tile extraction, matching, RANSAC, C4's pose (best and rival candidates), the attitude check,
the integrity rule, the estimator's fusion and the FDR records. ONNX Runtime's ``run`` is its own stage,
named after the stage that called it, so each model's time is split out of its caller's. Times are
exclusive (a stage's time leaves out the stages it calls) and wall clock (``perf_counter_ns``); what no
stage owns is ``pipeline`` (the fix path's own Python) or ``c3 loop`` (the candidate loop's). The summary
splits the path into ONNX models, ``matching`` outside them (xfeat_mnn's matrix product, classical's k-NN:
the matcher itself) and the rest; ``estimates_sha256`` digests every frame's estimate, so two code
versions run side by side can be shown to give the same answers.

The wrappers cost about a microsecond a call. ``--cprofile`` also writes a cProfile of the same run (it
slows Python-heavy code more than native code, so read its shares, not its totals, against the table).
A one-off measurement tool for ``docs/benchmarks.md``: the daemon does not use it.
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import hashlib
import json
import logging
import os
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog

from gps_denied_onboard.components.c7_inference.onnx_runtime import OnnxInferenceRuntime
from gps_denied_onboard.config import config_with_overrides, load_config
from gps_denied_onboard.replay import driver as replay_driver
from gps_denied_onboard.replay.inputs import from_fdr
from gps_denied_onboard.runtime_root import compose as compose_module

#: The order stages are printed in (a stage not listed is printed after them).
STAGE_ORDER = (
    "vpr",
    "rerank",
    "footprint chip cut",
    "rectification",
    "query extraction",
    "model: query extraction",
    "tile features (cache lookup)",
    "tile extraction",
    "model: tile extraction",
    "matching",
    "model: matching",
    "ransac",
    "c3 loop",
    "pose",
    "pose (rivals)",
    "attitude check",
    "integrity",
    "estimator fusion",
    "fdr records",
    "pipeline",
)


class StageTimer:
    """Exclusive wall time per stage, from wrapped callables (one thread)."""

    def __init__(self) -> None:
        self._stack: list[list[Any]] = []
        self.total_ns: dict[str, int] = defaultdict(int)
        self.calls: dict[str, int] = defaultdict(int)
        self.roots: list[dict[str, int]] = []
        self._current: dict[str, int] | None = None

    def wrap(self, fn: Callable[..., Any], stage: str | Callable[[str | None], str], *, root: bool = False):
        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            parent = self._stack[-1][0] if self._stack else None
            name = stage(parent) if callable(stage) else stage
            if root:
                self._current = defaultdict(int)
            t0 = time.perf_counter_ns()
            self._stack.append([name, 0])
            try:
                return fn(*args, **kwargs)
            finally:
                _, children = self._stack.pop()
                dt = time.perf_counter_ns() - t0
                self.total_ns[name] += dt - children
                self.calls[name] += 1
                if self._current is not None:
                    self._current[name] += dt - children
                if self._stack:
                    self._stack[-1][1] += dt
                if root and self._current is not None:
                    self.roots.append(dict(self._current))
                    self._current = None

        return timed


def _wrap_method(timer: StageTimer, obj: Any, name: str, stage: Any, **kw: Any) -> None:
    """Time ``obj.name`` as ``stage`` (once: an object two matchers share is wrapped once)."""
    if obj is None or not hasattr(obj, name) or getattr(getattr(obj, name), "stage_timed", False):
        return
    timed = timer.wrap(getattr(obj, name), stage, **kw)
    timed.stage_timed = True  # type: ignore[attr-defined]
    setattr(obj, name, timed)


def _model_stage(parent: str | None) -> str:
    return f"model: {parent}" if parent else "model"


def _pose_stage(parent: str | None) -> str:
    return "pose (rivals)" if parent == "integrity" else "pose"


def instrument(timer: StageTimer, root: Any) -> None:
    """Wrap the fix path's stage owners of the composed ``root`` (instance attributes only)."""
    p = root.pipeline
    _wrap_method(timer, p, "localise", "pipeline", root=True)
    _wrap_method(timer, p._vpr, "embed_query", "vpr")
    _wrap_method(timer, p._vpr, "retrieve_topk", "vpr")
    _wrap_method(timer, p._rerank, "rerank", "rerank")
    _wrap_method(timer, p._footprint_chips, "first", "footprint chip cut")
    # The matcher, or each rung's of an effort ladder (each instance once).
    ladder = getattr(p, "_ladder", None)
    found = [getattr(p, "_matcher", None)] + [r.matcher for r in (ladder.rungs if ladder else ())]
    matchers = list({id(m): m for m in found if m is not None}.values())
    ransacs = {id(r): r for r in (getattr(m, "_ransac_filter", None) for m in matchers) if r is not None}
    for m in matchers:
        _wrap_method(timer, m, "match", "c3 loop")
        _wrap_method(timer, m, "_query_view", "rectification")
        _wrap_method(timer, m, "extract_query", "query extraction")
        _wrap_method(timer, m, "extract_tile", "tile extraction")
        _wrap_method(timer, m, "match_features", "matching")
        _wrap_method(timer, getattr(m, "_tile_features", None), "lookup", "tile features (cache lookup)")
    for r in ransacs.values():
        _wrap_method(timer, r, "filter", "ransac")
    _wrap_method(timer, p._pose, "solve", _pose_stage)
    _wrap_method(timer, p, "_judge", "integrity")
    _wrap_method(timer, p._attitude, "note", "attitude check")
    _wrap_method(timer, p, "fuse_attempt", "estimator fusion")
    _wrap_method(timer, p._fdr, "record", "fdr records")


def table(timer: StageTimer) -> dict[str, Any]:
    """Per-attempt stage means (ms), shares of the fix path, and model vs the rest."""
    n = len(timer.roots)
    stages = [s for s in STAGE_ORDER if s in timer.total_ns] + sorted(
        s for s in timer.total_ns if s not in STAGE_ORDER
    )
    total_ns = sum(timer.total_ns.values())
    rows = []
    for s in stages:
        per = [r.get(s, 0) / 1e6 for r in timer.roots]
        rows.append(
            {
                "stage": s,
                "mean_ms": timer.total_ns[s] / 1e6 / max(n, 1),
                "p50_ms": statistics.median(per) if per else 0.0,
                "share": timer.total_ns[s] / total_ns if total_ns else 0.0,
                "calls": timer.calls[s],
            }
        )
    model_ns = sum(v for k, v in timer.total_ns.items() if k.startswith("model"))
    # The matcher's own arithmetic where no ONNX model matches (xfeat_mnn's matrix product, classical's
    # k-NN): the matcher, not overhead.
    matching_ns = timer.total_ns.get("matching", 0)
    rest_ns = total_ns - model_ns - matching_ns
    totals = [sum(r.values()) / 1e6 for r in timer.roots]
    per = max(n, 1) * 1e6
    return {
        "attempts": n,
        "fix_path_mean_ms": total_ns / per,
        "fix_path_p50_ms": statistics.median(totals) if totals else 0.0,
        "model_mean_ms": model_ns / per,
        "matching_mean_ms": matching_ns / per,
        "rest_mean_ms": rest_ns / per,
        "rest_over_model_and_matching": rest_ns / (model_ns + matching_ns)
        if model_ns + matching_ns
        else None,
        "stages": rows,
    }


def print_table(result: dict[str, Any], title: str) -> None:
    print(title)
    print(f"{'stage':32s} {'mean ms':>9s} {'p50 ms':>9s} {'share':>7s} {'calls':>7s}")
    for r in result["stages"]:
        print(
            f"{r['stage']:32s} {r['mean_ms']:9.1f} {r['p50_ms']:9.1f} "
            f"{100 * r['share']:6.1f}% {r['calls']:7d}"
        )
    ratio = result["rest_over_model_and_matching"]
    print(
        f"{result['attempts']} fix attempts; fix path mean {result['fix_path_mean_ms']:.1f} ms "
        f"(p50 {result['fix_path_p50_ms']:.1f}); ONNX models {result['model_mean_ms']:.1f} ms, matching "
        f"outside them {result['matching_mean_ms']:.1f} ms, the rest {result['rest_mean_ms']:.1f} ms"
        + (f" ({100 * ratio:.0f} % of models + matching)" if ratio is not None else "")
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fdr", type=Path, required=True, help="FDR directory recorded with every frame")
    ap.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE")
    ap.add_argument("--config", type=Path, default=None, help="profile (default: the recorded config)")
    ap.add_argument("--frames", type=int, default=0, help="replay only the first N frames (0: all)")
    ap.add_argument("--json", type=Path, default=None, help="write the table as JSON here")
    ap.add_argument("--cprofile", type=Path, default=None, help="also write a cProfile of the run here")
    args = ap.parse_args(argv)

    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.CRITICAL))
    inp = from_fdr(args.fdr)
    if args.config is not None or inp.recorded_config is None:
        config = load_config(args.config, args.set)
    else:
        config = config_with_overrides(inp.recorded_config, args.set, source=str(args.fdr))
    if args.frames > 0:
        inp.frames = inp.frames[: args.frames]

    timer = StageTimer()
    OnnxInferenceRuntime.run = timer.wrap(OnnxInferenceRuntime.run, _model_stage)  # type: ignore[method-assign]
    original = compose_module.compose_replay

    def composed(*a: Any, **kw: Any) -> Any:
        root = original(*a, **kw)
        instrument(timer, root)
        return root

    compose_module.compose_replay = composed  # type: ignore[assignment]
    profiler = cProfile.Profile() if args.cprofile else None
    t0 = time.monotonic()
    if profiler is not None:
        profiler.enable()
    report = replay_driver.run_replay(inp, config, with_map=True, force_sequential=True)
    if profiler is not None:
        profiler.disable()
        profiler.dump_stats(str(args.cprofile))
    wall_s = time.monotonic() - t0
    result = table(timer)
    result.update(
        {
            "wall_s": round(wall_s, 1),
            "strategy": config.matcher.strategy,
            "overrides": args.set,
            "frames": len(inp.frames),
            "load_avg": os.getloadavg(),
            "fix": report.get("fix"),
            # Identical behaviour before and after a change: the same digest of every frame's estimate.
            "estimates_sha256": hashlib.sha256(
                json.dumps(
                    [
                        [f["seq"], f["provenance"], f["lat_deg"], f["lon_deg"], f["horiz_sigma_m"]]
                        for f in report["per_frame"]
                    ]
                ).encode()
            ).hexdigest(),
        }
    )
    print(f"fix attempts {result['fix']}; estimates sha256 {result['estimates_sha256'][:16]}")
    print_table(
        result, f"fix path of {config.matcher.strategy}, {len(inp.frames)} frames, load {os.getloadavg()}"
    )
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
