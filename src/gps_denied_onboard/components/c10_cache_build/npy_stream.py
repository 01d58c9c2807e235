"""Writing a large ``.npy`` artifact of a cache crash-safely, hashing it on the way (C10)."""

from __future__ import annotations

import hashlib
import io
import os
from pathlib import Path
from typing import BinaryIO

import numpy as np

from gps_denied_onboard.components.c10_cache_build.manifest import ArtifactInfo

_COPY_CHUNK_BYTES = 8 << 20


class NpyStream:
    """Writes one ``.npy`` whose row count is known only at the end: rows are streamed to a raw
    temporary file, then the header and the rows are written to ``<name>.tmp`` (hashed on the way),
    fsynced and renamed to ``path``."""

    def __init__(self, path: Path) -> None:
        self._path = path
        self._raw_path = path.with_name(path.name + ".raw.tmp")
        self._raw: BinaryIO | None = open(self._raw_path, "wb")  # noqa: SIM115 - closed in finish/discard

    def append(self, array: np.ndarray) -> None:
        if self._raw is None:
            raise ValueError(f"{self._path.name}: already finished")
        self._raw.write(np.ascontiguousarray(array).data)

    def finish(self, dtype: np.dtype, shape: tuple[int, ...]) -> ArtifactInfo:
        if self._raw is None:
            raise ValueError(f"{self._path.name}: already finished")
        self._raw.close()
        self._raw = None
        expected = int(np.prod(shape)) * dtype.itemsize
        written = self._raw_path.stat().st_size
        if written != expected:
            raise OSError(f"{self._raw_path.name}: {written} bytes written, expected {expected}")
        tmp = self._path.with_name(self._path.name + ".tmp")
        head = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            head, {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}
        )
        digest = hashlib.sha256(head.getvalue())
        with open(tmp, "wb") as out:
            out.write(head.getvalue())
            with open(self._raw_path, "rb") as raw:
                while chunk := raw.read(_COPY_CHUNK_BYTES):
                    out.write(chunk)
                    digest.update(chunk)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, self._path)
        self._raw_path.unlink(missing_ok=True)
        return ArtifactInfo(sha256=digest.hexdigest(), bytes=self._path.stat().st_size)

    def discard(self) -> None:
        """Drop the raw temporary file (after ``finish`` or on failure)."""
        if self._raw is not None:
            self._raw.close()
            self._raw = None
        self._raw_path.unlink(missing_ok=True)


def save_npy_atomic(path: Path, array: np.ndarray) -> None:
    """``array`` to ``path`` as ``.npy``, crash-safely: written to ``<name>.tmp``, fsynced, renamed."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.save(fh, array)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
