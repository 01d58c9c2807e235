"""Network frame stream: the wire format between a camera process (or the SITL) and the daemon.

One message per frame, over a TCP byte stream::

    magic  b"GDNF"            4 bytes
    header_len  uint32 BE     4 bytes
    header      UTF-8 JSON    {"seq": int, "exposure_time_unix_usec": int, "encoding": "jpeg"|"png",
                               "width_px": int, "height_px": int}
    payload_len uint32 BE     4 bytes
    payload     encoded image (JPEG or PNG, BGR when decoded by OpenCV)

The reader validates every field and raises ``FrameStreamError`` naming what is wrong; the daemon
counts and records such frames and keeps going. ``EncodedFrame.decode`` reads the image size from the
payload's own PNG/JPEG header first and decodes only a payload whose size matches the frame header and
is at most ``MAX_FRAME_PIXELS``.
"""

from __future__ import annotations

import asyncio
import json
import struct
from dataclasses import dataclass

import cv2
import numpy as np

from gps_denied_onboard.constants import FRAME_STREAM_MAGIC
from gps_denied_onboard.helpers import bounded_json

_U32 = struct.Struct(">I")
MAX_HEADER_BYTES = 4096
MAX_PAYLOAD_BYTES = 32 << 20
#: Largest frame decoded, pixels (a 24 MP camera; 72 MB as BGR). A payload of a few MB can claim
#: 20000x20000 (1.2 GB decoded), so the size is read from the payload's own header before decoding.
MAX_FRAME_PIXELS = 6000 * 4000
_ENCODINGS = {"jpeg": ".jpg", "png": ".png"}

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: JPEG markers that start a frame header (SOF0..SOF15 except DHT 0xC4, JPG 0xC8, DAC 0xCC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
#: JPEG markers with no length field: TEM, RST0..RST7, SOI, EOI.
_JPEG_NO_LENGTH = frozenset({0x01, *range(0xD0, 0xDA)})
_JPEG_SOS = 0xDA


class FrameStreamError(ValueError):
    """A malformed frame message (bad magic, header, sizes or image payload)."""


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, which the format requires right after the signature;
    None when ``data`` does not start like a PNG."""
    if len(data) < 24 or not data.startswith(PNG_SIGNATURE) or data[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", data[16:24])
    return int(width), int(height)


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's first SOFn segment, walking the marker segments from SOI; None when
    ``data`` has no SOI, is cut short, or reaches the first scan (SOS) without a frame header."""
    if not data.startswith(b"\xff\xd8"):
        return None
    i, n = 2, len(data)
    while i + 2 <= n:
        if data[i] != 0xFF:
            return None  # between segments there must be a marker
        marker = data[i + 1]
        i += 2
        if marker == 0xFF:  # fill byte before a marker
            i -= 1
            continue
        if marker in _JPEG_NO_LENGTH:
            continue
        if marker == _JPEG_SOS or i + 2 > n:
            return None
        (length,) = struct.unpack(">H", data[i : i + 2])
        if marker in _JPEG_SOF:
            # length(2) precision(1) height(2) width(2) components(1)...
            if length < 8 or i + 7 > n:
                return None
            height, width = struct.unpack(">HH", data[i + 3 : i + 7])
            return int(width), int(height)
        if length < 2:
            return None
        i += length
    return None


_PAYLOAD_SIZE = {"jpeg": jpeg_size, "png": png_size}


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
        """Decode to (H, W, 3) uint8 BGR; raises FrameStreamError when the payload is not that image.

        Before anything is decoded, the size in the payload's own header (PNG IHDR, JPEG SOFn) must equal
        the frame header's and stay within MAX_FRAME_PIXELS: a decompression bomb is refused from a few
        bytes, and a payload of another format than ``encoding`` (which OpenCV would sniff and decode
        anyway, unchecked) is refused.
        """
        w, h = self.width_px, self.height_px
        size = _PAYLOAD_SIZE[self.encoding](self.payload)
        if size is None:
            raise FrameStreamError(
                f"frame {self.seq}: payload is not a decodable {self.encoding} image "
                "(no image size in its header); not decoded"
            )
        if size != (w, h):
            raise FrameStreamError(
                f"frame {self.seq}: header says {w}x{h}, {self.encoding} payload is {size[0]}x{size[1]}; "
                "not decoded"
            )
        if w < 1 or h < 1 or w * h > MAX_FRAME_PIXELS:
            raise FrameStreamError(
                f"frame {self.seq}: {w}x{h} ({w * h} px) is outside 1..{MAX_FRAME_PIXELS} px; not decoded"
            )
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
        header = bounded_json.loads(raw, max_bytes=MAX_HEADER_BYTES, what="frame header")
    except bounded_json.BoundedJsonError as exc:
        raise FrameStreamError(str(exc)) from exc
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
