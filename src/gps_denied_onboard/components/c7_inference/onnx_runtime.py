"""C7 ``InferenceRuntime`` on ONNX Runtime.

Input: a model path and the caller's ``EngineSignature``. Output: a loaded engine, one
``onnxruntime.InferenceSession`` per model, created at load time (never at the first frame), or an
``EngineLoadError`` naming the file and every mismatch.

Rule:
1. execution providers are tried in the order TensorRT -> CUDA -> CPU, keeping those
   ``onnxruntime.get_available_providers()`` reports; a provider whose session cannot be created is
   dropped for the next (``c7.inference.provider_fallback``);
2. inputs and outputs are checked against the signature (names, ranks, dtypes, fixed dims);
3. one warm-up pass on a dummy input, so provider initialisation happens at start-up, not in flight;
4. ``c7.inference.engine_loaded`` logs the path, the provider in use, the tensors and the load time.
Session options (``session_options``, measured in docs/benchmarks.md): ``daemon.onnx_intra_op_threads``
intra-op threads, one inter-op thread, sequential, every graph optimisation, memory arena and pattern on,
and no spin-waiting (``session.intra_op.allow_spinning=0``): on two cores shared with VO and the output, a
spinning worker takes the core another thread needs. A lock per session serves callers one at a time.

Test hook (SITL soak): when the variable named by ``ORT_FAULT_FILE_ENV`` is set when the runtime is built,
each ``run`` reads that file; while it holds a count N > 0, the run goes to ONNX Runtime with
``RunOptions.terminate`` set (ONNX Runtime itself raises its ``Fail``) and N is decremented (the file
removed at 0). It proves a raising runtime costs the frame and the daemon flies on with the same
sessions; not a native crash or a run that never returns. Arming it is logged
(``c7.inference.fault_hook_armed``); without the variable nothing is checked.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
import onnxruntime as ort
import structlog
from onnxruntime.capi import onnxruntime_pybind11_state as _ort_state

from gps_denied_onboard.components.c7_inference.protocol import (
    EngineLoadError,
    EngineSignature,
    InferenceError,
    TensorSpec,
)
from gps_denied_onboard.constants import LogEvent

_log = structlog.get_logger(__name__)

#: Preference order of execution providers; the first available one that accepts the model wins.
PROVIDER_PREFERENCE: tuple[str, ...] = (
    "TensorrtExecutionProvider",
    "CUDAExecutionProvider",
    "CPUExecutionProvider",
)

#: Whether ONNX Runtime's thread-pool workers spin-wait for work between operators (see the module
#: docstring): off by default.
ALLOW_SPINNING_DEFAULT: Final[bool] = False

#: Environment variable naming the fault-injection file (test hook; see the module docstring).
ORT_FAULT_FILE_ENV = "GDNAV_TEST_ORT_FAULT_FILE"


class _FaultHook:
    """The test hook of the module docstring: a count of runs to refuse, read from a file."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._lock = threading.Lock()
        self.injected = 0

    def take(self) -> bool:
        """True when this run must be refused (consumes one from the file's count)."""
        if not os.path.exists(self.path):
            return False
        with self._lock:
            try:
                with open(self.path, encoding="utf-8") as f:
                    count = int(f.read().strip() or "0")
            except (OSError, ValueError):
                return False
            try:
                if count <= 1:
                    os.unlink(self.path)
                else:
                    with open(self.path, "w", encoding="utf-8") as f:
                        f.write(str(count - 1))
            except OSError:
                return False
            if count < 1:
                return False
            self.injected += 1
            return True


#: ONNX Runtime's own exception classes (they derive from ``Exception`` directly, not RuntimeError).
_ORT_ERRORS: tuple[type[BaseException], ...] = (
    *(
        cls
        for name in (
            "Fail",
            "InvalidArgument",
            "NoSuchFile",
            "NoModel",
            "EngineError",
            "RuntimeException",
            "InvalidProtobuf",
            "ModelLoaded",
            "NotImplemented",
            "InvalidGraph",
            "EPFail",
        )
        if isinstance(cls := getattr(_ort_state, name, None), type)
    ),
    RuntimeError,
    ValueError,
    TypeError,
)

