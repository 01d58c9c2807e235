"""C2 contracts (seed ``c2_visual_place_recognition.md``)."""

from __future__ import annotations

import uuid
from dataclasses import dataclass

import numpy as np

from gps_denied_onboard.components.c6_tiles.types import TileId


@dataclass(frozen=True)
class VprQuery:
    frame_id: uuid.UUID
    #: (D,) float32, L2-normalised; D = the strategy's ``descriptor_dim()``.
    embedding: np.ndarray
    produced_at: int  # monotonic_ns


@dataclass(frozen=True)
class VprCandidate:
    tile_id: TileId
    #: Backbone metric; for L2-normalised embeddings the L2 distance (cosine-equivalent). For the
    #: geographic prior strategy: ground distance in metres from the prior to the tile centre.
    descriptor_distance: float
    descriptor_dim: int


@dataclass(frozen=True)
class VprResult:
    frame_id: uuid.UUID
    #: Ranked by ``descriptor_distance`` ascending; up to k entries.
    candidates: list[VprCandidate]
    retrieved_at: int  # monotonic_ns
    backbone_label: str


class VprError(RuntimeError):
    """Base of C2 errors."""


class VprBackboneError(VprError):
    """The backbone forward pass failed; no VprResult for this frame."""

    def __init__(self, message: str, *, backbone: str, frame_id: uuid.UUID | None = None) -> None:
        super().__init__(f"{message} (backbone={backbone}, frame={frame_id})")
        self.backbone = backbone
        self.frame_id = frame_id


class IndexUnavailableError(VprError):
    """The descriptor index cannot be searched (missing, not loaded, wrong dimension)."""

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{message} ({path})" if path else message)
        self.path = path
