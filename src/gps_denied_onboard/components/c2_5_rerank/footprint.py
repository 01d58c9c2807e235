"""C2.5's last step: when the prior is tight, the first chip C3 matches is cut around the footprint.

A tile's chip is centred on the tile, so it holds the camera's footprint only in part: the ground under
the camera can be up to half a tile (and, for the second and third candidates, more) from the chip's
centre. Across dates, where the matchers are short of inliers, that part matters. Measured on NAIP (2009
map at 3.3 m/px, 2014 frames at 1200 m AGL, one flight replayed through the fix path on every frame;
``docs/benchmarks.md``, "Chips around the footprint"): with XFeat + LighterGlue 160 of 161 fixes were
accepted with it against 152 without (best candidate's median inliers 124 against 97); with ALIKED +
LightGlue half as many frames had too few inliers (9 against 18), but more were then refused for low
match confidence, and 108 were accepted against 109; with DISK + LightGlue 114 against 109 (median
inliers 65 against 46). Nothing was accepted beyond 3 sigma either way.

``FootprintChips.first`` puts such a chip at the head of the candidates, in place of the candidate of the
same tile or else of the last one, so C3 still matches ``top_n`` chips. It applies only while the prior
places the footprint's centre within ``max_offset_frac`` of the chip's side at 3 sigma: otherwise the
chip would be centred on a guess, and the tiles C2 found are what C3 should see. The chip is the map's
pixels like any other; the integrity rule, the rivals and the gates judge its fix as they judge any fix.
"""

from __future__ import annotations

import math
from typing import Final

from gps_denied_onboard.components.c2_5_rerank.types import RerankCandidate, RerankResult
from gps_denied_onboard.components.c6_tiles.store import TileStore

#: The prior's 3-sigma offset, as a share of the chip's side, up to which the chip is cut around it.
FOOTPRINT_CHIP_MAX_OFFSET_FRAC: Final[float] = 0.125


class FootprintChips:
    """Cuts the footprint chip (``TileStore.chip_around``) and puts it first; see the module docstring."""

    def __init__(
        self,
        tile_store: TileStore,
        *,
        chip_size_px: int,
        max_offset_frac: float = FOOTPRINT_CHIP_MAX_OFFSET_FRAC,
    ) -> None:
        if chip_size_px < 1:
            raise ValueError(f"chip_size_px must be >= 1, got {chip_size_px}")
        self._tiles = tile_store
        self._chip_size_px = int(chip_size_px)
        #: Largest prior sigma (m, 1 sigma horizontal) for which the chip is cut around the footprint.
        self.max_sigma_m = max_offset_frac * chip_size_px * tile_store.gsd_m_px / 3.0

    def applies(self, horiz_sigma_m: float) -> bool:
        """Whether a prior of ``horiz_sigma_m`` (1 sigma, m) is tight enough to cut around."""
        return math.isfinite(horiz_sigma_m) and horiz_sigma_m <= self.max_sigma_m

    def first(self, result: RerankResult, lat_deg: float, lon_deg: float) -> RerankResult:
        """``result`` with the chip around (``lat_deg``, ``lon_deg``) first, as many candidates as before;
        ``result`` itself when the point is off the map or there are no candidates."""
        if not result.candidates:
            return result
        chip = self._tiles.chip_around(lat_deg, lon_deg, self._chip_size_px)
        if chip is None:
            return result
        same = [c for c in result.candidates if c.tile_id == chip.tile_id]
        rest = [c for c in result.candidates if c.tile_id != chip.tile_id]
        head = RerankCandidate(
            chip.tile_id,
            chip,
            rerank_inliers=-1,
            vpr_distance=same[0].vpr_distance if same else math.nan,
        )
        kept = [head, *rest][: len(result.candidates)]
        return RerankResult(frame_id=result.frame_id, candidates=kept, reranked_at=result.reranked_at)
