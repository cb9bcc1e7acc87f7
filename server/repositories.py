"""Left for ``server.services.sessions`` until it imports ``server.store``, which now holds every query."""

from server.store.models import model_site
from server.store.sites import floor_levels, floor_walls, site_settings

__all__ = ["floor_levels", "floor_walls", "model_site", "site_settings"]
