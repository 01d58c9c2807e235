"""C7 contract: a loaded inference engine, run by name with named numpy tensors."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class TensorSpec:
    """Expected tensor: name, rank (None = any) and numpy dtype name (``float32``, ``int64``...)."""

    name: str
    rank: int | None
    dtype: str


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
