"""Who may open a session on the ``opcua`` link, how often a client may fail to, and where
refused client certificates are kept (docs/opcua.md, "Security").

- ``SessionGuard`` is asyncua's message processor with vgripd's rules in front of it: on a
  secure channel whose SecurityPolicy and MessageSecurityMode are not configured (asyncua opens
  a SecurityPolicy None channel whatever the server offers, for GetEndpoints) only endpoint
  discovery is served; anything else, CreateSession and ActivateSession included, is answered
  ``BadSecurityPolicyRejected`` and the connection closed. A password sent in clear on a
  channel that does not encrypt is refused ``BadIdentityTokenRejected`` when the server could
  have had it encrypted. A session moves to another connection only with its client
  certificate. A connection holds one session: a second CreateSession closes the first
  (asyncua would keep both, and a watchdog task for each). RegisterServer(2) is refused (vgripd
  is no discovery server). A refused session request is answered without asyncua's ERROR
  lines: one rate-limited WARNING of ours.
- ``LoginThrottle`` (``vgripd.service.links.throttle``, shared with the web view) slows failed
  logins per client address and locks an address out after ``login_failures`` failures in a
  row.
- ``RejectedStore`` keeps refused client certificates, one file per thumbprint, the oldest
  removed beyond ``rejected_max_files`` files or ``REJECTED_MAX_BYTES``.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import logging
import os
import time
import weakref
from collections import Counter
from pathlib import Path
from typing import Any, Protocol

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.security_policies import SECURITY_POLICY_TYPE_MAP
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary

from vgripd.service.links.throttle import LoginThrottle

log = logging.getLogger(__name__)


class GuardedLink(Protocol):
    """What the guard reads of the ``opcua`` link (kept here, not imported, so the two
    modules form no import circle)."""

    options: Any
    faults: Counter[str]
    throttle: LoginThrottle
    channels: frozenset[tuple[str, int]]
    can_encrypt: bool
    session_certs: Any

    def fault(self, client: str, kind: str, level: int, msg: str, *args: Any) -> None: ...

#: What a channel that may not carry a session still serves: endpoint discovery.
DISCOVERY = frozenset(ua.NodeId(ua.Int32(i)) for i in (
    ua.ObjectIds.GetEndpointsRequest_Encoding_DefaultBinary,
    ua.ObjectIds.FindServersRequest_Encoding_DefaultBinary,
    ua.ObjectIds.CloseSecureChannelRequest_Encoding_DefaultBinary,
))
#: Services a discovery server offers and vgripd refuses on every channel.
REFUSED = frozenset(ua.NodeId(ua.Int32(i)) for i in (
    ua.ObjectIds.RegisterServerRequest_Encoding_DefaultBinary,
    ua.ObjectIds.RegisterServer2Request_Encoding_DefaultBinary,
))
#: Requests asyncua serves without an activated session.
SESSIONLESS = DISCOVERY | REFUSED | frozenset(ua.NodeId(ua.Int32(i)) for i in (
    ua.ObjectIds.CreateSessionRequest_Encoding_DefaultBinary,
    ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary,
    ua.ObjectIds.CloseSessionRequest_Encoding_DefaultBinary,
))
CREATE_SESSION = ua.NodeId(ua.Int32(ua.ObjectIds.CreateSessionRequest_Encoding_DefaultBinary))
ACTIVATE_SESSION = ua.NodeId(
    ua.Int32(ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary))
#: Refusals of an ActivateSession that count as a failed login (a guess at a user or password,
#: or an identity the server does not accept).
LOGIN_FAILURES = frozenset({
    ua.StatusCodes.BadUserAccessDenied, ua.StatusCodes.BadIdentityTokenRejected,
    ua.StatusCodes.BadIdentityTokenInvalid, ua.StatusCodes.BadSessionIdInvalid,
    ua.StatusCodes.BadSecurityChecksFailed,
})
#: Bytes the rejected-certificate store may hold (besides its file count).
REJECTED_MAX_BYTES = 4 * 1024 * 1024

_QUIET: contextvars.ContextVar[bool] = contextvars.ContextVar("vgripd_opcua_quiet",
                                                              default=False)
#: asyncua's loggers that speak while a session request is refused.
_MUTED_LOGGERS = ("asyncua.server.uaprocessor", "asyncua.server.internal_session",
                  "asyncua.server.internal_server")


class _Mute(logging.Filter):
    """Drops asyncua's records while ``SessionGuard`` refuses a session request in this task
    (its own line says why); every other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not _QUIET.get()


