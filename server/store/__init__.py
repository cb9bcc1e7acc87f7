"""The database, one module per aggregate. Nothing outside this package builds SQL.

Functions take an open ``Session`` (or, on the per-batch path, a Core ``Connection``)
inside the caller's transaction and take and return domain dataclasses (``server.domain``).
"""
