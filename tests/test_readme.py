"""The README and docs/ cannot drift: their commands parse, their links resolve, the config reference
(docs/configuration.md) matches config.py, CI runs the README's test command."""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import pytest

from gps_denied_onboard.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: The README and every page under docs/ (benchmarks included: its reproducing commands must parse too).
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_WORDS = 2600


def _code_lines() -> list[str]:
    texts = [p.read_text() for p in PAGES]
    blocks = [b for t in texts for b in re.findall(r"```(?:sh|bash)?\n(.*?)```", t, flags=re.S)]
    joined = [b.replace("\\\n", " ") for b in blocks]  # a command continued with a backslash is one line
    lines = [ln.strip() for b in joined for ln in b.splitlines() if ln.strip()]
    return [ln for ln in lines if not re.search(r"<[^>\s]+>", ln)]  # a template (<DATE>) is not a command


def test_readme_quick_start_is_two_commands_and_ci_runs_the_second() -> None:
    """The quick start block has exactly two commands; .ci/run calls the test one verbatim."""
    quick = README.split("## Quick start", 1)[1].split("##", 1)[0]
    commands = re.findall(r"```sh\n(.*?)```", quick, flags=re.S)[0].strip().splitlines()
    assert commands == ["bash scripts/demo.sh", "bash scripts/test.sh"]
    ci = (ROOT / ".ci" / "run").read_text()
    assert re.search(r"^bash scripts/test\.sh$", ci, flags=re.M)


@pytest.mark.parametrize("line", [ln for ln in _code_lines() if ln.startswith("gdnav ")])
def test_readme_gdnav_commands_parse(line: str) -> None:
    """Every gdnav command shown in the README or docs/ is accepted by the CLI's parser."""
    try:
        build_parser().parse_args(shlex.split(line)[1:])
    except SystemExit as exc:  # argparse exits on an unknown option or a missing argument
        pytest.fail(f"command in README.md or docs/ does not parse: {line} (exit {exc.code})")


def test_readme_config_reference_matches_config() -> None:
    """docs/configuration.md's table is what tools/gen_config_reference.py makes from config.py."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from gen_config_reference import REFERENCE, reference_block
    finally:
        sys.path.pop(0)
    assert REFERENCE == ROOT / "docs" / "configuration.md"
    assert reference_block() in REFERENCE.read_text(), "run: .venv/bin/python tools/gen_config_reference.py"


def test_readme_is_a_front_door() -> None:
    """The README stays short, and shows the quick start, the ArduPilot parameters and the provenance
    table near the top of their sections."""
    words = len(README.split())
    assert words <= README_MAX_WORDS, f"README.md has {words} words, at most {README_MAX_WORDS} expected"
    ardupilot = README.split("## Fly it with ArduPilot", 1)[1].split("\n## ", 1)[0]
    assert "GPS1_TYPE=14" in ardupilot[:1200], "the ArduPilot parameters table opens its section"
    assert "| `satellite_anchored` (3) |" in README, "the provenance table is in the README"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_readme_and_docs_links_resolve(page: Path) -> None:
    """Every relative link in the README and docs/ names a file that exists."""
    missing = []
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
        if "://" in target or target.startswith("mailto:"):
            continue
        if not (page.parent / target).exists():
            missing.append(target)
    assert not missing, f"{page.name} links to missing files: {missing}"
