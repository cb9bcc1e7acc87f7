"""Counting what a test wants to see (or not see) reached: an async function's calls, the failed
authentications of a client address."""

from __future__ import annotations

from types import ModuleType

from server.auth import FailureLimiter


def count_async_calls(monkeypatch, module: ModuleType, name: str) -> list[int]:
    """Replace ``module.name`` (an async function) by one that records each call, then calls it;
    the returned list grows by one per call."""
    calls: list[int] = []
    original = getattr(module, name)

    async def counted(*args):
        calls.append(1)
        return await original(*args)

    monkeypatch.setattr(module, name, counted)
    return calls


def failures_since(limiter: FailureLimiter, since: float, address: str = "127.0.0.1") -> int:
    """Failed authentications ``limiter`` recorded for ``address`` at or after ``since``
    (``time.monotonic()``). Counting by time, not by length, keeps earlier tests' failures that
    leave the sliding minute meanwhile out of the count."""
    return sum(t >= since for t in limiter._failures.get(address, ()))
