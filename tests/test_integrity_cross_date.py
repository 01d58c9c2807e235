"""Fix integrity on real cross-date imagery: NAIP 2009 map, frames rendered from the 2020 image.

ALIKED with mutual-nearest-neighbour matching finds a few dozen self-consistent matches per frame at
1200 m AGL across eleven years, and the fixes they give are tens of metres wrong with a stated sigma of
about ten (docs/benchmarks.md). The same flight is flown twice, the rule recorded but off and then on:
off, the flight must show such fixes (otherwise this test proves nothing); on, none is accepted, the rule
says why it refused each, and the estimate stays within its stated accuracy.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from aliked_fixture import aliked_t16_onnx  # noqa: F401  (session fixture)
from conftest import shared_path
from gps_denied_onboard.sitl.runner import SitlOptions, run_sitl, summary_lines

pytestmark = [pytest.mark.sitl, pytest.mark.realdata, pytest.mark.slow]

NAIP = ("data", "naip_timeseries", "naip")
#: Long enough for the first wrong fixes to be offered and fused (the first ~15 s of the flight).
DURATION_S = 40.0


def _fly(root: Path, onnx: Path, *overrides: str) -> dict:
    return run_sitl(
        SitlOptions(
            map_path=shared_path(*NAIP, "m_4709963_se_14_1_20090818.tif"),
            appearance_path=shared_path(*NAIP, "m_4709963_se_14_1_20200831.tif"),
            scenario="naip_cross_date",
            report_path=root / "report.json",
            workdir=root / "work",
            overrides=(
                "matcher.strategy=aliked_lightglue",
                f"matcher.aliked_weights_path={onnx}",
                *overrides,
            ),
            duration_s=DURATION_S,
            quiet=True,
        )
    )


def test_aliked_cross_date_fixes_beyond_3_sigma_are_refused(
    tmp_path_factory: pytest.TempPathFactory,
    aliked_t16_onnx: Path,  # noqa: F811
) -> None:
    off = _fly(tmp_path_factory.mktemp("integrity_off"), aliked_t16_onnx, "integrity.enabled=false")
    a_off = off["analysis"]
    assert a_off["accepted_fixes_beyond_3sigma"] >= 1, (a_off, summary_lines(off))

    on = _fly(tmp_path_factory.mktemp("integrity_on"), aliked_t16_onnx)
    a_on = on["analysis"]
    assert a_on["accepted_fixes_beyond_3sigma"] == 0, (a_on, summary_lines(on))
    assert a_on["no_fix_reasons"].get("integrity", 0) >= 1, a_on["no_fix_reasons"]
    # What leaves the daemon is within its stated accuracy: the flight's consistency, not just the fixes.
    assert on["consistency"]["beyond_3sigma"] == 0, summary_lines(on)
