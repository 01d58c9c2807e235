"""Refusals as a real `gdnav` process sees them: exit 2 (configuration) or 3 (a refused file or
resource), one plain line on stderr, never a traceback. `gdnav config check` refuses the
configuration-level ones with the same codes."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from daemon_harness import REPO, build_small_cache, free_tcp_port, free_udp_port

KEY_HEX = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff"
RUN = ("run",)
CHECK = ("config", "check")


def _gdnav(
    tmp_path: Path, command: tuple[str, ...], *overrides: str, config: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """`gdnav COMMAND --config sitl.yaml --set ...` in tmp_path, with ports and directories of its own.
    A daemon that starts instead of refusing is killed at the timeout (TimeoutExpired fails the test)."""
    cmd = [sys.executable, "-m", "gps_denied_onboard.cli", *command]
    cmd += ["--config", str(config or REPO / "config" / "sitl.yaml")]
    defaults = (
        f"camera.source=tcp://127.0.0.1:{free_tcp_port()}",
        f"mavlink.url=udpin:127.0.0.1:{free_udp_port()}",
        f"cache.dir={tmp_path / 'no-cache'}",
        f"fdr.dir={tmp_path / 'fdr'}",
    )
    if config is None:
        for item in (*defaults, *overrides):
            cmd += ["--set", item]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=tmp_path)


def _refusal(proc: subprocess.CompletedProcess[str], code: int) -> str:
    """Assert exit ``code`` and one plain refusal line, last on stderr; any other line must be one of the
    daemon's JSON log records (`gdnav run` logs its config before it can refuse a file). Returns it."""
    assert proc.returncode == code, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    plain = [ln for ln in lines if not ln.startswith("{")]
    assert plain == lines[-1:] and plain[0].startswith("gdnav: "), proc.stderr[-3000:]
    for ln in lines[:-1]:
        assert isinstance(json.loads(ln), dict)
    return plain[0]


def _config_refusal(proc: subprocess.CompletedProcess[str]) -> str:
    """A configuration refusal happens before logging starts: stderr is exactly one line, exit 2."""
    line = _refusal(proc, 2)
    assert proc.stderr.strip() == line
    return line


@pytest.mark.parametrize("command", [RUN, CHECK], ids=["run", "check"])
def test_cli_world_readable_signing_key_exits_3(tmp_path: Path, command: tuple[str, ...]) -> None:
    """A signing key file with mode 0644 is refused with exit 3, naming the file and the mode."""
    key = tmp_path / "mavlink.key"
    key.write_text(KEY_HEX)
    key.chmod(0o644)
    line = _refusal(_gdnav(tmp_path, command, f"mavlink.signing_key_file={key}"), 3)
    assert "mavlink.signing_key_file" in line and str(key) in line and "mode 0644" in line


@pytest.mark.parametrize("command", [RUN, CHECK], ids=["run", "check"])
def test_cli_invalid_mavlink_url_exits_2(tmp_path: Path, command: tuple[str, ...]) -> None:
    """An invalid mavlink.url is a configuration error naming the key path and the URL (the grammar's
    other cases are in test_config.py)."""
    url = "udpin:nohostport"
    line = _config_refusal(_gdnav(tmp_path, command, f"mavlink.url={url}"))
    assert "mavlink.url" in line and url in line


@pytest.mark.parametrize("command", [RUN, CHECK], ids=["run", "check"])
def test_cli_garbage_calibration_file_exits_3(tmp_path: Path, command: tuple[str, ...]) -> None:
    """A calibration file OpenCV cannot parse is refused with exit 3, naming the file."""
    calib = tmp_path / "calib.yaml"
    calib.write_bytes(b"garbage: [[[\x00\x01 not yaml %YAML\n")
    line = _refusal(_gdnav(tmp_path, command, f"camera.calibration_file={calib}"), 3)
    assert "camera.calibration_file" in line and str(calib) in line


@pytest.mark.parametrize("command", [RUN, CHECK], ids=["run", "check"])
def test_cli_non_utf8_config_exits_2(tmp_path: Path, command: tuple[str, ...]) -> None:
    """A profile that is not UTF-8 text is a configuration error naming the file."""
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"profile: \xff\xfe\n")
    line = _config_refusal(_gdnav(tmp_path, command, config=bad))
    assert str(bad) in line and "UTF-8" in line


