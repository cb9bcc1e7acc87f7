"""Work on the event loop that meets a slow path is run again in a thread."""

from __future__ import annotations

import asyncio
import threading
from types import SimpleNamespace

import pytest

from server.api.fastpath import run_blocking
from server.inline import WouldBlock, on_event_loop
from server.services.positioning import ModelCache


def _request(embedded: bool):
    return SimpleNamespace(app=SimpleNamespace(state=SimpleNamespace(db=SimpleNamespace(embedded=embedded))))


def test_work_that_would_block_on_the_loop_runs_again_in_a_thread():
    calls = []

    def work(x):
        calls.append((threading.get_ident(), on_event_loop.get()))
        if on_event_loop.get():
            raise WouldBlock("slow")
        return x * 2

    async def main():
        return threading.get_ident(), await run_blocking(_request(True), work, 21)

    loop_thread, answer = asyncio.run(main())
    assert answer == 42
    assert calls[0] == (loop_thread, True)
    assert calls[1][0] != loop_thread and calls[1][1] is False


def test_a_networked_database_always_uses_the_thread_pool():
    seen = []

    async def main():
        work = lambda: seen.append((threading.get_ident(), on_event_loop.get()))  # noqa: E731
        return threading.get_ident(), await run_blocking(_request(False), work)

    loop_thread, _ = asyncio.run(main())
    assert len(seen) == 1 and seen[0][0] != loop_thread and seen[0][1] is False


def test_the_model_cache_does_not_load_on_the_event_loop():
    class NoDatabase:
        def transaction(self):
            raise AssertionError("the cache must not read the database on the event loop")

    cache = ModelCache(NoDatabase())
    token = on_event_loop.set(True)
    try:
        with pytest.raises(WouldBlock):
            cache.get(1, "0" * 64)
    finally:
        on_event_loop.reset(token)
    assert cache.loads == 0
