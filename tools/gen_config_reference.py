"""Regenerate the configuration reference (docs/configuration.md) from config.py (run after changing a
setting).

    .venv/bin/python tools/gen_config_reference.py   # rewrites the block between the markers

tests/test_readme.py fails when docs/configuration.md and config.py disagree.
"""

from __future__ import annotations

import ast
import dataclasses
import re
import sys
import typing
from pathlib import Path

from gps_denied_onboard import config as cfg

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "docs" / "configuration.md"
BEGIN, END = "<!-- config-reference:begin -->", "<!-- config-reference:end -->"
_SYM = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}


def _field_docs() -> dict[tuple[str, str], tuple[str, str]]:
    text = Path(cfg.__file__).read_text()
    lines = text.splitlines()
    docs: dict[tuple[str, str], tuple[str, str]] = {}
    for node in ast.parse(text).body:
        if not isinstance(node, ast.ClassDef):
            continue
        for st in node.body:
            if isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name):
                i, doc = st.lineno - 2, []
                while i >= 0 and lines[i].strip().startswith("#:"):
                    doc.insert(0, lines[i].strip()[2:].strip())
                    i -= 1
                ann = ast.get_source_segment(text, st.annotation) or ""
                docs[(node.name, st.target.id)] = (" ".join(doc), ann)
    return docs


def _allowed(ann: str) -> str:
    if ann.startswith("PosFloat"):
        return "> 0"
    if ann.startswith("PosInt"):
        return ">= 1"
    if ann.startswith("Fraction"):
        return "0 .. 1"
    if ann.startswith("Bool"):
        return "true / false"
    if "OutputKind" in ann:
        return "list of gps_input, global_position_sensor, vision_position_estimate"
    lit = re.findall(r"Literal\[(.*?)\]", ann)
    if lit:
        return "one of " + lit[0].replace('"', "")
    return ", ".join(f"{_SYM[a]} {b.strip()}" for a, b in re.findall(r"\b(gt|ge|lt|le)=([^,)\]]+)", ann))


def _rows(cls: type, docs: dict[tuple[str, str], tuple[str, str]], prefix: str = "") -> list[str]:
    rows: list[str] = []
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            rows += _rows(hints[f.name], docs, prefix + f.name + ".")
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        shown = "null" if default is None else list(default) if isinstance(default, tuple) else default
        doc, ann = docs.get((cls.__name__, f.name), ("", ""))
        rows.append(f"| `{prefix}{f.name}` | `{shown}` | {_allowed(ann)} | {doc.replace('``', '`')} |")
    return rows


def reference_block() -> str:
    body = "\n".join(
        ["| key | default | allowed | meaning |", "|---|---|---|---|", *_rows(cfg.Config, _field_docs())]
    )
    return f"{BEGIN}\n{body}\n{END}"


def main() -> int:
    text = REFERENCE.read_text()
    start, end = text.index(BEGIN), text.index(END) + len(END)
    REFERENCE.write_text(text[:start] + reference_block() + text[end:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
