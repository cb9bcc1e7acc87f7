"""Unexpected exceptions become a logged JSON 500, so the connection stays usable."""

from __future__ import annotations

import logging

from starlette.types import ASGIApp, Receive, Scope, Send

from server.api.asgi import TrackedSend, send_json

log = logging.getLogger("server")


class InternalErrors:
    """Pure ASGI middleware: an exception that escapes a route is logged and answered with
    ``500 {"detail": "internal server error"}`` instead of re-raised into the server, which
    would drop the client's keep-alive connection (and the client's next request with it)."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        tracked = TrackedSend(send)
        try:
            await self.app(scope, receive, tracked)
        except Exception:
            log.exception("unhandled error in %s %s", scope.get("method"), scope.get("path"))
            if tracked.started:
                raise
            await send_json(send, 500, {"detail": "internal server error"})