#: Errors that mean the model file is bad, whatever the provider.
_MODEL_ERRORS: tuple[type[BaseException], ...] = tuple(
    cls
    for name in ("InvalidProtobuf", "InvalidGraph", "NoSuchFile", "NoModel")
    if isinstance(cls := getattr(_ort_state, name, None), type)
)

# ONNX Runtime type strings -> numpy dtype names.
_ORT_TO_NUMPY: dict[str, str] = {
    "tensor(float)": "float32",
    "tensor(float16)": "float16",
    "tensor(double)": "float64",
    "tensor(bfloat16)": "bfloat16",
    "tensor(int8)": "int8",
    "tensor(int16)": "int16",
    "tensor(int32)": "int32",
    "tensor(int64)": "int64",
    "tensor(uint8)": "uint8",
    "tensor(uint16)": "uint16",
    "tensor(uint32)": "uint32",
    "tensor(uint64)": "uint64",
    "tensor(bool)": "bool",
    "tensor(string)": "str",
}

#: Warm-up sizes for dynamic dimensions: an image-like (rank-4) input gets 2x3x64x64 (a batch of two
#: keeps the fused pipeline's 2B layout valid), anything else 1 for the leading dim and 8 elsewhere.
_WARMUP_IMAGE_DIMS: tuple[int, ...] = (2, 3, 64, 64)
_WARMUP_LEADING = 1
_WARMUP_OTHER = 8


@dataclass(frozen=True)
class EngineInfo:
    """What was loaded, as the model itself declares it.

    ``inputs``/``outputs`` carry the model's declared names, ranks, dtypes and shapes (``None`` for a
    dynamic dimension). ``warmup`` is ``"ok"``, ``"skipped: <why>"``, ``"failed: <why>"`` or
    ``"disabled"``; ``warmup_shapes`` are the dummy input shapes used (empty when no warm-up ran).
    """

    engine_id: str
    path: str
    label: str
    provider: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    load_ms: float
    warmup: str
    warmup_shapes: tuple[tuple[str, tuple[int, ...]], ...]
    #: The session options set (``session_options_fields``), as logged with ``c7.inference.engine_loaded``.
    session_options: tuple[tuple[str, str], ...] = ()


@dataclass
class _Engine:
    info: EngineInfo
    session: ort.InferenceSession
    input_names: frozenset[str]
    lock: threading.Lock


def resolve_providers(requested: Sequence[str] | None = None) -> tuple[str, ...]:
    """Providers to try, in order: ``requested`` (default TensorRT -> CUDA -> CPU) that are available.

    Raises ``ValueError`` when none of them is available in this onnxruntime build.
    """
    wanted = tuple(requested) if requested is not None else PROVIDER_PREFERENCE
    available = set(ort.get_available_providers())
    chosen = tuple(p for p in wanted if p in available)
    if not chosen:
        raise ValueError(
            f"none of the execution providers {list(wanted)} is available "
            f"(onnxruntime offers {sorted(available)})"
        )
    return chosen


def _spec_from_node(node: Any) -> TensorSpec:
    """TensorSpec as declared by the model (ORT NodeArg): symbolic/unknown dims become None."""
    dims = tuple(d if isinstance(d, int) and d >= 0 else None for d in (node.shape or ()))
    return TensorSpec(
        name=node.name,
        rank=len(dims),
        dtype=_ORT_TO_NUMPY.get(node.type, node.type),
        shape=dims,
    )


def _describe(spec: TensorSpec) -> str:
    rank = "any rank" if spec.rank is None else f"rank {spec.rank}"
    return f"{rank} {spec.dtype}"


def _compare(kind: str, expected: TensorSpec, actual: TensorSpec) -> str | None:
    """One mismatch line, or None when the model's tensor satisfies the expectation."""
    rank_ok = expected.rank is None or expected.rank == actual.rank
    dtype_ok = actual.dtype in expected.dtypes
    if not (rank_ok and dtype_ok):
        return (
            f"{kind} '{expected.name}': expected {_describe(expected)}, "
            f"model has rank {actual.rank} {actual.dtype}"
        )
    if expected.shape is not None and actual.shape is not None and len(expected.shape) == len(actual.shape):
        for axis, (want, have) in enumerate(zip(expected.shape, actual.shape, strict=True)):
            if want is not None and have is not None and want != have:
                return (
                    f"{kind} '{expected.name}': dim {axis} expected {want}, model has {have} "
                    f"(model shape {list(actual.shape)})"
                )
    return None


