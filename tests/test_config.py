"""Config loading: strict validation, one-line key-path errors, exit code 2 from the CLI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from gps_denied_onboard.config import ConfigError, config_to_dict, load_config

REPO = Path(__file__).resolve().parents[1]


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cfg.yaml"
    p.write_text(text)
    return p


def test_config_profiles_load_with_expected_strategies() -> None:
    """Both shipped profiles validate; airborne defaults to disk_lightglue, sitl to auto (ALIKED when an
    export is in models/, else the weights-free classical matcher)."""
    airborne = load_config(REPO / "config" / "airborne.yaml")
    sitl = load_config(REPO / "config" / "sitl.yaml")
    assert airborne.matcher.strategy == "disk_lightglue"
    assert sitl.matcher.strategy == "auto" and sitl.matcher.model_dir == "models"
    assert sitl.mavlink.outputs == ("gps_input",)


def test_config_unknown_key_names_path(tmp_path: Path) -> None:
    """A misspelt key is an error naming its dotted path, not silently ignored."""
    with pytest.raises(ConfigError) as err:
        load_config(_write(tmp_path, "matcher:\n  min_inlier_threshold: 30\n"))
    assert err.value.key_path == "matcher.min_inlier_threshold"
    assert "unknown key" in str(err.value)


def test_config_wrong_type_is_not_coerced(tmp_path: Path) -> None:
    """A quoted number is a string, not an int: strict types, no coercion."""
    with pytest.raises(ConfigError) as err:
        load_config(_write(tmp_path, "camera:\n  queue_depth: '3'\n"))
    assert err.value.key_path == "camera.queue_depth"
    assert "integer" in str(err.value)


def test_config_out_of_range_names_bound(tmp_path: Path) -> None:
    """An out-of-range value names the bound that was expected and the value given."""
    with pytest.raises(ConfigError) as err:
        load_config(_write(tmp_path, "rerank:\n  top_n: 11\n"))
    assert err.value.key_path == "rerank.top_n"
    assert "less than or equal to 10" in str(err.value) and "11" in str(err.value)


def test_config_bad_literal_lists_valid_values() -> None:
    """An unknown output kind lists the valid ones."""
    with pytest.raises(ConfigError) as err:
        load_config(None, ["mavlink.outputs=[gps_input, gps_output]"])
    assert "gps_input" in str(err.value) and "global_position_sensor" in str(err.value)


def test_config_override_applies_and_validates() -> None:
    """--set overrides are applied to nested keys and go through the same validation."""
    cfg = load_config(REPO / "config" / "sitl.yaml", ["matcher.min_inliers_threshold=40", "cache.dir=/tmp/x"])
    assert cfg.matcher.min_inliers_threshold == 40
    assert cfg.cache.dir == "/tmp/x"
    assert config_to_dict(cfg)["matcher"]["min_inliers_threshold"] == 40


def test_config_missing_file_is_error(tmp_path: Path) -> None:
    """A missing profile is a ConfigError naming the file."""
    with pytest.raises(ConfigError) as err:
        load_config(tmp_path / "nope.yaml")
    assert "nope.yaml" in str(err.value)


def test_cli_run_bad_config_exits_2_with_one_line(tmp_path: Path) -> None:
    """`gdnav run` with an invalid profile exits 2 and prints one line naming the key path."""
    bad = _write(tmp_path, "estimator:\n  fix_gate_chi2: -1\n")
    proc = subprocess.run(
        [sys.executable, "-m", "gps_denied_onboard.cli", "run", "--config", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "estimator.fix_gate_chi2" in lines[0] and "greater than 0" in lines[0]


def test_cli_run_refuses_missing_cache_with_exit_3(tmp_path: Path) -> None:
    """A valid profile pointing at a missing cache is refused at start-up (exit 3), naming the cache."""
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "gps_denied_onboard.cli",
            "run",
            "--config",
            str(REPO / "config" / "sitl.yaml"),
            "--set",
            f"cache.dir={tmp_path / 'no-cache'}",
            "--set",
            f"fdr.dir={tmp_path / 'fdr'}",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 3
    assert "cache" in proc.stderr.splitlines()[-1]


@pytest.mark.parametrize(
    "argv",
    [
        ["--help"],
        ["run", "--help"],
        ["cache", "--help"],
        ["cache", "build", "--help"],
        ["sitl", "--help"],
        ["sitl", "run", "--help"],
        ["config", "--help"],
        ["config", "check", "--help"],
    ],
)
def test_cli_every_subcommand_has_help(argv: list[str]) -> None:
    """Every subcommand answers --help with usage text and exit 0."""
    proc = subprocess.run(
        [sys.executable, "-m", "gps_denied_onboard.cli", *argv], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert "usage: gdnav" in proc.stdout


@pytest.mark.parametrize(
    ("override", "key_path"),
    [
        ("terrain.ground_alt_amsl_m=.nan", "terrain.ground_alt_amsl_m"),
        ("estimator.max_output_sigma_m=.inf", "estimator.max_output_sigma_m"),
        ("init.lat_deg=-.inf", "init.lat_deg"),
        ("camera.intrinsics.dist_coeffs=[0.1, .nan]", "camera.intrinsics.dist_coeffs"),
    ],
)
def test_config_non_finite_float_is_refused_with_key_path(override: str, key_path: str) -> None:
    """NaN and infinity are refused in every float setting (plain, optional, bounded, in a list)."""
    with pytest.raises(ConfigError) as err:
        load_config(None, [override])
    assert err.value.key_path == key_path
    assert "finite" in str(err.value)


def test_config_fdr_max_bytes_below_segment_bytes_is_refused() -> None:
    """A recorder bound smaller than one segment is refused, naming fdr.max_bytes and both values."""
    with pytest.raises(ConfigError) as err:
        load_config(None, ["fdr.max_bytes=65536", "fdr.segment_bytes=1048576"])
    assert err.value.key_path == "fdr.max_bytes"
    assert "1048576" in str(err.value) and "65536" in str(err.value)
    assert load_config(None, ["fdr.max_bytes=1048576", "fdr.segment_bytes=1048576"]).fdr.max_bytes == 1048576


@pytest.mark.parametrize(
    "url",
    [
        "udpin:nohostport",
        "udpin::14550",
        "udpin:127.0.0.1:0",
        "udpin:127.0.0.1:70000",
        "tcp:host:x1",
        "http://127.0.0.1:80",
        "ttyACM0",
    ],
)
def test_config_invalid_mavlink_url_is_refused(url: str) -> None:
    """mavlink.url must be SCHEME:HOST:PORT (PORT 1..65535) or a serial device path."""
    with pytest.raises(ConfigError) as err:
        load_config(None, [f"mavlink.url={url}"])
    assert err.value.key_path == "mavlink.url" and repr(url) in str(err.value)


@pytest.mark.parametrize(
    "url", ["udpin:0.0.0.0:14550", "udp:127.0.0.1:14560", "tcp:10.0.0.2:5760", "/dev/ttyTHS1"]
)
def test_config_valid_mavlink_urls_are_accepted(url: str) -> None:
    """The documented connection strings validate."""
    assert load_config(None, [f"mavlink.url={url}"]).mavlink.url == url


def test_config_non_utf8_file_is_refused(tmp_path: Path) -> None:
    """A profile that is not UTF-8 text is a ConfigError naming the file, not a UnicodeDecodeError."""
    p = tmp_path / "latin1.yaml"
    p.write_bytes("profile: caf\xe9\n".encode("latin-1"))
    with pytest.raises(ConfigError) as err:
        load_config(p)
    assert str(p) in str(err.value) and "UTF-8" in str(err.value)


def test_config_override_that_is_not_yaml_is_refused() -> None:
    """An override whose value does not parse as YAML is a ConfigError naming the key."""
    with pytest.raises(ConfigError) as err:
        load_config(None, ["camera.source=[unclosed"])
    assert err.value.key_path == "camera.source"
