"""The README cannot drift: its commands parse, its config reference matches config.py, CI runs its
test command."""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import pytest

from gps_denied_onboard.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _code_lines() -> list[str]:
    blocks = re.findall(r"```(?:sh|bash)?\n(.*?)```", README, flags=re.S)
    return [ln.strip() for b in blocks for ln in b.splitlines() if ln.strip()]


def test_readme_quick_start_is_two_commands_and_ci_runs_the_second() -> None:
    """The quick start block has exactly two commands; .ci/run calls the test one verbatim."""
    quick = README.split("## Quick start", 1)[1].split("##", 1)[0]
    commands = re.findall(r"```sh\n(.*?)```", quick, flags=re.S)[0].strip().splitlines()
    assert commands == ["bash scripts/demo.sh", "bash scripts/test.sh"]
    ci = (ROOT / ".ci" / "run").read_text()
    assert re.search(r"^bash scripts/test\.sh$", ci, flags=re.M)


@pytest.mark.parametrize("line", [ln for ln in _code_lines() if ln.startswith("gdnav ")])
def test_readme_gdnav_commands_parse(line: str) -> None:
    """Every gdnav command shown in the README is accepted by the CLI's parser."""
    try:
        build_parser().parse_args(shlex.split(line)[1:])
    except SystemExit as exc:  # argparse exits on an unknown option or a missing argument
        pytest.fail(f"README command does not parse: {line} (exit {exc.code})")


def test_readme_config_reference_matches_config() -> None:
    """The README's configuration table is what tools/gen_config_reference.py makes from config.py."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from gen_config_reference import reference_block
    finally:
        sys.path.pop(0)
    assert reference_block() in README, "run: .venv/bin/python tools/gen_config_reference.py"
