"""The operator web view, its JSON API and Prometheus metrics (docs/web.md)."""

from vgripd.service.web.app import StatusEndpointError, WebServer
from vgripd.service.web.trigger import WEB_LINK, WebTriggerLink

__all__ = ["WEB_LINK", "StatusEndpointError", "WebServer", "WebTriggerLink"]
