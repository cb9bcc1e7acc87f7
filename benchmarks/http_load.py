"""The benchmarks' HTTP load side: aiohttp, because a load generator that shares the
machine with the server must cost little per request (httpx's async client spends
≈ 4× more CPU per request and capped the earlier figures)."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable

import aiohttp


def client(base: str, key: str, connections: int) -> aiohttp.ClientSession:
    """A keep-alive client for ``base`` sending ``Authorization: Bearer key``."""
    return aiohttp.ClientSession(
        base, headers={"Authorization": f"Bearer {key}"},
        connector=aiohttp.TCPConnector(limit=connections, force_close=False),
        timeout=aiohttp.ClientTimeout(total=120),
    )


async def closed_loop(session: aiohttp.ClientSession, request: Callable[[int], tuple[str, str, object]],
                      count: int, concurrency: int) -> tuple[float, list[float]]:
    """Send ``count`` requests from ``concurrency`` workers, each sending its next as soon as
    the last is answered; ``request(i)`` gives (method, path, json body or None).
    Returns the elapsed seconds and every latency; any non-2xx answer raises."""
    latencies: list[float] = []
    todo = iter(range(count))

    async def worker() -> None:
        for i in todo:
            method, path, body = request(i)
            t0 = time.perf_counter()
            async with session.request(method, path, json=body) as answer:
                await answer.read()
                answer.raise_for_status()
            latencies.append(time.perf_counter() - t0)

    started = time.perf_counter()
    await asyncio.gather(*(worker() for _ in range(concurrency)))
    return time.perf_counter() - started, latencies


def _processes() -> dict[int, tuple[str, int, list[str]]] | None:
    """Every process as /proc shows it: pid → (name, parent pid, the stat fields after the name);
    None where there is no /proc."""
    try:
        procs: dict[int, tuple[str, int, list[str]]] = {}
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                with open(f"/proc/{entry}/stat") as f:
                    head, rest = f.read().rsplit(")", 1)
            except OSError:
                continue
            fields = rest.split()
            procs[int(entry)] = (head.split("(", 1)[-1], int(fields[1]), fields)
        return procs
    except (OSError, ValueError):
        return None


def _cpu_of(keep) -> float | None:
    """CPU time (user + system, s) of the processes for which ``keep(pid, parent_pid, name)``
    holds (None where there is no /proc)."""
    procs = _processes()
    if procs is None:
        return None
    tick = os.sysconf("SC_CLK_TCK")
    return sum(int(fields[11]) + int(fields[12])  # utime, stime
               for pid, (name, parent, fields) in procs.items() if keep(pid, parent, name)) / tick


def cpu_seconds(pid: int) -> float | None:
    """CPU time used so far by process ``pid`` and its children: a server's cost per
    request, unlike its throughput, does not move with the rest of the machine's load."""
    return _cpu_of(lambda p, parent, _: p == pid or parent == pid)


def database_cpu_seconds() -> float | None:
    """CPU time (s) used so far by every PostgreSQL process on this machine, those that have
    exited included: a backend's time moves into its postmaster's ``cutime``/``cstime`` when it
    ends. Counting only the live processes (as this did before) lost the time of
    every connection closed during the run: with a pool that opened and closed connections under
    load, 0.1-0.2 ms of a batch's ≈ 0.8 ms."""
    procs = _processes()
    if procs is None:
        return None
    total = 0.0
    for name, parent, fields in procs.values():
        if name != "postgres":
            continue
        total += int(fields[11]) + int(fields[12])  # utime, stime
        if procs.get(parent, ("",))[0] != "postgres":  # the postmaster: its reaped children's too
            total += int(fields[13]) + int(fields[14])  # cutime, cstime
    return total / os.sysconf("SC_CLK_TCK")