def test_cli_run_non_utf8_cache_manifest_exits_3(tmp_path: Path) -> None:
    """A cache whose manifest is not UTF-8 text is refused at start-up with exit 3, naming the manifest."""
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "manifest.json").write_bytes(b"\xff\xfe{")
    line = _refusal(_gdnav(tmp_path, RUN, f"cache.dir={cache}"), 3)
    assert "cache" in line and "manifest.json" in line and "UTF-8" in line


@pytest.mark.parametrize("command", [RUN, CHECK], ids=["run", "check"])
def test_cli_fdr_max_bytes_below_segment_bytes_exits_2(tmp_path: Path, command: tuple[str, ...]) -> None:
    """fdr.max_bytes smaller than one segment is a configuration error naming fdr.max_bytes."""
    proc = _gdnav(tmp_path, command, "fdr.max_bytes=65536", "fdr.segment_bytes=1048576")
    line = _config_refusal(proc)
    assert "fdr.max_bytes" in line and "segment_bytes" in line


@pytest.mark.parametrize("command", [RUN, CHECK], ids=["run", "check"])
def test_cli_nan_ground_altitude_exits_2(tmp_path: Path, command: tuple[str, ...]) -> None:
    """terrain.ground_alt_amsl_m: .nan is a configuration error naming the key path."""
    line = _config_refusal(_gdnav(tmp_path, command, "terrain.ground_alt_amsl_m=.nan"))
    assert "terrain.ground_alt_amsl_m" in line and "finite" in line


@pytest.fixture(scope="module")
def small_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_small_cache(tmp_path_factory.mktemp("cache"))[1]


@pytest.mark.parametrize("bind_host", ["127.0.0.1", "0.0.0.0"])
def test_cli_run_udpin_port_held_by_another_socket_exits_3(
    tmp_path: Path, small_cache: Path, bind_host: str
) -> None:
    """With another process's socket on the daemon's udpin port (bound with SO_REUSEADDR, as pymavlink
    binds it), `gdnav run` refuses with exit 3 instead of starting and stealing that socket's input."""
    cache = small_cache
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as first:
        first.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        first.bind((bind_host, 0))
        port = first.getsockname()[1]
        url = f"udpin:127.0.0.1:{port}"
        line = _refusal(_gdnav(tmp_path, RUN, f"cache.dir={cache}", f"mavlink.url={url}"), 3)
    assert f"UDP port {port}" in line and "already bound" in line and url in line


@pytest.mark.parametrize("command", [RUN, CHECK], ids=["run", "check"])
@pytest.mark.parametrize("under", [False, True], ids=["file", "below-a-file"])
def test_cli_fdr_dir_not_a_directory_exits_3(tmp_path: Path, command: tuple[str, ...], under: bool) -> None:
    """An fdr.dir that is a regular file (or lies below one) is refused at start with exit 3: the daemon
    flew with no recorder, so its next restart had nothing to resume from."""
    (tmp_path / "fdr-file").write_text("not a directory\n")
    fdr = tmp_path / "fdr-file" / "fdr" if under else tmp_path / "fdr-file"
    line = _refusal(_gdnav(tmp_path, command, f"fdr.dir={fdr}"), 3)
    assert "fdr.dir" in line and str(fdr) in line and "not a directory" in line


@pytest.mark.parametrize(
    ("key", "value", "valid"),
    [("matcher.strategy", "clasical", "classical"), ("rerank.strategy", "inlier", "passthrough")],
    ids=["matcher", "rerank"],
)
def test_cli_config_check_refuses_a_misspelt_strategy_as_run_does(
    tmp_path: Path, key: str, value: str, valid: str
) -> None:
    """A misspelt strategy name fails `config check` with exit 3 and the very line `run` refuses it with
    (check passed it before), listing the valid names."""
    check = _refusal(_gdnav(tmp_path, CHECK, f"{key}={value}"), 3)
    run = _refusal(_gdnav(tmp_path, RUN, f"{key}={value}"), 3)
    assert check == run
    assert key in check and repr(value) in check and valid in check
