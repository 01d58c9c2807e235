"""What opening a map cache costs, and the daemon's start on it: this code against another, side by side.

    .venv/bin/python tools/cache_open_bench.py --cache DIR [--cache DIR ...] \
        [--code before=/tmp/main_src] [--repeats 3] [--daemon] [--json OUT]

``--code NAME=ROOT`` adds a version of the project (a checkout or ``git archive`` of another commit: its
``src`` is put first on PYTHONPATH, its ``config/sitl.yaml`` is the daemon's profile); this tree is
``after``. Each measurement runs in a fresh process, the versions interleaved within each repeat so
that the machine's load weighs on all alike:

- ``open``: ``TileStore.open`` at each level the version has (after: ``full`` and ``light``; a version
  with the ``verify_hashes`` bool: ``hashes`` and ``no_hashes``), with the cache's files in the page
  cache (``warm``: read once before) and out of it (``cold``: ``posix_fadvise(DONTNEED)`` on the cache's
  own files, nothing else on the machine is touched).
- ``--daemon``: ``gdnav run`` on the version's ``config/sitl.yaml`` (classical matcher, geo_prior VPR,
  nothing listening on the camera or MAVLink ports), from the spawn to its ``daemon.ready`` log line, with
  ``cache.verify_hashes`` true and false, cold and warm; then SIGTERM.

A one-off measurement tool for ``docs/benchmarks.md`` ("Cache open: constant time"); the daemon does not
use it.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

#: Run in the child: open the cache at one level and print the seconds as JSON.
_OPEN_CHILD = r"""
import inspect, json, os, sys, time
from pathlib import Path
cache, level, cold = Path(sys.argv[1]), sys.argv[2], sys.argv[3] == "cold"
from gps_denied_onboard.components.c6_tiles.store import TileStore
files = [p for p in cache.iterdir() if p.is_file()]
for p in files:
    fd = os.open(p, os.O_RDONLY)
    try:
        if cold:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        else:
            while os.read(fd, 8 << 20):
                pass
    finally:
        os.close(fd)
if "verify_hashes" in inspect.signature(TileStore.open).parameters:
    kwargs = {"verify_hashes": level == "hashes"}
else:
    from gps_denied_onboard.components.c10_cache_build.manifest import Verification
    kwargs = {"verification": Verification(level)}
t0 = time.perf_counter()
store = TileStore.open(cache, **kwargs)
seconds = time.perf_counter() - t0
print(json.dumps({"seconds": seconds, "tiles": len(store), "mosaic_bytes": int(store.mosaic.nbytes)}))
"""


def _levels(src: Path) -> tuple[str, ...]:
    text = (src / "gps_denied_onboard" / "components" / "c6_tiles" / "store.py").read_text()
    return ("hashes", "no_hashes") if "verify_hashes: bool" in text else ("full", "light")


def _env(src: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(src), "PYTHONDONTWRITEBYTECODE": "1"}


def _drop(cache: Path) -> None:
    for p in cache.iterdir():
        if p.is_file():
            fd = os.open(p, os.O_RDONLY)
            try:
                os.fsync(fd)
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


def _open_once(src: Path, cache: Path, level: str, temp: str) -> dict[str, Any]:
    proc = subprocess.run(
        [sys.executable, "-c", _OPEN_CHILD, str(cache), level, temp],
        env=_env(src),
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"open failed ({src}, {level}): {proc.stderr[-2000:]}")
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _daemon_ready_s(code_root: Path, cache: Path, verify: bool, temp: str) -> float:
    if temp == "cold":
        _drop(cache)
    with tempfile.TemporaryDirectory(prefix="gdnav-ready-") as work:
        cmd = [sys.executable, "-m", "gps_denied_onboard.cli", "run", "--config"]
        cmd.append(str(code_root / "config" / "sitl.yaml"))
        for item in (
            f"cache.dir={cache}",
            f"cache.verify_hashes={str(verify).lower()}",
            f"fdr.dir={Path(work) / 'fdr'}",
            f"camera.source=tcp://127.0.0.1:{_free_port(socket.SOCK_STREAM)}",
            f"mavlink.url=udpin:127.0.0.1:{_free_port(socket.SOCK_DGRAM)}",
            "matcher.strategy=classical",
            "vpr.strategy=geo_prior",
        ):
            cmd += ["--set", item]
        log = Path(work) / "daemon.log"
        t0 = time.monotonic()
        with log.open("wb") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=out, env=_env(code_root / "src"), cwd=code_root)
        try:
            while time.monotonic() - t0 < 300:
                if "daemon.ready" in log.read_text(errors="replace"):
                    return time.monotonic() - t0
                if proc.poll() is not None:
                    raise RuntimeError(f"the daemon exited {proc.returncode}: {log.read_text()[-2000:]}")
                time.sleep(0.02)
            raise RuntimeError("no daemon.ready in 300 s")
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", action="append", required=True, type=Path)
    parser.add_argument("--code", action="append", default=[], metavar="NAME=ROOT")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--daemon", action="store_true", help="also time gdnav run to daemon.ready")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    codes = {"after": ROOT}
    for item in args.code:
        name, _, root = item.partition("=")
        codes[name] = Path(root).resolve()
    rows: dict[tuple[str, str, str, str, str], list[float]] = {}
    sizes: dict[str, dict[str, Any]] = {}
    for _ in range(args.repeats):
        for cache in args.cache:
            for temp in ("cold", "warm"):
                for name, root in codes.items():
                    for level in _levels(root / "src"):
                        got = _open_once(root / "src", cache, level, temp)
                        sizes[str(cache)] = {"tiles": got["tiles"], "mosaic_bytes": got["mosaic_bytes"]}
                        rows.setdefault((str(cache), "open", name, level, temp), []).append(got["seconds"])
                    if args.daemon:
                        for verify in (True, False):
                            seconds = _daemon_ready_s(root, cache, verify, temp)
                            key = (str(cache), "daemon.ready", name, f"verify_hashes={verify}", temp)
                            rows.setdefault(key, []).append(seconds)
    print(f"load average at the end: {os.getloadavg()}")
    print("| cache | tiles | mosaic | what | code | setting | page cache | median s | runs |")
    print("|---|---|---|---|---|---|---|---|---|")
    out = []
    for (cache, what, name, level, temp), values in rows.items():
        size = sizes[cache]
        median = statistics.median(values)
        gib = size["mosaic_bytes"] / 2**30
        runs = ", ".join(f"{v:.3f}" for v in values)
        print(
            f"| {Path(cache).name} | {size['tiles']} | {gib:.2f} GiB | {what} | {name} | {level} | {temp} "
            f"| {median:.3f} | {runs} |"
        )
        out.append({"cache": cache, **size, "what": what, "code": name, "setting": level, "page_cache": temp,
                    "median_s": median, "runs_s": values})  # fmt: skip
    if args.json is not None:
        args.json.write_text(json.dumps({"load_average": os.getloadavg(), "rows": out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
