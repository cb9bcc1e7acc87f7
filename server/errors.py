"""Domain errors raised by services and parsers. They say what went wrong, never how
HTTP reports it: the API layer (``server.app``) maps each class to its status."""

from __future__ import annotations

from typing import Any


class ServiceError(Exception):
    """``detail`` is a message, or a list of problems (dicts naming e.g. the ``field``
    or ``row`` and a ``msg``)."""

    def __init__(self, detail: Any):
        super().__init__(detail if isinstance(detail, str) else repr(detail))
        self.detail = detail


class NotFound(ServiceError):
    pass


class Conflict(ServiceError):
    """The request is valid but the state of the data does not allow it (now)."""


class NoReadyModel(Conflict):
    """The site has no model that can serve."""

    def __init__(self, site_id: int):
        super().__init__(f"site {site_id} has no ready model")
        self.site_id = site_id


class TooLarge(ServiceError):
    pass


class Invalid(ServiceError):
    pass


class InvalidField(Invalid):
    """One named input field of the request is invalid."""

    def __init__(self, field: str, msg: str):
        super().__init__([{"field": field, "msg": msg}])
        self.field = field
        self.msg = msg


class UnsupportedMedia(ServiceError):
    """A document in a format that is not understood."""


class Unavailable(ServiceError):
    """A resource the service needs (the database) does not answer."""