def check_signature(
    signature: EngineSignature, inputs: Sequence[TensorSpec], outputs: Sequence[TensorSpec]
) -> list[str]:
    """All mismatches between a signature and a model's declared tensors (empty list = compatible).

    Every expected input and output must exist with a matching rank, dtype and fixed dims; extra model
    outputs are allowed; an extra model input is not (nothing would feed it).
    """
    problems: list[str] = []
    model_in = {s.name: s for s in inputs}
    model_out = {s.name: s for s in outputs}
    for kind, expected_specs, model in (
        ("input", signature.inputs, model_in),
        ("output", signature.outputs, model_out),
    ):
        for expected in expected_specs:
            actual = model.get(expected.name)
            if actual is None:
                problems.append(
                    f"{kind} '{expected.name}': missing (model {kind}s: {sorted(model) or 'none'})"
                )
                continue
            line = _compare(kind, expected, actual)
            if line is not None:
                problems.append(line)
    fed = {s.name for s in signature.inputs}
    problems.extend(
        f"input '{name}': required by the model but not in signature '{signature.label}'"
        for name in sorted(set(model_in) - fed)
    )
    return problems


def _warmup_feed(
    inputs: Sequence[TensorSpec],
) -> tuple[dict[str, np.ndarray] | None, str]:
    """Dummy inputs for a warm-up run, or (None, reason) when a shape or dtype cannot be guessed.

    Dynamic dims take small sizes (see ``_WARMUP_IMAGE_DIMS``). Defaults depend only on the position,
    so inputs sharing a dynamic dimension agree on it: kpts0 (1,8,2) and desc0 (1,8,D) both get N=8.
    """
    rng = np.random.default_rng(0)
    feed: dict[str, np.ndarray] = {}
    for spec in inputs:
        if spec.shape is None:
            return None, f"input '{spec.name}' has an unknown shape"
        try:
            dtype = np.dtype(spec.dtype)
        except TypeError:
            return None, f"input '{spec.name}' has dtype {spec.dtype}, no dummy value for it"
        if dtype.kind not in "fiub":
            return None, f"input '{spec.name}' has dtype {spec.dtype}, no dummy value for it"
        dims: list[int] = []
        for axis, dim in enumerate(spec.shape):
            if dim is not None:
                dims.append(dim)
            elif len(spec.shape) == 4:
                dims.append(_WARMUP_IMAGE_DIMS[axis])
            else:
                dims.append(_WARMUP_LEADING if axis == 0 else _WARMUP_OTHER)
        if dtype.kind == "f":
            feed[spec.name] = rng.random(dims, dtype=np.float32).astype(dtype)
        else:
            feed[spec.name] = np.zeros(dims, dtype=dtype)
    return feed, ""


def session_options_fields(
    intra_op_threads: int, *, allow_spinning: bool = ALLOW_SPINNING_DEFAULT
) -> tuple[tuple[str, str], ...]:
    """The session options of the module docstring, as (name, value) pairs (what ``session_options`` sets)."""
    spin = "1" if allow_spinning else "0"
    return (
        ("intra_op_num_threads", str(intra_op_threads)),
        ("inter_op_num_threads", "1"),
        ("execution_mode", "ORT_SEQUENTIAL"),
        ("graph_optimization_level", "ORT_ENABLE_ALL"),
        ("enable_cpu_mem_arena", "True"),
        ("enable_mem_pattern", "True"),
        ("session.intra_op.allow_spinning", spin),
        ("session.inter_op.allow_spinning", spin),
    )


