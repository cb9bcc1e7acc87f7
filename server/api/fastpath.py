"""The hot routes (batches, locate) read their bodies and run their work themselves.

``read_json`` parses and validates a JSON body in one pydantic pass (FastAPI decodes it
to Python objects first and validates those) and reports errors exactly as FastAPI does.
``run_blocking`` runs the route's synchronous work right on the event loop when the
database is embedded (SQLite: every call a local file access of a fraction of a
millisecond, where a thread-pool hop costs more CPU than that in GIL hand-offs), and in
the thread pool when it is networked, so that waits on the network don't stall the process,
or when the work meets a slow path (``server.inline.WouldBlock``: a model to load).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.auth import Authenticator, Principal
from server.db import Database
from server.errors import UnsupportedMedia
from server.inline import WouldBlock, on_event_loop

M = TypeVar("M", bound=BaseModel)
T = TypeVar("T")


def json_body_doc(model: type[BaseModel]) -> dict[str, Any]:
    """``openapi_extra`` for a route that reads ``model`` itself (the app publishes the schema)."""
    ref = {"$ref": f"#/components/schemas/{model.__name__}"}
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": ref}}}}


#: bodies larger than this are parsed in the thread pool, not on the event loop
PARSE_INLINE_MAX_BYTES = 64 * 1024


async def read_json(request: Request, model: type[M]) -> M:
    """The body as ``model``: 415 unless it is declared JSON (or not declared), 422 as FastAPI words it."""
    media = request.headers.get("content-type", "application/json").split(";")[0].strip().lower()
    if media != "application/json" and not media.endswith("+json"):
        raise UnsupportedMedia(f"unsupported media type {media!r}: send application/json")
    body = await request.body()
    try:
        if len(body) > PARSE_INLINE_MAX_BYTES:
            return await run_in_threadpool(model.model_validate_json, body)
        return model.model_validate_json(body)
    except ValidationError as exc:
        raise RequestValidationError(
            [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False, include_input=False)]
        ) from None


async def run_blocking(request: Request, work: Callable[..., T], *args: Any) -> T:
    return await run_work(request.app.state.db, work, *args)


async def run_work(db: Database, work: Callable[..., T], *args: Any) -> T:
    """``work(*args)`` on the event loop (embedded database), else or on ``WouldBlock`` in the thread pool."""
    if db.embedded:
        token = on_event_loop.set(True)
        try:
            return work(*args)
        except WouldBlock:
            pass  # it wrote nothing: run it again where it may wait
        finally:
            on_event_loop.reset(token)
    return await run_in_threadpool(work, *args)


def replaying(messages: list[Message], error: Exception | None, receive: Receive) -> Receive:
    """A ``receive`` that gives ``messages`` again (the body a fast path read), then raises ``error``
    if reading stopped on one, then goes on with ``receive``: the app behind sees the request as
    it arrived."""
    pending = list(messages)
    failed = [error] if error is not None else []

    async def replayed() -> Message:
        if pending:
            return pending.pop(0)
        if failed:
            raise failed.pop()
        return await receive()

    return replayed


class BodyUnread(Exception):
    """Reading a request's body stopped: ``error`` is what ``receive`` raised (None: the client went away)."""

    def __init__(self, messages: list[Message], error: Exception | None):
        super().__init__("body unread")
        self.messages, self.error = messages, error


async def read_body(receive: Receive) -> tuple[list[Message], bytes]:
    """The messages a request's body came in (to replay) and the body, or ``BodyUnread`` carrying the
    messages read so far and what stopped the reading (a body too large, too slow, cut off: the
    route reports it when they are replayed to it)."""
    messages: list[Message] = []
    chunks: list[bytes] = []
    try:
        while True:
            message = await receive()
            messages.append(message)
            if message["type"] != "http.request":  # the client went away: as the route sees it
                raise BodyUnread(messages, None)
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                return messages, b"".join(chunks)
    except BodyUnread:
        raise
    except Exception as exc:  # noqa: BLE001
        raise BodyUnread(messages, exc) from None


def _header(scope: Scope, name: bytes) -> bytes | None:
    """The first value of header ``name`` (lower case), as Starlette's ``headers.get`` gives it."""
    return next((value for key, value in scope["headers"] if key == name), None)


def declared_json(scope: Scope) -> bool:
    """Declared JSON (or not declared), as ``read_json`` takes it, with a length small enough to parse inline."""
    media = (_header(scope, b"content-type") or b"application/json").decode("latin-1").split(";")[0].strip().lower()
    length = _header(scope, b"content-length")
    return (media == "application/json" or media.endswith("+json")) and length is not None and length.isdigit() \
        and int(length) <= PARSE_INLINE_MAX_BYTES


async def key_principal(auth: Authenticator, scope: Scope) -> Principal | None:
    """The key's principal as ``server.api.deps`` finds it, or None where it would refuse the request
    (no bearer key, an address waiting after failures, an unknown key): the route then refuses it
    itself, counting the failure once."""
    authorization = _header(scope, b"authorization")
    scheme, _, credentials = (authorization or b"").decode("latin-1").partition(" ")
    credentials = credentials.strip()
    if not scheme or not credentials or scheme.lower() != "bearer":
        return None
    principal = auth.bootstrap(credentials)
    if principal is None:
        client = scope.get("client")
        if auth.failures.retry_after(client[0] if client else "") is not None:
            return None
        principal = await run_in_threadpool(auth.stored, credentials)
    return principal


class RouteAnswers(Exception):
    """This request is the route's to answer (a fast path's refusal: the route gives its own)."""


class FastPath:
    """Base of the pure ASGI fast paths in front of the router (``LocateFastPath``,
    ``BatchFastPath``): a ``POST`` to ``path`` with a bearer key allowing device work and a JSON
    body of declared length is answered by ``answer`` (the route's own work and bytes) without
    FastAPI's per-request machinery (trying the routes in turn, solving dependencies, its
    exception and exit-stack wrappers). Everything else — another route, no key or a refused one,
    a body not declared JSON or of no declared length, a body cut off, ``answer`` raising for any
    reason, dependency overrides in place, ``app.state.<flag>`` false — goes to the app as it
    arrived (the body replayed), where the route answers exactly as it always did."""

    #: the route's path (``fullmatch``; its groups go to ``answer``)
    path: ClassVar[re.Pattern[str]]
    #: the ``app.state`` attribute that turns this fast path on
    flag: ClassVar[str]

    def __init__(self, app: ASGIApp):
        self.app = app

    async def answer(self, state: Any, match: re.Match[str], principal: Principal, body: bytes) -> Response:
        """The route's response for this request; raise (``RouteAnswers`` or anything) to let the route answer."""
        raise NotImplementedError

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        match = self.path.fullmatch(scope["path"]) if scope["type"] == "http" and scope["method"] == "POST" \
            else None
        application = scope.get("app")
        if match is None or application is None or not getattr(application.state, self.flag, False) \
                or application.dependency_overrides or not declared_json(scope):
            await self.app(scope, receive, send)
            return
        try:
            messages, body = await read_body(receive)
        except BodyUnread as unread:  # a body too large, too slow, cut off: the route reports it
            await self.app(scope, replaying(unread.messages, unread.error, receive), send)
            return
        try:
            state = application.state
            principal = await key_principal(state.auth, scope)
            if principal is None or not principal.allows("device"):
                raise RouteAnswers
            response = await self.answer(state, match, principal, body)
        except Exception:  # noqa: BLE001  (refused, invalid or failed: the route answers, its own way)
            await self.app(scope, replaying(messages, None, receive), send)
            return
        await response(scope, receive, send)
