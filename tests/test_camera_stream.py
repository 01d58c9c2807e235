"""The frame stream wire format and the daemon's newest-wins queue."""

from __future__ import annotations

import asyncio
import json
import struct
import time
import zlib

import cv2
import numpy as np
import pytest

from gps_denied_onboard.camera import stream
from gps_denied_onboard.camera.stream import (
    PNG_SIGNATURE,
    EncodedFrame,
    FrameStreamError,
    encode_frame,
    read_frame,
)
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


# --- decompression bombs: the payload's own size is checked before anything is decoded -----------------


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_bomb(width: int, height: int) -> bytes:
    """A valid 1-bit greyscale PNG of all-black rows: ~100 kB on the wire, 1.2 GB once decoded as BGR."""
    ihdr = struct.pack(">IIBBBBB", width, height, 1, 0, 0, 0, 0)  # bit depth 1, greyscale
    comp = zlib.compressobj(9)
    row = b"\x00" * (1 + (width + 7) // 8)  # filter byte 0, then the packed pixels
    idat = b"".join(comp.compress(row) for _ in range(height)) + comp.flush()
    return PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")


def _message(payload: bytes, encoding: str, width_px: int, height_px: int) -> bytes:
    header = json.dumps(
        {
            "seq": 9,
            "exposure_time_unix_usec": 1,
            "encoding": encoding,
            "width_px": width_px,
            "height_px": height_px,
        }
    ).encode()
    return b"GDNF" + struct.pack(">I", len(header)) + header + struct.pack(">I", len(payload)) + payload


class _DecodeSpy:
    """Stands in for cv2.imdecode: counts calls; decodes only when allowed (a bomb must never get here)."""

    def __init__(self) -> None:
        self.calls = 0
        self.allow = False
        self._real = cv2.imdecode

    def __call__(self, buf: np.ndarray, flags: int) -> np.ndarray | None:
        self.calls += 1
        if not self.allow:
            raise AssertionError(f"imdecode called on a {buf.size}-byte payload that must be refused")
        return self._real(buf, flags)


@pytest.fixture
def decode_spy(monkeypatch: pytest.MonkeyPatch) -> _DecodeSpy:
    spy = _DecodeSpy()
    monkeypatch.setattr(stream.cv2, "imdecode", spy)
    return spy


def test_stream_png_bomb_refused_from_ihdr_before_decoding(decode_spy: _DecodeSpy) -> None:
    """A small PNG whose IHDR says 20000x20000 is refused from its header (never decoded), both when the
    frame header says 640x480 and when it claims the bomb's size; a normal PNG frame still decodes."""
    bomb = _png_bomb(20000, 20000)
    assert len(bomb) < 2 << 20
    t0 = time.monotonic()
    with pytest.raises(FrameStreamError, match=r"header says 640x480, png payload is 20000x20000"):
        _read(_message(bomb, "png", 640, 480)).decode()
    with pytest.raises(FrameStreamError, match=r"20000x20000 \(400000000 px\) is outside"):
        _read(_message(bomb, "png", 20000, 20000)).decode()
    assert time.monotonic() - t0 < 1.0
    assert decode_spy.calls == 0

    decode_spy.allow = True
    img = _image()
    frame = _read(encode_frame(img, seq=1, exposure_time_unix_usec=1, encoding="png"))
    np.testing.assert_array_equal(frame.decode(), img)
    assert decode_spy.calls == 1


def test_stream_jpeg_bomb_refused_from_sof_before_decoding(decode_spy: _DecodeSpy) -> None:
    """A JPEG whose SOF0 says 20000x20000 is refused without decoding; a normal JPEG frame decodes."""
    ok, buf = cv2.imencode(".jpg", _image())
    assert ok
    jpeg = bytearray(buf.tobytes())
    sof = jpeg.index(b"\xff\xc0")  # baseline frame header: FF C0, length(2), precision(1), height, width
    jpeg[sof + 5 : sof + 9] = struct.pack(">HH", 20000, 20000)
    with pytest.raises(FrameStreamError, match=r"header says 64x48, jpeg payload is 20000x20000"):
        _read(_message(bytes(jpeg), "jpeg", 64, 48)).decode()
    with pytest.raises(FrameStreamError, match=r"is outside 1\.\.24000000 px"):
        _read(_message(bytes(jpeg), "jpeg", 20000, 20000)).decode()
    assert decode_spy.calls == 0

    decode_spy.allow = True
    frame = _read(encode_frame(_image(), seq=1, exposure_time_unix_usec=1, encoding="jpeg"))
    assert frame.decode().shape == (48, 64, 3)
    assert decode_spy.calls == 1


def test_stream_payload_of_another_format_is_refused(decode_spy: _DecodeSpy) -> None:
    """A JPEG payload in a frame declared PNG is refused: OpenCV would sniff any format and decode it."""
    ok, buf = cv2.imencode(".jpg", _image())
    assert ok
    with pytest.raises(FrameStreamError, match="not a decodable png"):
        _read(_message(buf.tobytes(), "png", 64, 48)).decode()
    assert decode_spy.calls == 0
