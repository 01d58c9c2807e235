"""compose_root: strategy selection from config, the model-directory gate, start-up refusals."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import structlog
from pymavlink.dialects.v20 import ardupilotmega as D

from aliked_fixture import aliked_t16_onnx  # noqa: F401 - session fixture
from daemon_harness import build_small_cache, free_udp_port
from gps_denied_onboard.clock import DaemonClock
from gps_denied_onboard.components.c3_matcher.aliked_lightglue import AlikedLightGlueMatcher
from gps_denied_onboard.components.c3_matcher.classical import ClassicalMatcher
from gps_denied_onboard.components.c10_cache_build.manifest import CacheManifest, Verification
from gps_denied_onboard.config import load_config
from gps_denied_onboard.runtime_root import StartupError, compose_root
from gps_denied_onboard.runtime_root.compose import cache_verification
from gps_denied_onboard.runtime_root.link_first import open_link_first

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_small_cache(tmp_path_factory.mktemp("compose"))[1]


def _config(tmp_path: Path, cache: Path, *sets: str):  # type: ignore[no-untyped-def]
    return load_config(
        REPO / "config" / "sitl.yaml", [f"cache.dir={cache}", f"fdr.dir={tmp_path / 'fdr'}", *sets]
    )


def test_compose_auto_without_model_dir_runs_classical(tmp_path: Path, cache_dir: Path) -> None:
    """strategy auto with no model directory builds the weights-free matcher and says why."""
    with structlog.testing.capture_logs() as logs:
        root = compose_root(_config(tmp_path, cache_dir, "matcher.strategy=auto", "matcher.model_dir=null"))
    root.close()
    assert isinstance(root.matcher, ClassicalMatcher)
    picked = [e for e in logs if e["event"] == "c3.matcher.auto_selected"]
    assert picked and picked[0]["strategy"] == "classical" and "model_dir" in picked[0]["reason"]


def test_compose_auto_with_verified_aliked_export_runs_aliked(
    tmp_path: Path,
    cache_dir: Path,
    aliked_t16_onnx: Path,  # noqa: F811
) -> None:
    """strategy auto with a verified ALIKED model directory builds aliked_lightglue from it."""
    root = compose_root(
        _config(tmp_path, cache_dir, "matcher.strategy=auto", f"matcher.model_dir={aliked_t16_onnx.parent}")
    )
    root.close()
    assert isinstance(root.matcher, AlikedLightGlueMatcher)


def test_compose_tampered_model_dir_refuses_explicit_strategy_but_auto_falls_back(
    tmp_path: Path,
    cache_dir: Path,
    aliked_t16_onnx: Path,  # noqa: F811
) -> None:
    """A model directory whose manifest does not match its files: an explicit learned strategy is
    refused at start-up naming the file; auto falls back to classical and says why."""
    bad = tmp_path / "models"
    bad.mkdir()
    (bad / aliked_t16_onnx.name).write_bytes(aliked_t16_onnx.read_bytes()[:-16] + b"\0" * 16)
    (bad / "manifest.json").write_text((aliked_t16_onnx.parent / "manifest.json").read_text())
    with pytest.raises(StartupError) as err:
        compose_root(
            _config(tmp_path, cache_dir, "matcher.strategy=aliked_lightglue", f"matcher.model_dir={bad}")
        )
    assert err.value.what == "matcher.model_dir" and aliked_t16_onnx.name in str(err.value)
    with structlog.testing.capture_logs() as logs:
        root = compose_root(_config(tmp_path, cache_dir, "matcher.strategy=auto", f"matcher.model_dir={bad}"))
    root.close()
    assert isinstance(root.matcher, ClassicalMatcher)
    assert any(e["event"] == "c3.matcher.auto_selected" and "unusable" in e["reason"] for e in logs)


def test_compose_auto_with_absent_model_dir_runs_classical(tmp_path: Path, cache_dir: Path) -> None:
    """A fresh machine: sitl.yaml's model directory does not exist; auto runs classical and says why,
    and an explicit classical strategy never looks at the directory."""
    absent = tmp_path / "no-models"
    with structlog.testing.capture_logs() as logs:
        root = compose_root(
            _config(tmp_path, cache_dir, "matcher.strategy=auto", f"matcher.model_dir={absent}")
        )
    root.close()
    assert isinstance(root.matcher, ClassicalMatcher)
    assert any(e["event"] == "c3.matcher.auto_selected" and "unusable" in e["reason"] for e in logs)
    root = compose_root(
        _config(tmp_path, cache_dir, "matcher.strategy=classical", f"matcher.model_dir={absent}")
    )
    root.close()
    assert isinstance(root.matcher, ClassicalMatcher)


def test_compose_missing_disk_model_refuses_start(tmp_path: Path, cache_dir: Path) -> None:
    """The airborne default (disk_lightglue) with no model file stops start-up naming the file."""
    missing = tmp_path / "disk.onnx"
    with pytest.raises(StartupError) as err:
        compose_root(
            _config(
                tmp_path, cache_dir, "matcher.strategy=disk_lightglue", f"matcher.disk_weights_path={missing}"
            )
        )
    assert "disk.onnx" in str(err.value)


def test_compose_unknown_strategy_lists_valid_names(tmp_path: Path, cache_dir: Path) -> None:
    """An unknown matcher name is refused with the list of linked strategies."""
    with pytest.raises(StartupError) as err:
        compose_root(_config(tmp_path, cache_dir, "matcher.strategy=superglue"))
    assert "classical" in str(err.value) and "aliked_lightglue" in str(err.value)
    assert err.value.what == "matcher.strategy"


def test_auto_orders_by_what_this_machine_can_run() -> None:
    """``auto``: with a GPU execution provider the seed's default (DISK + LightGlue) first; on a CPU alone
    the cheapest fix first, and the reason names which."""
    from gps_denied_onboard.runtime_root.compose import auto_order

    order, why = auto_order(("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"))
    assert order[0] == "disk_lightglue" and "TensorrtExecutionProvider" in why
    order, why = auto_order(("CPUExecutionProvider",))
    assert order[0] == "xfeat" and order[-1] == "disk_lightglue" and "CPU only" in why


@pytest.fixture(scope="module")
def cache_with_fields(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from gps_denied_onboard.components.c10_cache_build.map_fields import build_map_fields

    cache = build_small_cache(tmp_path_factory.mktemp("compose_fields"))[1]
    build_map_fields(cache, progress=False)
    return cache


def test_compose_auto_on_a_cpu_flies_the_area_correlation_first_on_a_calibrated_cache(
    tmp_path: Path, cache_with_fields: Path
) -> None:
    """auto on a CPU alone with the cache's calibrated orientation fields: orientation_corr is the fast
    rung, the keypoint strategy auto picked the heavy one, and the log says why."""
    with structlog.testing.capture_logs() as logs:
        root = compose_root(
            _config(tmp_path, cache_with_fields, "matcher.strategy=auto", "matcher.model_dir=null")
        )
    root.close()
    ladder = root.pipeline.ladder
    assert ladder is not None
    assert [(r.name, r.strategy) for r in ladder.rungs] == [
        ("correlation", "orientation_corr"),
        ("keypoints", "classical"),
    ]
    picked = [e for e in logs if e["event"] == "c3.matcher.auto_selected" and e.get("area_rung")]
    assert picked and "calibrated" in picked[0]["reason"]


def test_compose_auto_without_fields_keeps_the_keypoint_matcher_alone(
    tmp_path: Path, cache_dir: Path
) -> None:
    with structlog.testing.capture_logs() as logs:
        root = compose_root(_config(tmp_path, cache_dir, "matcher.strategy=auto", "matcher.model_dir=null"))
    root.close()
    ladder = root.pipeline.ladder
    assert ladder is not None and [r.strategy for r in ladder.rungs] == ["classical"]
    assert any(e.get("area_rung") is False and "gdnav cache fields" in e["reason"] for e in logs)


def test_compose_orientation_corr_without_fields_refuses_start_naming_the_command(
    tmp_path: Path, cache_dir: Path
) -> None:
    with pytest.raises(StartupError, match="gdnav cache fields"):
        compose_root(_config(tmp_path, cache_dir, "matcher.strategy=orientation_corr"))


def _decoded(msg: Any) -> Any:
    """``msg`` as the autopilot (system 1, component 1) sends it, packed and decoded."""
    tx = D.MAVLink(None, srcSystem=1, srcComponent=1)
    return D.MAVLink(None).decode(bytearray(msg.pack(tx)))


def _flip_middle_mosaic_byte(cache: Path) -> None:
    mosaic = np.load(cache / CacheManifest.load(cache).mosaic_name, mmap_mode="r")
    height, width = mosaic.shape[:2]
    at = int(mosaic.offset) + ((height // 2) * width + width // 2) * 3
    del mosaic
    with (cache / CacheManifest.load(cache).mosaic_name).open("r+b") as f:
        f.seek(at)
        byte = f.read(1)[0]
        f.seek(at)
        f.write(bytes([byte ^ 0xFF]))


def test_cache_verification_is_full_only_when_asked_and_on_the_ground(tmp_path: Path) -> None:
    """The daemon's level: light unless cache.verify_hashes asks for full and the autopilot says the
    vehicle is on the ground; in the air, or with nothing known, light whatever the config says."""
    off = _config(tmp_path, tmp_path)
    on = _config(tmp_path, tmp_path, "cache.verify_hashes=true")
    assert off.cache.verify_hashes is False, "the shipped profile's default"
    assert [cache_verification(off, air)[0] for air in (False, True, None)] == [Verification.LIGHT] * 3
    assert cache_verification(on, False)[0] is Verification.FULL
    assert cache_verification(on, True) == (
        Verification.LIGHT,
        "cache.verify_hashes set aside: in the air (never re-hashed in flight)",
    )
    assert cache_verification(on, None)[0] is Verification.LIGHT


def test_compose_never_rehashes_the_map_in_the_air_whatever_the_config(
    tmp_path: Path, cache_dir: Path
) -> None:
    """cache.verify_hashes: true on a cache with one corrupt byte in the middle of its mosaic. The
    autopilot says flying (a restart in the air): the daemon starts on the light check, which does not
    read the mosaic; it says on the ground: the full check reads it and refuses the cache, naming it."""
    cache = tmp_path / "cache"
    shutil.copytree(cache_dir, cache)
    _flip_middle_mosaic_byte(cache)
    for landed, armed in ((D.MAV_LANDED_STATE_IN_AIR, True), (D.MAV_LANDED_STATE_ON_GROUND, False)):
        run = tmp_path / f"run{landed}"
        config = _config(
            run, cache, "cache.verify_hashes=true", f"mavlink.url=udpin:127.0.0.1:{free_udp_port()}"
        )
        clock = DaemonClock()
        link = open_link_first(config, clock)
        mode = D.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (D.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        heartbeat = D.MAVLink_heartbeat_message(D.MAV_TYPE_QUADROTOR, D.MAV_AUTOPILOT_PX4, mode, 0, 4, 3)
        state = D.MAVLink_extended_sys_state_message(D.MAV_VTOL_STATE_UNDEFINED, landed)
        now_s = clock.now_unix_s()
        for msg in (heartbeat, state):
            assert link.tracker.handle(_decoded(msg), now_s)
        with structlog.testing.capture_logs() as logs:
            if landed == D.MAV_LANDED_STATE_IN_AIR:
                root = compose_root(config, pre_constructed={"clock": clock, "link": link})
                root.close()
                assert root.tile_store.verification is Verification.LIGHT
            else:
                with pytest.raises(StartupError, match=r"mosaic_z\d+\.npy.*sha256 mismatch"):
                    compose_root(config, pre_constructed={"clock": clock, "link": link})
                link.close()
        opened = [e for e in logs if e["event"] == "c6.cache.opened" and "why" in e]
        if landed == D.MAV_LANDED_STATE_IN_AIR:
            assert opened and "in the air" in opened[0]["why"]
