"""C2.5 strategy interface."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from gps_denied_onboard.camera.types import NavCameraFrame
from gps_denied_onboard.components.c2_5_rerank.types import RerankResult
from gps_denied_onboard.components.c2_vpr.types import VprResult


@runtime_checkable
class RerankStrategy(Protocol):
    def rerank(self, frame: NavCameraFrame, vpr_result: VprResult) -> RerankResult: ...
