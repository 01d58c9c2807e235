"""XFeat with mutual nearest neighbours, label ``xfeat_mnn``: the real-time learned strategy for a CPU.

The same XFeat extractor as ``xfeat`` (model, preprocessing, keypoints, and so its precomputed tile
features: ``features_label`` is ``xfeat``), but no LightGlue model: a pair's matches are its mutual
nearest neighbours on L2-normalised descriptors, one (Nq, 64) x (64, Nt) matrix product and an argmax
each way (``helpers.lightglue_runtime.mutual_nearest_neighbours``); pairs with a cosine below
``XFEAT_MNN_MIN_SIMILARITY`` are dropped, RANSAC drops the other wrong ones.

Inputs: a nav frame and the re-ranked chips; outputs: RANSAC inliers per candidate, with no per-match
confidence (``inlier_scores`` None: a cosine is not a calibrated confidence, so the integrity rule's
``min_mean_confidence``, which applies only where a LightGlue model ran, does not apply).

Failure phases: ``xfeat_forward`` (a chip's forward pass) and ``mnn_match`` drop that candidate;
``xfeat_forward_query`` fails the whole frame.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from gps_denied_onboard.components.c3_matcher import xfeat
from gps_denied_onboard.components.c3_matcher.features import Features, TileFeatureSource
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.learned import require_runtimes
from gps_denied_onboard.components.c7_inference.protocol import InferenceRuntime
from gps_denied_onboard.components.c13_fdr.protocol import FdrClient
from gps_denied_onboard.config import MatcherConfig
from gps_denied_onboard.helpers.lightglue_runtime import mutual_nearest_neighbours
from gps_denied_onboard.helpers.ransac_filter import RansacFilter

LABEL: Final[str] = "xfeat_mnn"

#: Cosine below which a mutual pair is dropped. Measured on 60 NAIP cross-date frames (docs/benchmarks.md,
#: C3 matcher, xfeat_mnn): 0.7 solved 58 with 2 wrong, no floor 55 with 3; 0.5-0.6 change nothing, 0.8
#: loses a third of the frames, and Lowe's ratio test (0.8-0.95) loses most of them. No matching rule
#: tried (a higher floor, the ratio test, top-k by cosine, fewer keypoints) raises the inlier ratio to
#: ``integrity.min_inlier_ratio`` honestly: docs/benchmarks.md, "xfeat_mnn: evidence the integrity rule
#: accepts" (``tools/mnn_rules.py``).
XFEAT_MNN_MIN_SIMILARITY: Final[float] = 0.7


def match_mutual_nn(
    query: Features, tile: Features, *, min_similarity: float = XFEAT_MNN_MIN_SIMILARITY
) -> np.ndarray:
    """Correspondences (M, 4) float32 (query x, y, tile x, y px) of the features' mutual nearest
    neighbours by cosine (each is the other's best match; ties to the lower index), sorted by query index.
    No confidence column: the candidate loop then gives the integrity rule none."""
    if query.count == 0 or tile.count == 0:
        return np.empty((0, 4), dtype=np.float32)
    pairs, _similarity = mutual_nearest_neighbours(
        query.descriptors, tile.descriptors, min_similarity=min_similarity
    )
    return np.hstack([query.keypoints_px[pairs[:, 0]], tile.keypoints_px[pairs[:, 1]]]).astype(np.float32)


class XFeatMnnMatcher(xfeat.XFeatMatcher):
    """XFeat features via C7 + mutual nearest neighbours + shared RANSAC (see module docstring)."""

    label = LABEL
    match_phase = "mnn_match"
    features_label = xfeat.LABEL

    def match_features(self, query: Features, tile: Features) -> np.ndarray:
        return match_mutual_nn(query, tile)


def create(
    config: MatcherConfig,
    ransac_filter: RansacFilter,
    inference_runtime: InferenceRuntime,
    health_window: RollingHealthWindow,
    fdr_client: FdrClient | None = None,
    tile_features: TileFeatureSource | None = None,
) -> XFeatMnnMatcher:
    """Registry factory for ``xfeat_mnn``: builds the strategy, which loads the XFeat engine from
    ``config.xfeat_weights_path`` now; it takes no LightGlue helper."""
    require_runtimes(LABEL, inference_runtime=inference_runtime)
    return XFeatMnnMatcher(
        inference_runtime, None, ransac_filter, fdr_client, health_window, config, tile_features
    )
