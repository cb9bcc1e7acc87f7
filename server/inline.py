"""Work run right on the event loop must not wait on anything slow.

The hot routes run their work on the event loop when the database is embedded (see
``server.api.fastpath``). A slow path that such work may reach — loading a trained model
from the database, up to a second for a large one — checks ``on_event_loop`` and raises
``WouldBlock`` instead; the route then runs the whole work again in the thread pool.
Work that may be sent back this way must not have written anything before the slow path.
"""

from __future__ import annotations

from contextvars import ContextVar

#: True while the current work runs on the event loop thread
on_event_loop: ContextVar[bool] = ContextVar("on_event_loop", default=False)


class WouldBlock(Exception):
    """The work reached a slow path while on the event loop: run it in a thread instead."""
