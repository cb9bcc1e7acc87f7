"""Refuse request bodies over their route's size before they are read into memory, and bodies
that stop arriving."""

from __future__ import annotations

import asyncio
import re
from collections.abc import Sequence

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.api.asgi import TrackedSend, send_json

#: the batch route: 1,000 steps and 1,000 scans of up to ~100 transmitters each fit in 4 MiB
BATCH_ROUTE = re.compile(r"^/api/v1/sessions/[^/]+/batches$")
#: the locate route: one scan (at most 2,048 transmitters)
LOCATE_ROUTE = re.compile(r"^/api/v1/sites/[^/]+/locate$")


#: the most header bytes (names and values) a request may carry: 431 beyond
MAX_HEADER_BYTES = 32 * 1024


class BodySizeLimit:
    """Pure ASGI middleware: 413 on a too-large Content-Length, or once a streamed body passes the
    limit (``max_bytes``, or the first of ``routes`` whose pattern matches the path); 408 when the
    client stops sending a body it started for ``read_timeout_s``; 431 when its headers exceed
    ``MAX_HEADER_BYTES``."""

    def __init__(self, app: ASGIApp, max_bytes: int, routes: Sequence[tuple[re.Pattern[str], int]] = (),
                 read_timeout_s: float | None = None):
        self.app = app
        self.max_bytes = max_bytes
        self.routes = list(routes)
        self.read_timeout_s = read_timeout_s

    def limit_for(self, path: str) -> int:
        return next((limit for pattern, limit in self.routes if pattern.match(path)), self.max_bytes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if sum(len(name) + len(value) for name, value in scope["headers"]) > MAX_HEADER_BYTES:
            await send_json(send, 431, {"detail": f"request headers exceed {MAX_HEADER_BYTES} bytes"})
            return
        limit = self.limit_for(scope.get("path", ""))
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await self._refuse(send, limit)
            return
        seen = 0
        body_done = False
        tracked = TrackedSend(send)

        async def limited_receive() -> Message:
            nonlocal seen, body_done
            if body_done or self.read_timeout_s is None:
                message = await receive()  # after the body: e.g. a stream waiting for the disconnect
            else:
                try:
                    message = await asyncio.wait_for(receive(), self.read_timeout_s)
                except TimeoutError:
                    raise _TooSlow(self.read_timeout_s) from None
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
                if seen > limit:
                    raise _TooLarge(limit)
            return message

        try:
            await self.app(scope, limited_receive, tracked)
        except (_TooLarge, _TooSlow) as exc:  # when no handler inside answered it
            if not tracked.started:
                await send_json(send, exc.status_code, {"detail": exc.detail})

    async def _refuse(self, send: Send, limit: int) -> None:
        await send_json(send, 413, {"detail": f"request body exceeds {limit} bytes"})


class _TooLarge(HTTPException):
    """Raised while reading: an HTTPException, so the route's own body parsing (which words any
    other error as a 400) lets it through to the app's handler."""

    def __init__(self, limit: int):
        super().__init__(413, f"request body exceeds {limit} bytes")


class _TooSlow(HTTPException):
    def __init__(self, timeout_s: float | None):
        super().__init__(408, f"the request body did not arrive within {timeout_s:g} s")
