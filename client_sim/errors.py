"""The command-line failures a user can fix, each told in one line: what went wrong and where."""

from __future__ import annotations

import argparse
import math

import httpx

from .http_client import ApiError

EXIT_FAILED, EXIT_USAGE = 1, 2


class CliError(Exception):
    """A failure told in one line on stderr; ``code`` is the exit status."""

    def __init__(self, message: str, code: int = EXIT_FAILED):
        super().__init__(message)
        self.code = code


def explain(exc: BaseException, url: str | None) -> CliError | None:
    """The one-line message for a failure a user can fix (None: a bug, let it raise)."""
    where = url or "the server"
    if isinstance(exc, CliError):
        return exc
    if isinstance(exc, ApiError):
        if exc.status == 401:
            return CliError(f"{where} refused the {exc.key_name} (401: {exc.detail})")
        if exc.status == 403:
            return CliError(f"{where}: the {exc.key_name} may not do this (403: {exc.detail})")
        if exc.status == 404:
            return CliError(f"{where}: {exc.detail} (404)")
        return CliError(f"{where}: {exc}")
    if isinstance(exc, httpx.ConnectError):
        return CliError(f"cannot connect to {where}: is the server running? ({exc})")
    if isinstance(exc, httpx.HTTPError):
        return CliError(f"{where}: {type(exc).__name__}: {exc}")
    if isinstance(exc, OSError) and exc.filename:
        return CliError(f"{exc.filename}: {exc.strerror}", EXIT_USAGE)
    return None


def number(kind: type, low: float, *, above: bool = False, high: float | None = None):
    """An argparse type: a ``kind`` (int or float) at least ``low`` (greater, with ``above``) and at most
    ``high``; anything else is a usage error naming the value (a zero interval divided by zero, a
    negative count crashed numpy, with a traceback)."""
    what = f"{'an integer' if kind is int else 'a number'} {'>' if above else '≥'} {low:g}"
    what += "" if high is None else f" and ≤ {high:g}"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not math.isfinite(value) or (value <= low if above else value < low) or \
                (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {what}, not {text!r}")
        return value

    return parse


#: ``--seed``: numpy's generators take no negative seed
seed_int = number(int, 0)
