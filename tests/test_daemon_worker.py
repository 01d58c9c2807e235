"""The pipeline's worker threads (``daemon.worker``): the fix thread runs at a lower priority than the
rest of the daemon (Linux sets nice values per thread), so the event loop's 10 Hz output and VO go first
when the two cores are short."""

from __future__ import annotations

import asyncio
import os
import sys
import threading

import pytest

from gps_denied_onboard.daemon.worker import WorkerThread


@pytest.mark.skipif(sys.platform != "linux", reason="nice values are per thread on Linux only")
def test_a_worker_thread_runs_at_the_nice_value_it_was_given_and_the_rest_do_not() -> None:
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    if base + 5 > 19:
        pytest.skip("this process already runs at the lowest priority")

    async def run() -> tuple[int, int, int]:
        fix, track = WorkerThread("fix", nice=5), WorkerThread("track")
        try:
            own = lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())  # noqa: E731
            fix_nice, track_nice = await fix.submit(own), await track.submit(own)
            return fix_nice, track_nice, own()
        finally:
            await asyncio.gather(fix.stop(1.0), track.stop(1.0))

    fix_nice, track_nice, main_nice = asyncio.run(run())
    assert (fix_nice, track_nice, main_nice) == (base + 5, base, base)


def test_gdnav_run_sets_numpys_blas_threads_before_numpy_loads() -> None:
    """``daemon.blas_threads``: the variables OpenBLAS reads when it loads are set before anything has
    imported numpy; once numpy is in, it is too late, and ``limit_blas_threads`` says so."""
    import subprocess

    code = (
        "import os, sys\n"
        "from gps_denied_onboard.cli import limit_blas_threads\n"
        "assert 'numpy' not in sys.modules\n"
        "ok = limit_blas_threads(1)\n"
        "import numpy\n"
        "first = os.environ['OPENBLAS_NUM_THREADS']\n"
        "print(ok, first, limit_blas_threads(2), os.environ['OPENBLAS_NUM_THREADS'])\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert out.stdout.split() == ["True", "1", "False", "1"], out.stderr
