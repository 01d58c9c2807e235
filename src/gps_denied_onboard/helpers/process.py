"""A child process that ends with its parent (Linux ``prctl(PR_SET_PDEATHSIG)``)."""

from __future__ import annotations

import contextlib
import ctypes
import signal
from typing import Final

#: prctl(2): the signal a process gets when the thread that started it ends.
_PR_SET_PDEATHSIG: Final = 1


def die_with_parent(sig: signal.Signals = signal.SIGKILL) -> bool:
    """Have the kernel send ``sig`` to this process the moment the thread that started it ends. False
    where the call is not available (not Linux)."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)) == 0
    return False
