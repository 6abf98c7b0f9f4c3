"""The operator web view, its JSON API and Prometheus metrics (docs/web.md)."""

from vgripd.service.web.app import StatusEndpointError, WebServer

__all__ = ["StatusEndpointError", "WebServer"]