def session_options(
    intra_op_threads: int, *, allow_spinning: bool = ALLOW_SPINNING_DEFAULT
) -> ort.SessionOptions:
    """A fresh ``SessionOptions`` with the module docstring's settings (errors-only ORT logging)."""
    if intra_op_threads < 1:
        raise ValueError(f"intra_op_threads must be >= 1, got {intra_op_threads}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = intra_op_threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.enable_cpu_mem_arena = True
    opts.enable_mem_pattern = True
    spin = "1" if allow_spinning else "0"
    opts.add_session_config_entry("session.intra_op.allow_spinning", spin)
    opts.add_session_config_entry("session.inter_op.allow_spinning", spin)
    # Errors only: failures reach the caller as EngineLoadError/InferenceError anyway.
    opts.log_severity_level = 3
    return opts


class OnnxInferenceRuntime:
    """``InferenceRuntime`` backed by ONNX Runtime sessions (see the module docstring).

    ``intra_op_threads``: threads per operator (``DaemonConfig.onnx_intra_op_threads``).
    ``providers``: execution providers to try in order; default TensorRT -> CUDA -> CPU. Unavailable
    ones are skipped; ``ValueError`` if none is available.
    ``warmup``: run one dummy forward pass at load time.
    ``provider_options``: optional per-provider option dicts (e.g. TensorRT's ``trt_fp16_enable``).
    ``allow_spinning``: let ONNX Runtime's idle workers spin-wait (off by default; see the module docstring).
    """

    def __init__(
        self,
        intra_op_threads: int = 2,
        providers: Sequence[str] | None = None,
        warmup: bool = True,
        *,
        provider_options: Mapping[str, Mapping[str, Any]] | None = None,
        allow_spinning: bool = ALLOW_SPINNING_DEFAULT,
    ) -> None:
        if intra_op_threads < 1:
            raise ValueError(f"intra_op_threads must be >= 1, got {intra_op_threads}")
        self._intra_op_threads = intra_op_threads
        self._allow_spinning = bool(allow_spinning)
        self._providers = resolve_providers(providers)
        self._warmup = warmup
        self._provider_options = {k: dict(v) for k, v in (provider_options or {}).items()}
        self._engines: dict[str, _Engine] = {}
        self._registry_lock = threading.Lock()
        self._counter = itertools.count(1)
        fault_file = os.environ.get(ORT_FAULT_FILE_ENV)
        self._fault = _FaultHook(fault_file) if fault_file else None
        if self._fault is not None:
            _log.warning(LogEvent.C7_FAULT_HOOK_ARMED, env=ORT_FAULT_FILE_ENV, path=fault_file)

    @property
    def providers(self) -> tuple[str, ...]:
        """Execution providers that will be tried, in order."""
        return self._providers

    def _session_options(self) -> ort.SessionOptions:
        return session_options(self._intra_op_threads, allow_spinning=self._allow_spinning)

    def _create_session(self, path: str) -> ort.InferenceSession:
        """Session on the first provider that accepts the model; later providers are fallbacks."""
        last_exc: BaseException | None = None
        for start in range(len(self._providers)):
            chain = self._providers[start:]
            options = [self._provider_options.get(p, {}) for p in chain]
            try:
                return ort.InferenceSession(
                    path,
                    sess_options=self._session_options(),
                    providers=list(chain),
                    provider_options=options,
                )
            except _ORT_ERRORS as exc:
                last_exc = exc
                if isinstance(exc, _MODEL_ERRORS):
                    break  # the file itself is bad: another provider will not help
                if len(chain) > 1:
                    _log.warning(
                        LogEvent.C7_PROVIDER_FALLBACK,
                        path=path,
                        provider=chain[0],
                        next_provider=chain[1],
                        error=str(exc),
                    )
        message = f"cannot create an ONNX Runtime session (providers {list(self._providers)}): {last_exc}"
        raise EngineLoadError(message, path=path) from last_exc

    def load_engine(self, path: str, signature: EngineSignature | None = None) -> str:
        """Create the session, check ``signature``, warm it up; returns the engine id.

        Raises ``EngineLoadError`` (with ``.path``) when the file is missing, is not a loadable ONNX
        model, or does not match ``signature``; the message lists every mismatch.
        """
        t0 = time.perf_counter()
        file = Path(path)
        if not file.is_file():
            what = "is a directory, not a model file" if file.is_dir() else "model file not found"
            raise EngineLoadError(what, path=path)
        session = self._create_session(path)
        inputs = tuple(_spec_from_node(n) for n in session.get_inputs())
        outputs = tuple(_spec_from_node(n) for n in session.get_outputs())
        label = signature.label if signature is not None else file.stem
        if signature is not None:
            problems = check_signature(signature, inputs, outputs)
            if problems:
                raise EngineLoadError(
                    f"model does not match signature '{signature.label}': " + "; ".join(problems), path=path
                )
        provider = session.get_providers()[0]
        warmup, warmup_shapes = self._run_warmup(session, path, inputs)
        load_ms = (time.perf_counter() - t0) * 1000.0
        with self._registry_lock:
            engine_id = f"{label}#{next(self._counter)}"
            info = EngineInfo(
                engine_id=engine_id,
                path=path,
                label=label,
                provider=provider,
                inputs=inputs,
                outputs=outputs,
                load_ms=load_ms,
                warmup=warmup,
                warmup_shapes=warmup_shapes,
                session_options=session_options_fields(
                    self._intra_op_threads, allow_spinning=self._allow_spinning
                ),
            )
            self._engines[engine_id] = _Engine(
                info=info,
                session=session,
                input_names=frozenset(s.name for s in inputs),
                lock=threading.Lock(),
            )
        _log.info(
            LogEvent.C7_ENGINE_LOADED,
            engine_id=engine_id,
            path=path,
            provider=provider,
            inputs={s.name: [s.dtype, list(s.shape or ())] for s in inputs},
            outputs={s.name: [s.dtype, list(s.shape or ())] for s in outputs},
            load_ms=round(load_ms, 1),
            warmup=warmup,
            intra_op_threads=self._intra_op_threads,
            session_options=dict(info.session_options),
        )
        return engine_id

    def _run_warmup(
        self, session: ort.InferenceSession, path: str, inputs: Sequence[TensorSpec]
    ) -> tuple[str, tuple[tuple[str, tuple[int, ...]], ...]]:
        if not self._warmup:
            return "disabled", ()
        feed, reason = _warmup_feed(inputs)
        if feed is None:
            _log.warning(LogEvent.C7_WARMUP_SKIPPED, path=path, reason=reason)
            return f"skipped: {reason}", ()
        shapes = tuple((name, tuple(int(d) for d in arr.shape)) for name, arr in feed.items())
        try:
            session.run(None, feed)
        except _ORT_ERRORS as exc:
            # The dummy shapes are a guess; a model that rejects them may still run on real inputs, so
            # this is reported rather than fatal.
            _log.warning(LogEvent.C7_WARMUP_FAILED, path=path, shapes=dict(shapes), error=str(exc).strip())
            return f"failed: {str(exc).strip()}", shapes
        return "ok", shapes

    def _engine(self, engine_id: str) -> _Engine:
        engine = self._engines.get(engine_id)
        if engine is None:
            raise InferenceError(
                f"unknown engine id '{engine_id}' (loaded: {sorted(self._engines) or 'none'})"
            )
        return engine

    def run(self, engine_id: str, inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """One forward pass; every model output by name. Raises ``InferenceError`` (chained)."""
        engine = self._engine(engine_id)
        missing = engine.input_names - set(inputs)
        if missing:
            raise InferenceError(
                f"engine '{engine_id}' ({engine.info.path}): missing inputs {sorted(missing)}; "
                f"got {sorted(inputs)}"
            )
        feed = {name: inputs[name] for name in engine.input_names}
        names = [s.name for s in engine.info.outputs]
        run_options = None
        if self._fault is not None and self._fault.take():
            run_options = ort.RunOptions()
            run_options.terminate = True  # ONNX Runtime refuses the run and raises its own Fail
        try:
            with engine.lock:
                values = engine.session.run(names, feed, run_options)
        except _ORT_ERRORS as exc:
            shapes = {k: f"{v.dtype}{list(np.shape(v))}" for k, v in feed.items()}
            raise InferenceError(
                f"engine '{engine_id}' ({engine.info.path}) failed on inputs {shapes}: {str(exc).strip()}"
            ) from exc
        return dict(zip(names, values, strict=True))

    def provider(self, engine_id: str) -> str:
        """Execution provider in use for the engine (e.g. ``CPUExecutionProvider``)."""
        return self._engine(engine_id).info.provider

    def engine_info(self, engine_id: str) -> EngineInfo:
        """What was loaded for ``engine_id``: path, provider, declared tensors, load and warm-up."""
        return self._engine(engine_id).info
