"""The command-line failures a user can fix, each told in one line: what went wrong and where."""

from __future__ import annotations

import argparse

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


def seed_int(text: str) -> int:
    """An argparse type for ``--seed``: a non-negative integer (numpy's generators take no negative
    seed), else a usage error naming the value."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, not {text!r}")
    return value