def mute_asyncua_refusals() -> None:
    """Install ``_Mute`` on asyncua's server loggers (idempotent)."""
    for name in _MUTED_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, _Mute) for f in logger.filters):
            logger.addFilter(_Mute())


def allowed_channels(policy_types: list[ua.SecurityPolicyType]) -> frozenset[tuple[str, int]]:
    """``(SecurityPolicyUri, MessageSecurityMode)`` of the configured policies."""
    found = set()
    for kind in policy_types:
        policy, mode, _level = SECURITY_POLICY_TYPE_MAP[kind]
        assert isinstance(mode, ua.MessageSecurityMode)
        found.add((str(getattr(policy, "URI", "")), int(mode)))
    return frozenset(found)


def _request_name(typeid: ua.NodeId) -> str:
    """``CreateSession`` for the CreateSessionRequest's encoding id."""
    ident = typeid.Identifier
    name = ua.ObjectIdNames.get(ident, str(ident)) if isinstance(ident, int) else str(ident)
    return str(name).removesuffix("Request_Encoding_DefaultBinary")


def status_name(code: int) -> str:
    return str(ua.StatusCode(ua.UInt32(code)).name)


# -- failed logins ----------------------------------------------------------------------------


# -- refused certificates ---------------------------------------------------------------------


class RejectedStore:
    """Refused client certificates in ``folder``, named by thumbprint (a certificate refused
    again only refreshes its file's time), at most ``max_files`` files and
    ``max_bytes`` bytes: the least recently refused go first."""

    def __init__(self, folder: Path, max_files: int, max_bytes: int = REJECTED_MAX_BYTES) -> None:
        self.folder = folder
        self.max_files = max_files
        self.max_bytes = max_bytes

    def keep(self, der: bytes, thumbprint: str) -> Path | None:
        """Store ``der``; its path, or None when nothing is kept (no room at all, or the
        folder cannot be written: the refusal is what matters, not the copy)."""
        if self.max_files <= 0 or len(der) > self.max_bytes:
            return None
        path = self.folder / f"{thumbprint}.der"
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            files = self._files()
            if path.name not in {name for _, name, _ in files}:
                tmp = path.with_suffix(".tmp")
                tmp.write_bytes(der)
                tmp.replace(path)
            # newest of all, even on a file system with coarse timestamps
            newest = max((mtime for mtime, _, _ in files), default=0)
            stamp = max(time.time_ns(), newest + 1)
            os.utime(path, ns=(stamp, stamp))
            self._prune([f for f in files if f[1] != path.name], len(der))
        except OSError:
            return None
        return path

    def _files(self) -> list[tuple[int, str, int]]:
        """(mtime ns, name, size) of the kept certificates, oldest first."""
        files = []
        for entry in os.scandir(self.folder):
            if entry.name.endswith(".der") and entry.is_file(follow_symlinks=False):
                st = entry.stat(follow_symlinks=False)
                files.append((st.st_mtime_ns, entry.name, st.st_size))
        return sorted(files)

    def _prune(self, others: list[tuple[int, str, int]], size: int) -> None:
        """Remove the oldest of ``others`` until they and the newest file (``size`` bytes)
        fit."""
        total = size + sum(s for *_, s in others)
        count = len(others) + 1
        for _mtime, name, old_size in others:
            if count <= self.max_files and total <= self.max_bytes:
                break
            with contextlib.suppress(FileNotFoundError):
                (self.folder / name).unlink()
            count -= 1
            total -= old_size


# -- the message processor --------------------------------------------------------------------


