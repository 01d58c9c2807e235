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
