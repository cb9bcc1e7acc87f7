"""Small pieces shared by the project's pure ASGI middlewares."""

from __future__ import annotations

import json
from typing import Any

from starlette.types import Message, Send


class TrackedSend:
    """Wraps ``send`` and remembers whether the response has started (after that, no other
    response can be sent in its place)."""

    def __init__(self, send: Send):
        self._send = send
        self.started = False

    async def __call__(self, message: Message) -> None:
        self.started = self.started or message["type"] == "http.response.start"
        await self._send(message)


async def send_json(send: Send, status: int, payload: Any) -> None:
    """A complete JSON response."""
    body = json.dumps(payload).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
        }
    )
    await send({"type": "http.response.body", "body": body})
