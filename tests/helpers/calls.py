"""Counting the calls of an async function a test wants to see (or not see) reached."""

from __future__ import annotations

from types import ModuleType


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
