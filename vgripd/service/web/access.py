"""Who may read what from the web view (docs/web.md, "Security model"), as one aiohttp middleware
and one response hook, apart from the routes themselves:

- the ``Host:`` header must name the view (its bind address, ``localhost`` on a loopback or
  wildcard bind, on a wildcard bind the address the client connected to, or
  ``status.allowed_hosts``); anything else is a DNS-rebinding attempt or a misdirected
  request: 421;
- with a non-loopback bind every route needs the token (``status.guards_reads``) unless
  ``status.public_read``: ``Authorization: Bearer <token>``, or the session cookie that
  ``POST /login`` sets for a browser (HttpOnly, SameSite=Strict). Actions take the header only,
  so the cookie alone can never start one (no cross-site request can set that header);
- a presented token (the ``Bearer`` header on any route, the ``/login`` form) is judged once
  per request, and wrong ones are throttled per client address (``LoginThrottle``, as the OPC
  UA link's logins): each failure answered no sooner than ``1 / login_rate_per_s`` after the
  address's previous one, ``login_failures`` in a row lock the address out for
  ``login_lockout_s``: its tokens are then refused unchecked (429, the right one too);
- an exception a handler did not turn into an answer is a 500 with one rate-limited log line,
  never a traceback per request;
- every answer carries the security headers (``SECURITY_HEADERS``).

The session cookie's value is an HMAC of a fixed label under the token: it survives a restart,
changes with the token, and does not reveal it.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import ipaddress
import logging
import socket
import time
import traceback
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from aiohttp import web

from vgripd.redaction import REDACTED
from vgripd.service.links.ratelog import RateLimitedLog
from vgripd.service.links.throttle import LoginThrottle
from vgripd.service.web.bodies import login_form

if TYPE_CHECKING:
    from vgripd.config import StatusConfig

log = logging.getLogger("vgripd.service.web")

SESSION_COOKIE = "vgripd-session"
# Routes that answer without the token even where reads are guarded: the login form.
OPEN_PATHS = frozenset({"/login"})
SECURITY_HEADERS = {
    # Scripts, styles, images and the event stream from the view itself only; no inline code,
    # no framing, forms post back here only.
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; "
        "connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'"),
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Resource-Policy": "same-origin",
}
LOGIN_PAGE = """<!doctype html>
<html lang="en">
<head><meta charset="utf-8"><title>vgripd: log in</title></head>
<body>
<h1>vgripd</h1>
<p>{message}</p>
<form method="post" action="/login">
<label>Token <input name="token" type="password" autocomplete="current-password" autofocus></label>
<button type="submit">Log in</button>
</form>
</body>
</html>
"""
LOGIN_ASK = "This view needs the token ([status] token in the daemon's config)."
LOGIN_WRONG = "Wrong token."
#: Where the middleware keeps its judgement of a request's Bearer token.
# (aiohttp before 3.12 has no RequestKey: a plain string key there)
_JUDGED: Any = (web.RequestKey("vgripd_bearer_ok", bool) if hasattr(web, "RequestKey")
                else "vgripd_bearer_ok")

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _same_ip(a: str, b: str) -> bool:
    """Two address literals name the same address (an IPv4-mapped IPv6 one as its IPv4)."""
    try:
        x, y = ipaddress.ip_address(a), ipaddress.ip_address(b.split("%", 1)[0])
    except ValueError:
        return False
    x = getattr(x, "ipv4_mapped", None) or x
    y = getattr(y, "ipv4_mapped", None) or y
    return x == y


def host_name(header: str) -> str:
    """The name of a ``Host:`` header without its port, lower case, brackets and a trailing
    dot removed (``[::1]:8730`` -> ``::1``, ``Cell.local.:80`` -> ``cell.local``)."""
    text = header.strip().lower()
    if text.startswith("["):
        text = text[1:text.find("]")] if "]" in text else text[1:]
    elif text.count(":") == 1:
        text = text.split(":", 1)[0]
    return text.rstrip(".")


def _parse_bearer(request: web.Request) -> str:
    header = request.headers.get("Authorization", "")
    return header[7:].strip() if header[:7].lower() == "bearer " else ""


class Access:
    """The access rules of one web view, from its ``[status]`` section."""

    def __init__(self, st: StatusConfig) -> None:
        self._token = st.token if st.token not in (None, REDACTED) else None
        self.guards_reads = st.guards_reads
        bind = host_name(st.host) if st.host else ""
        self._wildcard = bind in ("", "0.0.0.0", "::")
        names = set(st.allowed_hosts)
        if not self._wildcard:
            names.add(bind)
        if self._wildcard or _is_loopback(bind):
            names |= {"localhost", "127.0.0.1", "::1"}
        if self._wildcard:  # how the machine calls itself; not an attacker's name
            names.add(socket.gethostname().lower())
        self.allowed_hosts = frozenset(names)
        self._session = (None if self._token is None else hmac.new(
            self._token.encode(), b"vgripd web session", hashlib.sha256).hexdigest())
        self.ratelog = RateLimitedLog(log, interval_s=60.0)
        self.throttle = LoginThrottle(st.login_failures, st.login_rate_per_s,
                                      st.login_lockout_s)
        self.lockout_s = st.login_lockout_s
        #: Wrong tokens counted (``vgripd_web_login_failures_total``), lockouts begun, and
        #: tokens refused unchecked while their address was locked out (``/metrics``).
        self.failures = 0
        self.lockouts = 0
        self.refused_locked = 0

    # --- checks ---------------------------------------------------------------------------

    def host_ok(self, header: str | None, local: str | None = None) -> bool:
        """Whether a ``Host:`` header names this view. A request without one (HTTP/1.0) has
        no name to rebind; on a wildcard bind an address literal is accepted when it is the
        address the client connected to (``local``, the socket's own)."""
        if header is None:
            return True
        name = host_name(header)
        if name in self.allowed_hosts:
            return True
        return self._wildcard and local is not None and _same_ip(name, local)

    def _matches(self, given: str) -> bool:
        return self._token is not None and hmac.compare_digest(given.encode(),
                                                               self._token.encode())

    def bearer_ok(self, request: web.Request) -> bool:
        """The request carries ``Authorization: Bearer <token>`` (constant-time compare; the
        middleware's judgement, which counted a wrong one)."""
        judged = request.get(_JUDGED)
        return bool(judged) if judged is not None else self._matches(_parse_bearer(request))

    async def judge(self, request: web.Request, given: str, where: str) -> bool:
        """Whether ``given`` is the token, throttled per client address: a wrong one is
        counted and answered no sooner than the throttle says; while the address is locked
        out, 429 without a look at ``given``."""
        host = request.remote or "?"
        now = time.monotonic()
        left = self.throttle.locked(host, now)
        if left > 0:
            self.refused_locked += 1
            raise web.HTTPTooManyRequests(
                headers={"Retry-After": str(max(1, round(left)))},
                text=f"too many wrong tokens from {host}: tokens from this address are refused "
                     f"for {left:.0f} s more (status.login_lockout_s)")
        if self._matches(given):
            self.throttle.succeeded(host)
            return True
        self.failures += 1
        delay, locked = self.throttle.failed(host, now)
        if locked:
            self.lockouts += 1
            self.ratelog.warning(host, "lockout", "web view: %s: %d wrong tokens in a row (the "
                                 "last at %s): its tokens are refused for %g s "
                                 "(status.login_lockout_s)", host, self.throttle.max_failures,
                                 where, self.lockout_s)
        else:
            self.ratelog.warning(host, "login", "web view: wrong token at %s from %s", where,
                                 host)
        if delay > 0:
            await asyncio.sleep(delay)
        return False

    def require_action(self, request: web.Request, enabled: bool, key: str) -> None:
        """The check of an action: 404 while it is disabled (naming ``status.<key>``, the
        switch that enables it), 403 unless the request carries the token in its header
        (never the login cookie)."""
        if not enabled:
            raise web.HTTPNotFound(text=f"this action is disabled in the config: it needs "
                                        f"status.{key} = true (with status.token)")
        if not self.bearer_ok(request):
            raise web.HTTPForbidden(text="this action needs the token: "
                                         "Authorization: Bearer <status.token>")

    def holds_token(self, request: web.Request) -> bool:
        """The request carries the token: the header, or the session cookie of ``/login``."""
        if self.bearer_ok(request):
            return True
        cookie = request.cookies.get(SESSION_COOKIE, "")
        return self._session is not None and hmac.compare_digest(cookie.encode(),
                                                                 self._session.encode())

    # --- the middleware -------------------------------------------------------------------

    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        client = request.remote or "?"
        sockname = request.transport.get_extra_info("sockname") if request.transport else None
        local = sockname[0] if isinstance(sockname, tuple) and sockname else None
        # An absolute-form target (``GET http://name/path``) names the host too, and aiohttp
        # goes by it: both must be ours.
        absolute = None if request.raw_path.startswith("/") else request.host
        if not (self.host_ok(request.headers.get("Host"), local)
                and (absolute is None or self.host_ok(absolute, local))):
            self.ratelog.warning(client, "host", "web view: refused Host %r from %s (not the "
                                 "bind address or status.allowed_hosts)",
                                 request.headers.get("Host", "")[:100], client)
            raise web.HTTPMisdirectedRequest(
                text="this Host is not served here (status.allowed_hosts)")
        given = _parse_bearer(request)
        if given:  # judged once, here: a wrong one counts whatever the route
            request[_JUDGED] = await self.judge(request, given, request.path[:100])
        if (self.guards_reads and request.path not in OPEN_PATHS
                and not self.holds_token(request)):
            return self._unauthorized(request)
        try:
            return await handler(request)
        except (web.HTTPException, asyncio.CancelledError, ConnectionError):
            raise
        except Exception as err:
            self.ratelog.log(logging.ERROR, "web", f"{request.path}:{type(err).__name__}",
                             "web view: %s %s failed: %s",
                             request.method, request.path[:200], "".join(
                                 traceback.format_exception(err)).rstrip())
            raise web.HTTPInternalServerError(text="internal error (logged)") from None

    def _unauthorized(self, request: web.Request) -> web.Response:
        client = request.remote or "?"
        self.ratelog.info(client, "no token", "web view: %s %s from %s without the token",
                          request.method, request.path[:200], client)
        headers = {"WWW-Authenticate": 'Bearer realm="vgripd"'}
        if request.path == "/" and request.method == "GET":  # a browser: the login form
            return web.Response(status=401, text=LOGIN_PAGE.format(message=LOGIN_ASK),
                                content_type="text/html", headers=headers)
        return web.Response(status=401, headers=headers, text=(
            "this view needs the token: Authorization: Bearer <status.token>, "
            "or log in at /login"))

    # --- login ----------------------------------------------------------------------------

    async def login_form(self, request: web.Request) -> web.Response:
        return web.Response(text=LOGIN_PAGE.format(message=LOGIN_ASK),
                            content_type="text/html", headers={"Cache-Control": "no-store"})

    async def login(self, request: web.Request) -> web.Response:
        """``POST /login`` (form field ``token``): the session cookie and back to the page."""
        given = (await login_form(request)).get("token", "")
        if self._session is None or not given or not await self.judge(request, given,
                                                                        "/login"):
            return web.Response(status=403, text=LOGIN_PAGE.format(message=LOGIN_WRONG),
                                content_type="text/html")
        resp = web.Response(status=303, headers={"Location": "/"})
        resp.set_cookie(SESSION_COOKIE, self._session, httponly=True, samesite="Strict",
                        path="/")
        return resp

    # --- every answer ---------------------------------------------------------------------

    @staticmethod
    async def add_headers(request: web.Request, response: web.StreamResponse) -> None:
        for name, value in SECURITY_HEADERS.items():
            response.headers.setdefault(name, value)


class ServerLogLimit(logging.Filter):
    """Rate-limits what aiohttp's own server logger writes for bad requests (one line per
    client and kind a minute, the traceback left out: a client that sends garbage decides
    nothing about the journal's size)."""

    def __init__(self, ratelog: RateLimitedLog) -> None:
        super().__init__()
        self.ratelog = ratelog

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        args = record.args if isinstance(record.args, tuple) else ()
        client = str(args[0]) if args else "?"
        text = record.getMessage()
        if record.exc_info and record.exc_info[1] is not None:
            err = record.exc_info[1]
            text += f": {type(err).__name__}: {str(err)[:200]}"
        # A client's broken request is no fault of the daemon: a warning at most.
        self.ratelog.log(min(record.levelno, logging.WARNING), client, str(record.msg), "%s",
                         text)
        return False
