"""Frame sources: network stream (SITL / a camera process), and OpenCV capture (V4L2, RTSP, video file).

A source is an async iterator of frames that still need decoding (decoding runs on the pipeline
thread, not on the event loop). Sources reconnect on their own with capped, jittered backoff and never
wait forever: every connect and read has a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import threading
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Protocol
from urllib.parse import urlparse

import numpy as np
import structlog

from gps_denied_onboard.camera.stream import EncodedFrame, FrameStreamError, read_frame
from gps_denied_onboard.constants import LogEvent

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class RawFrame:
    """A frame already decoded by the capture backend (OpenCV sources)."""

    seq: int
    exposure_time_unix_usec: int
    image_bgr: np.ndarray

    def decode(self) -> np.ndarray:
        return self.image_bgr


CapturedFrame = EncodedFrame | RawFrame


class FrameSource(Protocol):
    name: str
    #: Malformed messages seen (each also logged); the daemon reports it.
    bad_frames: int
    #: Times the source was (re)opened; more than one means it was lost and came back.
    connections: int

    def frames(self) -> AsyncIterator[CapturedFrame]: ...


class CameraSourceError(ValueError):
    """The configured camera source string cannot be used."""


class _Backoff:
    def __init__(self, cap_s: float) -> None:
        self._cap_s = cap_s
        self._next_s = 0.2

    def reset(self) -> None:
        self._next_s = 0.2

    def next_delay_s(self) -> float:
        delay = self._next_s * (0.5 + random.random())  # jitter: no lock-step reconnect storms
        self._next_s = min(self._cap_s, self._next_s * 2.0)
        return min(delay, self._cap_s)


class TcpFrameSource:
    """Connects to ``tcp://HOST:PORT`` and reads the frame-stream format (see camera.stream)."""

    def __init__(
        self, host: str, port: int, *, connect_timeout_s: float, frame_timeout_s: float, backoff_max_s: float
    ) -> None:
        self.name = f"tcp://{host}:{port}"
        self._host, self._port = host, port
        self._connect_timeout_s = connect_timeout_s
        self._frame_timeout_s = frame_timeout_s
        self._backoff = _Backoff(backoff_max_s)
        self.bad_frames = 0
        self.connections = 0
        self.connected = False

    async def frames(self) -> AsyncIterator[CapturedFrame]:
        while True:
            try:
                reader, writer = await asyncio.wait_for(
                    asyncio.open_connection(self._host, self._port), self._connect_timeout_s
                )
            except (OSError, asyncio.TimeoutError) as exc:
                delay = self._backoff.next_delay_s()
                log.debug(
                    "camera.connect_failed", source=self.name, error=str(exc), retry_in_s=round(delay, 2)
                )
                await asyncio.sleep(delay)
                continue
            self.connected = True
            self.connections += 1
            self._backoff.reset()
            log.info(LogEvent.CAMERA_CONNECTED, source=self.name)
            try:
                while True:
                    frame = await asyncio.wait_for(read_frame(reader), self._frame_timeout_s)
                    yield frame
            except FrameStreamError as exc:
                # The byte stream is out of sync after a malformed message: count it and reconnect.
                self.bad_frames += 1
                log.warning(LogEvent.CAMERA_BAD_FRAME, source=self.name, error=str(exc))
            except (asyncio.IncompleteReadError, ConnectionError, asyncio.TimeoutError, OSError) as exc:
                log.warning(LogEvent.CAMERA_DISCONNECTED, source=self.name, error=type(exc).__name__)
            finally:
                self.connected = False
                writer.close()
                with contextlib.suppress(OSError, asyncio.TimeoutError):
                    await asyncio.wait_for(writer.wait_closed(), 1.0)
            await asyncio.sleep(self._backoff.next_delay_s())


