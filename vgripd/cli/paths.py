"""Where the installed service keeps its files (systemd/vgripd.service): the commands' defaults.
A module of its own, so that a command names them without importing the daemon."""

from __future__ import annotations

#: The config the unit runs (``ConfigurationDirectory=vgripd``, read-only for the service).
DEFAULT_CONFIG = "/etc/vgripd/vgripd.toml"
#: The service's writable state (``StateDirectory=vgripd``): recordings, the cell includes.
DEFAULT_STATE_DIR = "/var/lib/vgripd"
