"""The shared base of the learned C3 strategies: one ONNX extractor run the same way on the query and on
tiles, features matched pairwise, inside the candidate loop of ``base.CandidateLoopMatcher``.

A strategy names its extractor (``weights_field``, ``signature``) and implements ``_forward`` (one image
-> ``Features`` in its own pixels), helped by ``unpack_extractor_outputs`` and ``strongest_in_image_px``.
This base loads the engine at construction (a missing or mismatched model fails at start-up), matches with
the shared LightGlue helper (a strategy may override ``match_features``), takes precomputed tile features
only when they were made by this very extractor (``extractor_identity``), and gives the registry its
factory (``create``).
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from typing import ClassVar, TypeVar

import numpy as np

from gps_denied_onboard.components.c3_matcher.base import CandidateLoopMatcher, match_with_lightglue
from gps_denied_onboard.components.c3_matcher.features import Features, TileFeatureSource
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.tile_features import ExtractorIdentity
from gps_denied_onboard.components.c7_inference.protocol import (
    EngineLoadError,
    EngineSignature,
    InferenceRuntime,
)
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.helpers.lightglue_runtime_protocol import LightGluePairMatcher
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

_M = TypeVar("_M", bound="LearnedPairMatcher")


class LearnedPairMatcher(CandidateLoopMatcher):
    """A learned extractor run the same way on the query and on tiles (``_forward``), whose features are
    matched by the shared LightGlue helper (``self._lightglue_runtime``): DISK, ALIKED, XFeat."""

    match_phase = "lightglue_match"
    #: ``MatcherConfig`` field holding the extractor's ONNX file, and the signature it must follow.
    weights_field: ClassVar[str]
    signature: ClassVar[EngineSignature]
    #: What the refusal of an unset ``weights_field`` says the strategy needs.
    model_needed: ClassVar[str]
    #: Name of the tile-feature set (files, manifest entry) this extractor makes; None = ``label``.
    #: Strategies that share an extractor share its precomputed features.
    features_label: ClassVar[str | None] = None

    def __init__(
        self,
        runtime: InferenceRuntime,
        lightglue_runtime: LightGluePairMatcher | None,
        ransac_filter: RansacFilter,
        fdr_client: FdrClient | None,
        health_window: RollingHealthWindow,
        config: MatcherConfig,
        tile_features: TileFeatureSource | None = None,
    ) -> None:
        """Loads the extractor from ``config.<weights_field>`` (C7's ``EngineLoadError`` when it is unset,
        missing, or does not match ``signature`` or ``_check_model``)."""
        super().__init__(
            ransac_filter=ransac_filter, fdr_client=fdr_client, health_window=health_window, config=config
        )
        path = getattr(config, self.weights_field)
        if not path:
            raise EngineLoadError(
                f"not set; the {self.label} strategy needs {self.model_needed}",
                path=f"matcher.{self.weights_field}",
            )
        self._runtime = runtime
        self._lightglue_runtime = lightglue_runtime
        self._model_path = str(path)
        self._identity: ExtractorIdentity | None = None
        self._engine_id = runtime.load_engine(self._model_path, self.signature)
        self._check_model()
        self._long_side_px = int(config.input_long_side_px)
        self._max_keypoints = int(config.max_keypoints)
        if tile_features is not None and tile_features.identity != self.extractor_identity:
            # A set of another model must never be mixed in; the composition root opens the set for
            # this identity.
            raise ValueError(
                f"precomputed tile features made by {tile_features.identity} given to the {self.label} "
                f"strategy whose extractor is {self.extractor_identity}"
            )
        self._tile_features = tile_features

    @classmethod
    def create(
        cls: type[_M],
        config: MatcherConfig,
        lightglue_runtime: LightGluePairMatcher,
        ransac_filter: RansacFilter,
        inference_runtime: InferenceRuntime,
        health_window: RollingHealthWindow,
        fdr_client: FdrClient | None = None,
        tile_features: TileFeatureSource | None = None,
    ) -> _M:
        """Registry factory of a strategy that matches with the LightGlue helper: builds it, which loads
        its extractor now. ValueError when the composition root did not wire the ONNX collaborators."""
        require_runtimes(cls.label, inference_runtime=inference_runtime, lightglue_runtime=lightglue_runtime)
        return cls(
            inference_runtime,
            lightglue_runtime,
            ransac_filter,
            fdr_client,
            health_window,
            config,
            tile_features,
        )

    @property
    def engine_id(self) -> str:
        return self._engine_id

    @property
    def extractor_identity(self) -> ExtractorIdentity:
        """``tile_features.ExtractorIdentity`` of this strategy's tile features (model sha256, chip size,
        keypoint cap, input size): what a precomputed set must have been made with. Hashes the model
        file on first use (OSError when it cannot be read)."""
        if self._identity is None:
            self._identity = ExtractorIdentity.of(
                self.features_label or self.label, self._model_path, self._config
            )
        return self._identity

    # --- hooks ---------------------------------------------------------------------------------------
    def _check_model(self) -> None:
        """Refuse (``EngineLoadError``) a loaded model the signature cannot rule out; read its layout."""

    @abc.abstractmethod
    def _forward(self, image_bgr: np.ndarray) -> Features:
        """Features of one image in its original pixel coordinates."""

    def extract_query(self, image_bgr: np.ndarray) -> Features:
        return self._forward(image_bgr)

    def extract_tile(self, chip_bgr: np.ndarray) -> Features:
        return self._forward(chip_bgr)

    def match_features(self, query: Features, tile: Features) -> np.ndarray:
        return match_with_lightglue(self._lightglue_runtime, query, tile)


def unpack_extractor_outputs(
    outputs: Mapping[str, np.ndarray],
    name: str,
    error: type[ValueError],
    descriptor_dim: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An extractor's outputs in the LightGlue-ONNX layout -> keypoints (N, 2) float32 (x, y) px of the
    input tensor, scores (N,) float32, descriptors (N, D) float32 (D = ``descriptor_dim`` when given).

    Raises ``error`` naming the model ``name`` for a missing output or shapes that disagree.
    """
    try:
        kpts = np.asarray(outputs["keypoints"])
        scores = np.asarray(outputs["scores"])
        desc = np.asarray(outputs["descriptors"])
    except KeyError as exc:
        raise error(f"{name} output {exc} missing; got {sorted(outputs)}") from exc
    if kpts.ndim != 3 or kpts.shape[0] != 1 or kpts.shape[2] != 2:
        raise error(f"keypoints must be (1, N, 2), got {kpts.shape}")
    n = kpts.shape[1]
    if descriptor_dim is not None:
        if scores.shape != (1, n) or desc.shape != (1, n, descriptor_dim):
            raise error(
                f"scores {scores.shape} / descriptors {desc.shape} do not match (1, {n}) / "
                f"(1, {n}, {descriptor_dim})"
            )
    elif scores.shape != (1, n) or desc.ndim != 3 or desc.shape[:2] != (1, n):
        raise error(f"scores {scores.shape} / descriptors {desc.shape} do not match {n} keypoints")
    return kpts[0].astype(np.float32), scores[0].astype(np.float32), desc[0].astype(np.float32)


def strongest(
    pts: np.ndarray, scores: np.ndarray, desc: np.ndarray, max_keypoints: int
) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints, descriptors) of the ``max_keypoints`` highest scores (stable: ties keep their order),
    or all of them when there are no more than that."""
    if pts.shape[0] <= max_keypoints:
        return pts, desc
    order = np.argsort(-scores, kind="stable")[:max_keypoints]
    return pts[order], desc[order]


def tensor_to_image_px(pts: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """(N, 2) tensor px -> (N, 2) float32 px of the original image, tensor px = image px * (sx, sy)
    (pixel centres: (u + 0.5) / s - 0.5)."""
    return np.column_stack([(pts[:, 0] + 0.5) / sx - 0.5, (pts[:, 1] + 0.5) / sy - 0.5]).astype(np.float32)


def require_runtimes(label: str, **runtimes: object) -> None:
    """Refuse to build a learned strategy whose ONNX collaborators the composition root did not wire
    (ValueError naming the strategy and the missing ones)."""
    missing = [name for name, value in runtimes.items() if value is None]
    if missing:
        raise ValueError(f"the {label} strategy needs {missing} (not wired by the composition root)")
