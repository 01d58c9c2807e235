"""The frame stream wire format and the daemon's newest-wins queue."""

from __future__ import annotations

import asyncio
import struct

import numpy as np
import pytest

from gps_denied_onboard.camera.stream import EncodedFrame, FrameStreamError, encode_frame, read_frame
from gps_denied_onboard.daemon.frame_queue import LatestQueue


def _read(data: bytes) -> EncodedFrame:
    """Parse one message from bytes through a real StreamReader (created inside the running loop)."""

    async def go() -> EncodedFrame:
        r = asyncio.StreamReader()
        r.feed_data(data)
        r.feed_eof()
        return await read_frame(r)

    return asyncio.run(go())


def _image() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)


def test_stream_round_trip_png_is_lossless() -> None:
    """A PNG frame decodes to the exact pixels, with its header fields."""
    img = _image()
    msg = encode_frame(img, seq=7, exposure_time_unix_usec=1_700_000_000_123_456, encoding="png")
    frame = _read(msg)
    assert (frame.seq, frame.exposure_time_unix_usec, frame.width_px, frame.height_px) == (
        7,
        1_700_000_000_123_456,
        64,
        48,
    )
    np.testing.assert_array_equal(frame.decode(), img)


def test_stream_bad_magic_is_named() -> None:
    """Garbage instead of a frame is a FrameStreamError naming the magic."""
    with pytest.raises(FrameStreamError, match="magic"):
        _read(b"XXXX" + b"\0" * 16)


def test_stream_header_field_type_is_checked() -> None:
    """A header with a string seq is rejected with the field name."""
    header = b'{"seq": "1", "exposure_time_unix_usec": 1, "encoding": "png", "width_px": 1, "height_px": 1}'
    msg = b"GDNF" + struct.pack(">I", len(header)) + header + struct.pack(">I", 1) + b"x"
    with pytest.raises(FrameStreamError, match="'seq'"):
        _read(msg)


def test_stream_corrupt_payload_fails_decode_not_read() -> None:
    """A corrupt image payload is read, then refused at decode (on the pipeline thread)."""
    frame = EncodedFrame(1, 1, "jpeg", 64, 48, b"not a jpeg")
    with pytest.raises(FrameStreamError, match="not a decodable jpeg"):
        frame.decode()


def test_stream_size_mismatch_is_refused() -> None:
    """An image whose size differs from its header is refused."""
    msg = encode_frame(_image(), seq=1, exposure_time_unix_usec=1, encoding="png")
    frame = _read(msg)
    wrong = EncodedFrame(frame.seq, frame.exposure_time_unix_usec, "png", 65, 48, frame.payload)
    with pytest.raises(FrameStreamError, match="65x48"):
        wrong.decode()


def test_latest_queue_newest_wins_and_counts_drops() -> None:
    """With depth 1, putting three items keeps the last and counts two drops."""

    async def go() -> tuple[int, int]:
        q: LatestQueue[int] = LatestQueue(1)
        q.put(1)
        q.put(2)
        q.put(3)
        return await q.get(), q.dropped

    assert asyncio.run(go()) == (3, 2)