class OpenCvFrameSource:
    """V4L2 device, RTSP URL or video file through ``cv2.VideoCapture`` on a reader thread.

    The exposure time is the host clock at grab time (V4L2/RTSP give no better portable stamp).
    """

    def __init__(
        self,
        target: str | int,
        *,
        name: str,
        frame_timeout_s: float,
        backoff_max_s: float,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.name = name
        self._target = target
        self._frame_timeout_s = frame_timeout_s
        self._backoff = _Backoff(backoff_max_s)
        self._clock = clock
        self.bad_frames = 0
        self.connections = 0

    async def frames(self) -> AsyncIterator[CapturedFrame]:
        import cv2

        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[RawFrame | None] = asyncio.Queue(maxsize=2)
        stop = threading.Event()

        def reader() -> None:
            seq = 0
            while not stop.is_set():
                cap = cv2.VideoCapture(self._target)
                if not cap.isOpened():
                    time.sleep(self._backoff.next_delay_s())
                    continue
                self._backoff.reset()
                self.connections += 1
                while not stop.is_set():
                    ok, img = cap.read()
                    stamp_us = int(self._clock() * 1e6)
                    if not ok or img is None:
                        break
                    seq += 1
                    if img.ndim == 2:
                        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
                    frame = RawFrame(seq, stamp_us, img)
                    loop.call_soon_threadsafe(_offer, queue, frame)
                cap.release()
                loop.call_soon_threadsafe(_offer, queue, None)
                time.sleep(self._backoff.next_delay_s())

        thread = threading.Thread(target=reader, name=f"camera:{self.name}", daemon=True)
        thread.start()
        try:
            while True:
                try:
                    item = await asyncio.wait_for(queue.get(), self._frame_timeout_s)
                except asyncio.TimeoutError:
                    log.warning(LogEvent.CAMERA_DISCONNECTED, source=self.name, error="frame timeout")
                    continue
                if item is None:
                    log.warning(LogEvent.CAMERA_DISCONNECTED, source=self.name, error="capture ended")
                    continue
                yield item
        finally:
            stop.set()


def _offer(queue: asyncio.Queue[RawFrame | None], item: RawFrame | None) -> None:
    if queue.full():
        queue.get_nowait()  # newest wins; the daemon's own queue counts the drops that matter
    queue.put_nowait(item)


def open_frame_source(
    spec: str, *, connect_timeout_s: float, frame_timeout_s: float, backoff_max_s: float
) -> FrameSource:
    """Build a source from ``camera.source``: ``tcp://HOST:PORT``, ``v4l2:/dev/videoN``,
    ``rtsp://...``, ``file:PATH``."""
    if spec.startswith("tcp://"):
        url = urlparse(spec)
        if not url.hostname or not url.port:
            raise CameraSourceError(f"camera.source {spec!r}: expected tcp://HOST:PORT")
        return TcpFrameSource(
            url.hostname,
            url.port,
            connect_timeout_s=connect_timeout_s,
            frame_timeout_s=frame_timeout_s,
            backoff_max_s=backoff_max_s,
        )
    if spec.startswith("v4l2:"):
        dev = spec[len("v4l2:") :]
        target: str | int = int(dev[len("/dev/video") :]) if dev.startswith("/dev/video") else dev
        return OpenCvFrameSource(
            target, name=spec, frame_timeout_s=frame_timeout_s, backoff_max_s=backoff_max_s
        )
    if spec.startswith(("rtsp://", "rtsps://")):
        return OpenCvFrameSource(
            spec, name=spec, frame_timeout_s=frame_timeout_s, backoff_max_s=backoff_max_s
        )
    if spec.startswith("file:"):
        return OpenCvFrameSource(
            spec[len("file:") :], name=spec, frame_timeout_s=frame_timeout_s, backoff_max_s=backoff_max_s
        )
    raise CameraSourceError(
        f"camera.source {spec!r}: expected tcp://HOST:PORT, v4l2:/dev/videoN, rtsp://URL or file:PATH"
    )
