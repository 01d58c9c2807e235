"""The inference contract: a loaded inference engine, run by name with named numpy tensors.

C7 implements it (``components.c7_inference``); the shared helpers (``lightglue_runtime``,
``onnx_signatures``) and the build-time exporters (``models``) speak it, so it lives below all of them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class TensorSpec:
    """Expected tensor: name, rank (None = any) and numpy dtype name (``float32``, ``int64``...).

    ``dtype`` may list accepted alternatives separated by ``|`` (``"int64|float32"``: the LightGlue-ONNX
    exports disagree on the keypoint dtype). ``shape``, when given, has one entry per dimension: an int
    is a fixed size that a model with a static dimension there must have (``descriptors`` D=128), None
    accepts anything; dynamic model dimensions always pass.
    """

    name: str
    rank: int | None
    dtype: str
    shape: tuple[int | None, ...] | None = None

    @property
    def dtypes(self) -> tuple[str, ...]:
        """The accepted numpy dtype names (``dtype`` split on ``|``)."""
        return tuple(part.strip() for part in self.dtype.split("|") if part.strip())


@dataclass(frozen=True)
class EngineSignature:
    """What a strategy expects of a model file; checked at load time, never at the first frame."""

    label: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]


@runtime_checkable
class InferenceRuntime(Protocol):
    def load_engine(self, path: str, signature: EngineSignature | None = None) -> str:
        """Load (and warm up) a model file; returns an engine id. Raises ``EngineLoadError``."""
        ...

    def run(self, engine_id: str, inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run one forward pass; outputs by name. Raises ``InferenceError``."""
        ...

    def provider(self, engine_id: str) -> str:
        """Execution provider in use for the engine (e.g. ``CPUExecutionProvider``)."""
        ...


class InferenceError(RuntimeError):
    """A forward pass failed."""


class EngineLoadError(RuntimeError):
    """A model file is missing, unreadable, or its signature is not what the strategy expects."""

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path
