"""Network frame stream: the wire format between a camera process (or the SITL) and the daemon.

One message per frame, over a TCP byte stream::

    magic  b"GDNF"            4 bytes
    header_len  uint32 BE     4 bytes
    header      UTF-8 JSON    {"seq": int, "exposure_time_unix_usec": int, "encoding": "jpeg"|"png",
                               "width_px": int, "height_px": int}
    payload_len uint32 BE     4 bytes
    payload     encoded image (JPEG or PNG, BGR when decoded by OpenCV)

The reader validates every field and raises ``FrameStreamError`` naming what is wrong; the daemon
counts and records such frames and keeps going.
"""

from __future__ import annotations

import asyncio
import json
import struct
from dataclasses import dataclass

import cv2
import numpy as np

from gps_denied_onboard.constants import FRAME_STREAM_MAGIC

_U32 = struct.Struct(">I")
MAX_HEADER_BYTES = 4096
MAX_PAYLOAD_BYTES = 32 << 20
_ENCODINGS = {"jpeg": ".jpg", "png": ".png"}


class FrameStreamError(ValueError):
    """A malformed frame message (bad magic, header, sizes or image payload)."""


@dataclass(frozen=True)
class EncodedFrame:
    """A frame as received: header fields plus the still-encoded payload (decoded off the loop)."""

    seq: int
    exposure_time_unix_usec: int
    encoding: str
    width_px: int
    height_px: int
    payload: bytes

    def decode(self) -> np.ndarray:
        """Decode to (H, W, 3) uint8 BGR; raises FrameStreamError when the payload is not that image."""
        img = cv2.imdecode(np.frombuffer(self.payload, dtype=np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise FrameStreamError(f"frame {self.seq}: payload is not a decodable {self.encoding} image")
        if img.shape[1] != self.width_px or img.shape[0] != self.height_px:
            raise FrameStreamError(
                f"frame {self.seq}: header says {self.width_px}x{self.height_px}, "
                f"image is {img.shape[1]}x{img.shape[0]}"
            )
        return img


def encode_frame(
    image_bgr: np.ndarray,
    *,
    seq: int,
    exposure_time_unix_usec: int,
    encoding: str = "jpeg",
    quality: int = 92,
) -> bytes:
    """Serialise one frame message."""
    if encoding not in _ENCODINGS:
        raise FrameStreamError(f"unknown encoding {encoding!r}; expected one of {sorted(_ENCODINGS)}")
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if encoding == "jpeg" else []
    ok, buf = cv2.imencode(_ENCODINGS[encoding], image_bgr, params)
    if not ok:
        raise FrameStreamError("OpenCV could not encode the frame")
    header = json.dumps(
        {
            "seq": int(seq),
            "exposure_time_unix_usec": int(exposure_time_unix_usec),
            "encoding": encoding,
            "width_px": int(image_bgr.shape[1]),
            "height_px": int(image_bgr.shape[0]),
        }
    ).encode()
    payload = buf.tobytes()
    return FRAME_STREAM_MAGIC + _U32.pack(len(header)) + header + _U32.pack(len(payload)) + payload


def _parse_header(raw: bytes) -> dict[str, object]:
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FrameStreamError(f"frame header is not UTF-8 JSON: {exc}") from exc
    if not isinstance(header, dict):
        raise FrameStreamError("frame header must be a JSON object")
    for key in ("seq", "exposure_time_unix_usec", "width_px", "height_px"):
        value = header.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise FrameStreamError(
                f"frame header field {key!r}: expected a non-negative integer, got {value!r}"
            )
    encoding = header.get("encoding")
    if encoding not in _ENCODINGS:
        raise FrameStreamError(
            f"frame header field 'encoding': expected one of {sorted(_ENCODINGS)}, got {encoding!r}"
        )
    return header


async def read_frame(reader: asyncio.StreamReader) -> EncodedFrame:
    """Read one frame message. Raises ``asyncio.IncompleteReadError`` at EOF, ``FrameStreamError`` on
    malformed data (after which the stream is out of sync and must be reconnected)."""
    magic = await reader.readexactly(4)
    if magic != FRAME_STREAM_MAGIC:
        raise FrameStreamError(f"bad frame magic {magic!r}; expected {FRAME_STREAM_MAGIC!r}")
    (hlen,) = _U32.unpack(await reader.readexactly(4))
    if hlen == 0 or hlen > MAX_HEADER_BYTES:
        raise FrameStreamError(f"frame header length {hlen} outside 1..{MAX_HEADER_BYTES}")
    header = _parse_header(await reader.readexactly(hlen))
    (plen,) = _U32.unpack(await reader.readexactly(4))
    if plen == 0 or plen > MAX_PAYLOAD_BYTES:
        raise FrameStreamError(f"frame payload length {plen} outside 1..{MAX_PAYLOAD_BYTES}")
    payload = await reader.readexactly(plen)
    return EncodedFrame(
        seq=int(header["seq"]),  # type: ignore[call-overload]
        exposure_time_unix_usec=int(header["exposure_time_unix_usec"]),  # type: ignore[call-overload]
        encoding=str(header["encoding"]),
        width_px=int(header["width_px"]),  # type: ignore[call-overload]
        height_px=int(header["height_px"]),  # type: ignore[call-overload]
        payload=payload,
    )
