"""Latency of the local IPC a vision worker would send its measurements to the navigator core over.

Issue 36 splits the daemon into a light core (link, clocks, estimator, output) and a vision worker (camera,
VO, VPR, matching, pose). The worker sends time-stamped measurements; this measures, for a message shaped
like a judged fix, how long one takes to arrive on each candidate transport, side by side in one run:

- ``unix_seqpacket``: a ``socket.socketpair(AF_UNIX, SOCK_SEQPACKET)`` (message boundaries kept by the
  kernel) with msgpack;
- ``zmq_ipc``: a pyzmq ``PAIR`` over ``ipc://`` with msgpack (skipped, and said so, where pyzmq is not
  installed);
- ``mp_pipe``: ``multiprocessing.Pipe`` with pickle, the standard library's own.

Each message goes to a child process that sends it straight back; the one-way figure is half the round
trip. Messages are paced (``--rate-hz``) so that both ends sleep between them, as a 3-10 Hz stream's do:
a transport's wake-up cost is what the core would see. ``--busy N`` runs N busy loops at nice 0 beside
it, the companion's load of issue 36; both ends run at ``--nice`` where permitted.

    python tools/ipc_bench.py [--n 2000] [--rate-hz 200] [--busy 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import platform
import socket
import tempfile
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import msgpack
import numpy as np

#: A judged fix as the worker would send it (343 bytes in msgpack).
FIX_MESSAGE: dict[str, Any] = {
    "kind": "fix",
    "frame_seq": 12345,
    "exposure_unix_usec": 1_796_187_631_471_081,
    "lat_deg": 17.59245974253897,
    "lon_deg": 78.12141512264829,
    "alt_amsl_m": 482.03,
    "cov_ned_m2": [1.05, 0.01, 0.0, 0.01, 1.04, 0.0, 0.0, 0.0, 4.0],
    "shared_sigma_m": 1.027,
    "inliers": 427,
    "residual_px": 0.119,
    "tilt_off_cam_rad": [-0.0035, 0.015],
    "stamp_sigma_s": 0.04,
    "provenance": "satellite_anchored",
}


def _set_nice(nice: int | None) -> None:
    if nice is None:
        return
    with contextlib.suppress(PermissionError):  # where it may not: the figures say the nice it got
        os.setpriority(os.PRIO_PROCESS, 0, nice)


def _busy() -> None:
    os.setpriority(os.PRIO_PROCESS, 0, 0)
    while True:
        pass


# -- the echoing ends ---------------------------------------------------------------------------------


def _echo_unix(sock: socket.socket, nice: int | None) -> None:
    _set_nice(nice)
    while True:
        data = sock.recv(65536)
        if not data:
            return
        msgpack.unpackb(data)  # the core decodes what it gets
        sock.send(data)


def _echo_zmq(address: str, nice: int | None) -> None:
    import zmq

    _set_nice(nice)
    ctx = zmq.Context()
    s = ctx.socket(zmq.PAIR)
    s.connect(address)
    while True:
        data = s.recv()
        if data == b"":
            break
        msgpack.unpackb(data)
        s.send(data)
    s.close(0)
    ctx.term()


def _echo_pipe(conn: Connection, nice: int | None) -> None:
    _set_nice(nice)
    while True:
        obj = conn.recv()
        if obj is None:
            return
        conn.send(obj)


# -- one transport -----------------------------------------------------------------------------------


def _paced(n: int, rate_hz: float, round_trip: Callable[[], None]) -> np.ndarray:
    """``n`` round trips (after 100 unmeasured), one every 1/rate_hz s; their one-way halves, us."""
    period = 1.0 / rate_hz
    out = np.empty(n)
    for i in range(-100, n):
        t0 = time.perf_counter_ns()
        round_trip()
        dt = (time.perf_counter_ns() - t0) / 2e3
        if i >= 0:
            out[i] = dt
        time.sleep(max(0.0, period - (time.perf_counter_ns() - t0) / 1e9))
    return out


def bench_unix(n: int, rate_hz: float, nice: int | None) -> np.ndarray:
    parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    proc = mp.get_context("fork").Process(target=_echo_unix, args=(child, nice), daemon=True)
    proc.start()
    child.close()
    payload = FIX_MESSAGE

    def rt() -> None:
        parent.send(msgpack.packb(payload))
        msgpack.unpackb(parent.recv(65536))

    try:
        return _paced(n, rate_hz, rt)
    finally:
        parent.close()
        proc.join(5)


def bench_zmq(n: int, rate_hz: float, nice: int | None) -> np.ndarray | None:
    try:
        import zmq
    except ImportError:
        return None
    with tempfile.TemporaryDirectory() as d:
        address = f"ipc://{d}/bench.sock"
        ctx = zmq.Context()
        s = ctx.socket(zmq.PAIR)
        s.bind(address)
        proc = mp.get_context("fork").Process(target=_echo_zmq, args=(address, nice), daemon=True)
        proc.start()
        payload = FIX_MESSAGE

        def rt() -> None:
            s.send(msgpack.packb(payload))
            msgpack.unpackb(s.recv())

        try:
            return _paced(n, rate_hz, rt)
        finally:
            s.send(b"")
            proc.join(5)
            s.close(0)
            ctx.term()


def bench_pipe(n: int, rate_hz: float, nice: int | None) -> np.ndarray:
    parent, child = mp.Pipe()
    proc = mp.get_context("fork").Process(target=_echo_pipe, args=(child, nice), daemon=True)
    proc.start()
    payload = FIX_MESSAGE

    def rt() -> None:
        parent.send(payload)
        parent.recv()

    try:
        return _paced(n, rate_hz, rt)
    finally:
        parent.send(None)
        proc.join(5)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=2000, help="measured messages per transport")
    ap.add_argument("--rate-hz", type=float, default=200.0, help="messages per second")
    ap.add_argument("--busy", type=int, default=0, help="busy loops at nice 0 beside the run")
    ap.add_argument("--nice", type=int, default=-5, help="both ends' nice value, where permitted")
    ap.add_argument("--json", help="write the figures here")
    a = ap.parse_args(argv)
    _set_nice(a.nice)
    hogs = [mp.get_context("fork").Process(target=_busy, daemon=True) for _ in range(a.busy)]
    for h in hogs:
        h.start()
    size = len(msgpack.packb(FIX_MESSAGE))
    rows: dict[str, dict[str, float] | None] = {}
    try:
        for name, fn in (("unix_seqpacket", bench_unix), ("zmq_ipc", bench_zmq), ("mp_pipe", bench_pipe)):
            us = fn(a.n, a.rate_hz, a.nice)
            rows[name] = (
                None
                if us is None
                else {
                    "p50_us": float(np.percentile(us, 50)),
                    "p99_us": float(np.percentile(us, 99)),
                    "max_us": float(us.max()),
                }
            )
    finally:
        for h in hogs:
            h.terminate()
    cpu = platform.processor() or platform.machine()
    print(
        f"one-way latency of a {size}-byte fix message, {a.n} messages at {a.rate_hz:g} Hz, "
        f"{a.busy} busy loop(s) at nice 0, both ends at nice {os.getpriority(os.PRIO_PROCESS, 0)}; "
        f"{os.cpu_count()} CPUs ({cpu})"
    )
    print(f"{'transport':<16}{'p50 us':>10}{'p99 us':>10}{'max us':>10}")
    for name, r in rows.items():
        if r is None:
            print(f"{name:<16}{'(pyzmq not installed)':>30}")
        else:
            print(f"{name:<16}{r['p50_us']:>10.1f}{r['p99_us']:>10.1f}{r['max_us']:>10.1f}")
    if a.json:
        with open(a.json, "w") as fh:
            record = {"message_bytes": size, "n": a.n, "rate_hz": a.rate_hz, "busy": a.busy, "rows": rows}
            json.dump(record, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
