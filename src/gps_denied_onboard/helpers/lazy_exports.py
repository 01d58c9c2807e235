"""A package's exported names, each loaded from its submodule on first use (PEP 562).

A component package whose light types the navigator core needs (the estimator, the MAVLink link) and whose
heavy parts only the vision side needs (OpenCV, SciPy) exports both this way: importing the package, or
one light submodule of it, no longer imports the heavy ones.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, homes: Mapping[str, str]) -> Callable[[str], Any]:
    """The module ``__getattr__`` for ``package``: ``homes`` maps each exported name to the submodule
    (relative to ``package``) that defines it; the value is cached in the package once loaded."""

    def __getattr__(name: str) -> Any:
        module = homes.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
