"""Left for callers not yet moved to ``server.store``, which now holds every query.

Remove once ``server.services.sessions`` and ``benchmarks/locate_http.py`` import the
store directly.
"""

from server.store.models import model_artifact, model_site
from server.store.sites import floor_levels, floor_walls, site_settings

__all__ = ["floor_levels", "floor_walls", "model_artifact", "model_site", "site_settings"]
