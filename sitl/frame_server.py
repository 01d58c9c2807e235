"""TCP server that streams rendered nav frames to the daemon (the SITL's camera)."""

from __future__ import annotations

import asyncio
import contextlib


class FrameServer:
    """Serves one client at a time on 127.0.0.1; frames sent while no client is connected are counted
    as undelivered (a camera does not buffer for a missing consumer)."""

    def __init__(self) -> None:
        self._server: asyncio.base_events.Server | None = None
        self._writer: asyncio.StreamWriter | None = None
        self.port = 0
        self.delivered = 0
        self.undelivered = 0
        self.client_connected = asyncio.Event()

    async def start(self, port: int = 0) -> int:
        self._server = await asyncio.start_server(self._on_client, "127.0.0.1", port)
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._writer is not None:
            self._writer.close()
        self._writer = writer
        self.client_connected.set()

    def drop_client(self) -> bool:
        """Close the connection to the current client (a camera cable pulled); True if there was one."""
        writer, self._writer = self._writer, None
        if writer is None:
            return False
        writer.close()
        return True

    async def send(self, message: bytes) -> bool:
        writer = self._writer
        if writer is None or writer.is_closing():
            self.undelivered += 1
            return False
        try:
            writer.write(message)
            await asyncio.wait_for(writer.drain(), 1.0)
        except (ConnectionError, asyncio.TimeoutError, OSError):
            self.undelivered += 1
            self._writer = None
            return False
        self.delivered += 1
        return True

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
