"""Kept for old imports: the status endpoint is now the web view (``vgripd.service.web``), which
serves the same JSON at ``GET /api/status`` and, as an alias, ``GET /status``."""

from vgripd.service.web import StatusEndpointError
from vgripd.service.web import WebServer as StatusServer

__all__ = ["StatusEndpointError", "StatusServer"]
