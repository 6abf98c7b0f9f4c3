"""The service's own sections: ``[daemon]``, ``[record]`` and ``[status]`` (the web view)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from vgripd.config.common import AllowList, Model, is_ip, is_loopback
from vgripd.redaction import REDACTED


class DaemonConfig(Model):
    """The service: one job at a time, each bounded by ``job_timeout_s`` (see docs/daemon.md)."""

    job_timeout_s: float = Field(default=10.0, gt=0)
    # The camera down (no job can get a frame) for longer than this: the systemd watchdog stops
    # pinging, so systemd restarts the service (docs/daemon.md, "systemd integration").
    camera_down_restart_s: float = Field(default=60.0, gt=0)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    # Camera driver, pipeline and recorder in a worker process (docs/daemon.md, "Worker
    # process"); false runs them in the daemon's own interpreter (threads), as before.
    worker: bool = True
    # Cycle-time percentiles in `vgripd status` are taken over this many most recent jobs.
    stats_window: int = Field(default=1000, ge=1)
    # RECALIBRATE warning (docs/daemon.md): over the last `recalibrate_window` stereo jobs, the
    # share whose median epipolar residual exceeds vision.epipolar_warn_px; judged only once
    # `recalibrate_min_jobs` are in the window, raised while the share is above
    # `recalibrate_share`.
    recalibrate_window: int = Field(default=50, ge=1)
    recalibrate_share: float = Field(default=0.2, ge=0, lt=1)
    recalibrate_min_jobs: int = Field(default=10, ge=1)
    # File descriptors kept out of the server surfaces' share of RLIMIT_NOFILE: PLC client
    # links, the worker's pipes, shared-memory segments, recordings, the camera (docs/daemon.md,
    # "File budget").
    fd_reserve: int = Field(default=256, ge=32, le=1_000_000)

    @model_validator(mode="after")
    def _recalibrate_window(self) -> DaemonConfig:
        if self.recalibrate_min_jobs > self.recalibrate_window:
            raise ValueError(
                f"recalibrate_min_jobs ({self.recalibrate_min_jobs}) must not exceed "
                f"recalibrate_window ({self.recalibrate_window})"
            )
        return self


class RecordConfig(Model):
    """Recording of every job (images, metadata, config, result) for offline ``vgripd replay``.

    Off by default; when on, the oldest jobs are deleted beyond ``max_mb`` of the folder.
    """

    enabled: bool = False
    folder: Path = Path("/var/lib/vgripd/record")
    max_mb: float = Field(default=500.0, gt=0)


class StatusConfig(Model):
    """The operator web view, its JSON API (``GET /api/status`` behind ``vgripd status``) and
    ``/metrics`` (port 0: any free). See docs/web.md.

    Read-only unless an action is enabled here; an enabled action also needs a request that
    carries ``token`` (``Authorization: Bearer <token>``). A bind that is not a loopback
    address needs a ``token``, and then every route needs it too (the header, or the cookie
    of ``/login``) unless ``public_read`` opens the read-only routes to anyone who can reach
    the port. ``allowed_hosts``: host names (or addresses) a browser may call the view by,
    besides the bind address (and ``localhost`` on a loopback or wildcard bind); any other
    ``Host:`` is refused (421), which stops DNS rebinding. ``history``: jobs kept for the
    history page; ``bundle_jobs``: recorded jobs put in a support bundle.
    """

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(default=8730, ge=0, le=65535)
    token: str | None = None
    public_read: bool = False
    allowed_hosts: list[str] = Field(default_factory=list, max_length=64)
    allow_trigger: bool = False
    allow_support_bundle: bool = False
    # Commissioning from the page (docs/web.md, "Reload, tuning and audit"): reload the config
    # file, try vision parameters on the last job's images and save them to the config's
    # include (all with the token).
    allow_config_edit: bool = False
    history: int = Field(default=100, ge=1, le=10000)
    bundle_jobs: int = Field(default=5, ge=0, le=100)
    # Connections (docs/web.md, "Connections"): at most `max_connections` at once (ones that
    # never completed a request are evicted first), complete request headers within
    # `header_timeout_s` of connecting or of the previous answer, a body within
    # `body_timeout_s`; `allow` = client addresses/networks (unset: any).
    max_connections: int = Field(default=64, ge=2, le=4096)
    header_timeout_s: float = Field(default=10.0, ge=0.5, le=600.0)
    body_timeout_s: float = Field(default=10.0, ge=0.5, le=600.0)
    allow: AllowList = None
    # Wrong tokens (docs/web.md, "Wrong tokens"), per client address as the OPC UA link's
    # logins: each answered no sooner than 1 / `login_rate_per_s` after the previous one,
    # `login_failures` in a row lock the address's tokens out for `login_lockout_s`.
    login_failures: int = Field(default=10, ge=1, le=1000)
    login_rate_per_s: float = Field(default=10.0, gt=0.0, le=1000.0)
    login_lockout_s: float = Field(default=60.0, ge=0.0, le=86400.0)

    @field_validator("token")
    @classmethod
    def _long_token(cls, token: str | None) -> str | None:
        # The redaction marker: a recorded or bundled config stays loadable (replay); the
        # web view refuses to serve with it.
        if token is not None and token != REDACTED and len(token) < 16:
            raise ValueError("status.token must have at least 16 characters")
        return token

    @field_validator("allowed_hosts")
    @classmethod
    def _host_names(cls, hosts: list[str]) -> list[str]:
        for i, host in enumerate(hosts):
            name = host.strip("[]")
            if not name or any(c in name for c in "/@ ?#") or (":" in name and not is_ip(name)):
                raise ValueError(f"status.allowed_hosts[{i}] = {host!r}: a host name or address "
                                 f"as a browser puts it in the URL, without scheme, port or path")
        return [h.strip("[]").lower().rstrip(".") for h in hosts]

    @model_validator(mode="after")
    def _token_where_needed(self) -> StatusConfig:
        if self.token is None and not is_loopback(self.host):
            raise ValueError(
                f"status.host = {self.host!r} is not a loopback address: set status.token "
                f"(at least 16 characters) or bind status.host = \"127.0.0.1\"")
        wanted = [k for k in ("allow_trigger", "allow_support_bundle", "allow_config_edit")
                  if getattr(self, k)]
        if self.token is None and wanted:
            raise ValueError(f"status.{wanted[0]} = true needs status.token (actions are "
                             f"accepted only from requests that carry it)")
        return self

    @property
    def guards_reads(self) -> bool:
        """Whether the read-only routes need the token too (a non-loopback bind, unless
        ``public_read``)."""
        return not is_loopback(self.host) and not self.public_read