class SessionCerts(weakref.WeakKeyDictionary[Any, "bytes | None"]):
    """The client certificate each session was created with (``SessionGuard``), by session:
    every session the link's server created that is still alive."""

    async def end(self, link: str) -> None:
        """Close each session still open, after the server stopped: asyncua's ``stop`` closes
        only its own internal session, and keeps one whose client went away while it had
        subscriptions for the client to take over (OPC UA Part 4, 6.7); that session's timeout
        watch and its subscriptions' publish loops would outlive the link by its timeout."""
        for session in list(self):
            try:
                async with asyncio.timeout(5.0):
                    await session.close_session(True)
            except Exception as err:  # closing goes on; say why once
                log.warning("%s: closing an OPC UA session: %r", link, err)
        self.clear()


class SessionGuard(UaProcessor):
    """asyncua's processor for one connection, with the link's channel, login and logging
    rules in front of it (module docstring)."""

    def __init__(self, link: GuardedLink, host: str, client: str, *args: Any) -> None:
        super().__init__(*args)
        self.link = link
        self.host = host
        self.client = client

    def _channel_allowed(self) -> bool:
        policy = self._connection.security_policy
        return (str(policy.URI), int(policy.Mode)) in self.link.channels

    def _fault(self, requesthdr: Any, seqhdr: Any, code: int) -> None:
        response = ua.ServiceFault()
        response.ResponseHeader.ServiceResult = ua.StatusCode(ua.UInt32(code))
        self.send_response(requesthdr.RequestHandle, seqhdr, response)

    async def _process_message(self, typeid: Any, requesthdr: Any, seqhdr: Any,
                               body: Any) -> bool:
        if typeid in REFUSED:
            self._fault(requesthdr, seqhdr, ua.StatusCodes.BadServiceUnsupported)
            return True
        if not self._channel_allowed() and typeid not in DISCOVERY:
            policy = self._connection.security_policy
            mode = ua.MessageSecurityMode(policy.Mode).name.rstrip("_")
            what = {CREATE_SESSION: "CreateSession",
                    ACTIVATE_SESSION: "ActivateSession"}.get(typeid, "a session service")
            self.link.fault(self.host, "insecure", logging.WARNING,
                            "%s: %s on a channel with SecurityPolicy %s, mode %s refused "
                            "(BadSecurityPolicyRejected; only endpoint discovery is served "
                            "there), connection closed", self.client, what,
                            str(policy.URI).rsplit("#", 1)[-1], mode)
            self._fault(requesthdr, seqhdr, ua.StatusCodes.BadSecurityPolicyRejected)
            return False
        if typeid == ACTIVATE_SESSION:
            return await self._activate(typeid, requesthdr, seqhdr, body)
        if typeid not in SESSIONLESS and (self.session is None
                                          or not self.session.is_activated()):
            code = (ua.StatusCodes.BadSessionIdInvalid if self.session is None
                    else ua.StatusCodes.BadSessionNotActivated)
            self.link.fault(self.host, "session", logging.WARNING, "%s: %s refused (%s)",
                            self.client, _request_name(typeid), status_name(code))
            self._fault(requesthdr, seqhdr, code)
            return True
        if typeid == CREATE_SESSION and self.session is not None:
            await self._drop_session()
        token = _QUIET.set(typeid == CREATE_SESSION)
        try:
            ok = await super()._process_message(typeid, requesthdr, seqhdr, body)
        except (ServiceError, ua.UaStatusCodeError) as err:
            # a client's mistake: our one line (per client and interval), not asyncua's ERROR
            self.link.fault(self.host, "service", logging.WARNING, "%s: %s refused (%s)",
                            self.client, _request_name(typeid), status_name(err.code))
            self._fault(requesthdr, seqhdr, err.code)
            return True
        finally:
            _QUIET.reset(token)
        if typeid == CREATE_SESSION:
            self.remember_certificate()
        return ok

    async def _activate(self, typeid: Any, requesthdr: Any, seqhdr: Any, body: Any) -> bool:
        throttle = self.link.throttle
        if throttle.locked(self.host, time.monotonic()):
            self.link.faults["locked"] += 1
            self._fault(requesthdr, seqhdr, ua.StatusCodes.BadRequestNotAllowed)
            return True
        user, code, why = self._judge(requesthdr, body)
        if not code:
            token = _QUIET.set(True)
            try:
                ok = await super()._process_message(typeid, requesthdr, seqhdr, body)
            except (ServiceError, ua.UaStatusCodeError) as err:
                code = err.code
            except Exception as err:  # e.g. a ClientSignature that does not verify
                code = ua.StatusCodes.BadSecurityChecksFailed
                why = f"{type(err).__name__}: {err}"
            else:
                if self.session is not None and self.session.is_activated():
                    throttle.succeeded(self.host)
                return ok
            finally:
                _QUIET.reset(token)
        if code in LOGIN_FAILURES:
            await self._failed_login(user, code, why)
        else:
            self.link.fault(self.host, "session", logging.WARNING,
                            "%s: ActivateSession as %r refused (%s%s)", self.client, user,
                            status_name(code), f": {why}" if why else "")
        self._fault(requesthdr, seqhdr, code)
        return True

    def _judge(self, requesthdr: Any, body: Any) -> tuple[str, int, str]:
        """The login's user name ("anonymous" for none), and the status to refuse it with
        before asyncua sees it (0: pass it on) and why."""
        try:
            params = struct_from_binary(ua.ActivateSessionParameters, body.copy())
        except Exception:
            return "?", ua.StatusCodes.BadDecodingError, "undecodable request"
        if self.session is None:
            # A session created on another connection (asyncua lets a client take its
            # session over to a new channel): only with the certificate it was created with.
            existing = self.iserver.lookup_external_session(requesthdr.AuthenticationToken)
            mine = self._connection.security_policy.peer_certificate
            if existing is not None and self.link.session_certs.get(existing) != mine:
                return "?", ua.StatusCodes.BadSecurityChecksFailed, \
                    "a session created on another channel with another certificate"
        token = params.UserIdentityToken
        if isinstance(token, ua.UserNameIdentityToken):
            user = str(token.UserName)
            encrypted = int(self._connection.security_policy.Mode) == int(
                ua.MessageSecurityMode.SignAndEncrypt)
            if not token.EncryptionAlgorithm and not encrypted and self.link.can_encrypt:
                return user, ua.StatusCodes.BadIdentityTokenRejected, \
                    "password in clear on a channel that does not encrypt"
            return user, 0, ""
        if isinstance(token, ua.X509IdentityToken):
            return "certificate", 0, ""
        return "anonymous", 0, ""

    async def _drop_session(self) -> None:
        """A second CreateSession on this connection: asyncua keeps one session per
        connection and would leave the previous one registered and its watchdog task running
        (one more of each per request, without bound); close them first."""
        task, self._session_watchdog_task = self._session_watchdog_task, None
        if task is not None and not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        session, self.session = self.session, None
        if session is not None:
            self.link.session_certs.pop(session, None)
            await session.close_session(True)

    def remember_certificate(self) -> None:
        """After CreateSession: the session belongs to this channel's client certificate."""
        if self.session is not None:
            self.link.session_certs[self.session] = \
                self._connection.security_policy.peer_certificate

    async def _failed_login(self, user: str, code: int, why: str) -> None:
        """Count and log a failed login; hold the answer back as the throttle says."""
        link = self.link
        delay, locked = link.throttle.failed(self.host, time.monotonic())
        o = link.options
        if locked:
            link.faults["login"] += 1
            link.fault(self.host, "lockout", logging.WARNING,
                       "client %s: %d failed logins in a row (the last as %r): its logins "
                       "are refused for %g s (login_lockout_s)", self.host, o.login_failures,
                       user, o.login_lockout_s)
        else:
            link.fault(self.host, "login", logging.WARNING, "%s: login as %r refused (%s%s)",
                       self.client, user, status_name(code), f": {why}" if why else "")
        if delay > 0:
            await asyncio.sleep(delay)
