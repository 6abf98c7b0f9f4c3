"""OPC UA server link: vgripd serves a vision system after OPC 40100 (Machine Vision).

An asyncua ``Server`` runs on the daemon's own loop. A client (a PLC's OPC UA client, a robot,
a cell computer) calls ``VisionSystem.StartSingleJob`` and gets a ``RequestId``; the daemon
runs the job; ``Result.*`` variables and a ``ResultReadyEventType`` event carry the outcome.
The address space is ``drivers/links/opcua_space.py``; docs/opcua.md has it in full, the job
sequence a client follows, the security set-up and what of OPC 40100 is implemented.

Semantics follow the register handshake (``vgripd.peer.jobcore.Handshake``, whose plans the
space's writes carry out): one job at a time per link; a start while this link's
job runs is refused at once with ``BadInvalidState`` (the state machine is in SingleExecution)
and counted as ``BUSY`` in ``refusals()``; a recipe that is not configured (the daemon tells the
link its recipes, ``set_recipes``) or a wrong argument list is refused ``BadInvalidArgument`` /
``BadArgumentsMissing`` / ``BadTooManyArguments`` and counted ``BAD_REQUEST``; the selected
recipe stays what it was. A start the daemon refuses (another link's job runs, shutdown) is
answered as a result, with status BUSY or ABORTED and ``JobId`` 0, as the Modbus links answer
it. Results are written data first, ``Result.RequestId`` (retracted to 0 when a job starts) and
``Result.Sequence`` last; one Read request is answered without interleaving with a publish.

Pick lists: ``VisionSystem.Next`` asks for the next object of the last job's list, answered by
the daemon from that list (no image, the job's id) through the same publish, with
``Result.Count``/``Index``/``PickId``/``Score`` saying where the list stands. While the link
holds no list (nothing published yet, or the last result had none) the call fails
``BadNoData`` and is counted ``BAD_REQUEST``; while its own job runs ``BadInvalidState``
(``BUSY``), as the register handshake refuses them.

Security (``security``): endpoints exist only for the listed modes; ``"None"`` only when it is
listed. Signing modes need the server certificate, generated self-signed into
``certificate_dir`` at the first start. Users (``users``) log in with a password read from a
file or an environment variable at ``open``, never from the TOML; anonymous sessions only with
``allow_anonymous = true``. A session is created and activated only on a secure channel whose
policy and mode are listed (a SecurityPolicy None channel serves endpoint discovery only unless
``"None"`` is listed); failed logins are slowed and locked out per client address; refused
client certificates are kept, bounded, in ``certificate_dir/rejected`` (``opcua_guard``).

Connections go through the daemon's one connection manager (``vgripd.service.links.gate``) at
accept: addresses outside ``allow`` are closed at once; beyond ``max_connections`` (which the
daemon's file budget may lower) a newcomer evicts the oldest connection that has not activated a
session, and is refused when every connection has one.

Faults are the peer's, never the daemon's: a connection whose first bytes are not an OPC UA
Hello is closed, as is one that opens no session within ``activation_timeout_s`` or stays
silent beyond its session timeout (at most ``max_session_timeout_s``), or one whose messages
asyncua cannot process. Each is one log line per client and kind per ``log_interval_s``
(``RateLimitedLog``), without a traceback; asyncua's own warnings are routed the same way
unless the ``asyncua`` logger is configured explicitly. The server keeps serving.
"""

from __future__ import annotations

import asyncio
import datetime
import hmac
import logging
import os
import socket
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

try:
    from asyncua import Server, ua
    from asyncua.crypto.permission_rules import User, UserRole
    from asyncua.crypto.truststore import TrustStore
    from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
    from asyncua.server.internal_session import SessionState
    from asyncua.server.user_managers import UserManager
    from cryptography.hazmat.primitives import hashes  # an asyncua dependency
except ImportError as err:  # the registry turns this into the one-line DriverError
    raise ImportError(f"{err}; the opcua link needs asyncua: pip install 'vgripd[opcua]'") from None

from drivers.links.opcua_belt import count_argument
from drivers.links.opcua_guard import (
    LoginThrottle,
    RejectedStore,
    SessionCerts,
    SessionGuard,
    allowed_channels,
    mute_asyncua_refusals,
)
from drivers.links.opcua_space import Space, collector_paused, ensure_certificate, result_values
from drivers.links.opcua_vision import JobInfo, VisionSpace
from vgripd.config import AllowList
from vgripd.errors import LinkError
from vgripd.peer.jobcore import Command, Part, Step
from vgripd.peer.registers import checked_warnings
from vgripd.peer.visionsm import Verdict, VisionMachine
from vgripd.registry import OPCUA_CAPABILITIES
from vgripd.service.links.gate import Gate
from vgripd.service.links.protocol import LinkHealth, LinkState, Trigger, TriggerHandler
from vgripd.service.links.ratelog import RateLimitedLog
from vgripd.service.links.supervisor import SupervisedLink
from vgripd.types import JobResult, Status

log = logging.getLogger(__name__)

SECURITY_MODES = {
    "None": ua.SecurityPolicyType.NoSecurity,
    "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
    "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
}
SecurityMode = Literal["None", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt"]
#: "MachineVision": OPC 40100 on the official NodeSet; "vgripd": the older own namespace
#: (``namespace_uri``), deprecated, served for one more version
Model = Literal["MachineVision", "vgripd"]
WILDCARD_HOSTS = ("", "0.0.0.0", "::")
HELLO = b"HEL"  # every OPC UA TCP connection starts with a Hello message
CLOSE_TIMEOUT_S = 5.0
#: asyncua lines the link replaces with its own (per client, with the reason)
_REPLACED = frozenset({
    "Session timed out after %ss of inactivity",
    "Closing idle connection from %s: no ActivateSession within %.1fs",
    "Endpoints other than open requested but private key and certificate are not set.",
    "Refusing connection from %s: at max_connections=%s",
    "Not trusted certificate used: [CN=%s]",
})


class OpcUaUser(BaseModel):
    """One login: ``name`` and where its password is: ``password_file`` (first line, trailing
    newline stripped) or ``password_env`` (an environment variable's name)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, max_length=128)
    password_file: Path | None = None
    password_env: str | None = Field(None, min_length=1)

    @model_validator(mode="after")
    def _one_source(self) -> OpcUaUser:
        if (self.password_file is None) == (self.password_env is None):
            raise ValueError(f"user {self.name!r}: give exactly one of password_file and "
                             "password_env (passwords are never written in the TOML)")
        return self


def _both_models() -> list[Model]:
    return ["MachineVision", "vgripd"]


def _encrypted_only() -> list[SecurityMode]:
    return ["Basic256Sha256_SignAndEncrypt"]


class OpcUaOptions(BaseModel):
    """Options of ``type = "opcua"`` (docs/opcua.md, "Options")."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = "0.0.0.0"
    port: int = Field(4840, ge=0, le=65535)  # 0 = any free port (tests)
    path: str = "/vgripd"  # endpoint URL: opc.tcp://HOST:PORT/PATH
    security: list[SecurityMode] = Field(default_factory=_encrypted_only, min_length=1)
    certificate_dir: Path | None = Field(None, validate_default=True)
    certificate_days: int = Field(3650, ge=1, le=36500)
    trusted_clients_dir: Path | None = None
    allow_anonymous: bool = False
    users: list[OpcUaUser] = Field(default_factory=list, validate_default=True)
    namespace_uri: str = Field("urn:vgripd:machine-vision", min_length=1)
    models: list[Model] = Field(default_factory=_both_models, min_length=1)
    max_connections: int = Field(8, ge=1, le=256)
    activation_timeout_s: float = Field(10.0, ge=0.1, le=600.0)
    max_session_timeout_s: float = Field(60.0, ge=1.0, le=3600.0)
    log_interval_s: float = Field(60.0, ge=0.1, le=3600.0)
    allow: AllowList = None  # client addresses/networks accepted (unset: any)
    login_failures: int = Field(10, ge=1, le=1000)
    login_rate_per_s: float = Field(10.0, gt=0.0, le=1000.0)
    login_lockout_s: float = Field(60.0, ge=0.0, le=86400.0)
    rejected_max_files: int = Field(64, ge=0, le=10000)

    @field_validator("security", "models")
    @classmethod
    def _unique(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError("each may be listed once")
        return value

    @field_validator("path")
    @classmethod
    def _path(cls, value: str) -> str:
        if not value.startswith("/") or any(c.isspace() for c in value):
            raise ValueError("must start with / and contain no spaces (e.g. \"/vgripd\")")
        return value

    @field_validator("certificate_dir")
    @classmethod
    def _certificate_needed(cls, value: Path | None, info: ValidationInfo) -> Path | None:
        signed = [m for m in info.data.get("security", []) if m != "None"]
        if signed and value is None:
            raise ValueError(
                f"needed for security {signed[0]!r} (the server certificate is generated "
                "there at the first start); or set security = [\"None\"]")
        return value

    @field_validator("trusted_clients_dir")
    @classmethod
    def _trust_needs_signing(cls, value: Path | None, info: ValidationInfo) -> Path | None:
        if value is not None and "None" in info.data.get("security", ["None"]):
            raise ValueError("a client trust list needs every endpoint signed: with \"None\" "
                             "in security any client connects without a certificate")
        return value

    @field_validator("users")
    @classmethod
    def _someone(cls, value: list[OpcUaUser], info: ValidationInfo) -> list[OpcUaUser]:
        if not value and not info.data.get("allow_anonymous"):
            raise ValueError("give at least one user (name and password_file or "
                             "password_env), or set allow_anonymous = true")
        names = [u.name for u in value]
        if len(set(names)) != len(names):
            raise ValueError("each name may be listed once")
        return value


class _Users(UserManager):
    """Password check (constant time) and, when allowed, anonymous sessions. A user that is
    refused gets ``BadUserAccessDenied`` from asyncua; ``SessionGuard`` counts and logs it."""

    def __init__(self, passwords: dict[str, bytes], anonymous: bool) -> None:
        self.passwords = passwords
        self.anonymous = anonymous

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None:
            return User(role=UserRole.User, name="anonymous") if self.anonymous else None
        expected = self.passwords.get(username)
        given = (password or "").encode() if isinstance(password, str) else (password or b"")
        if expected is not None and hmac.compare_digest(expected, given):
            return User(role=UserRole.User, name=username)
        return None


class _Protocol(OPCUAProtocol):
    """asyncua's connection with vgripd's checks: Hello first, bounded silence, no crash on
    garbage. ``reason`` is set when the link closed it (already logged)."""

    def __init__(self, link: OpcUaLink, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.link = link
        self.host = "?"
        self.client = "?"
        self.opened = time.monotonic()
        self.last_data = self.opened
        self.first = b""
        self.reason = ""
        self.cert_checked = False
        self.activated = False  # a session was activated on it: the gate never evicts it

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        peer = transport.get_extra_info("peername")
        if isinstance(peer, tuple) and len(peer) >= 2:
            self.host, self.client = str(peer[0]), f"{peer[0]}:{peer[1]}"
        if not self.link.gate.admit(self):  # not allowed, or full of activated sessions
            self.reason = "refused at accept"
            transport.close()  # nothing written yet: closes at once
            return
        super().connection_made(transport)
        if self.transport is None:  # refused: max_connections
            self.link.fault(self.host, "refused", logging.WARNING,
                            "%s refused: %d connections open (max_connections)", self.client,
                            self.link.options.max_connections)
            return
        self.processor = SessionGuard(self.link, self.host, self.client, self.iserver,
                                      self.transport, self.limits)
        self.processor.set_policies(self.policies)
        self.link._admit(self)

    def data_received(self, data: bytes) -> None:
        if self.reason:
            return
        self.last_data = time.monotonic()
        if len(self.first) < len(HELLO):
            self.first += data[:len(HELLO) - len(self.first)]
            if not HELLO.startswith(self.first):
                self.drop("garbage", f"not OPC UA (first bytes {self.first!r}, expected a "
                          "Hello)")
                return
        super().data_received(data)

    async def _process_one_msg(self, header: Any, buf: Any) -> bool:
        try:
            ok = await super()._process_one_msg(header, buf)
        except Exception as err:
            self.drop("protocol", f"message not understood ({type(err).__name__}: {err})")
            return False
        if ok and not self.activated and self.session_timeout_s() is not None:
            self.activated = True
            self.link.gate.activity(self, valid=True)
        if ok and not self.cert_checked and self.processor is not None:
            # The secure channel's own client certificate, judged as soon as the channel is
            # open (not only the one a client chooses to repeat in CreateSession).
            der = getattr(self.processor._connection.security_policy, "peer_certificate", None)
            if der:
                self.cert_checked = True
                why = self.link._untrusted(der)
                if why:
                    self.drop("untrusted", why)
                    return False
        return ok

    def connection_lost(self, ex: BaseException | None) -> None:
        super().connection_lost(ex)
        self.link._forget(self, ex)

    def session_timeout_s(self) -> float | None:
        """The timeout of the session this connection activated (it may be closed since:
        asyncua closes a timed-out session but not its socket); None before activation."""
        session = self.processor.session if self.processor is not None else None
        if session is None or session.state == SessionState.Created:
            return None
        timeout_s: float | None = session.session_timeout
        return timeout_s

    def shut(self, reason: str) -> None:
        """Closed by the gate (evicted; already logged)."""
        if self.reason or self.transport is None:
            return
        self.reason = reason
        self.transport.abort()

    def drop(self, kind: str, why: str) -> None:
        """Close the connection for a fault of the peer: one line, no traceback."""
        if self.reason or self.transport is None:
            return
        self.reason = why
        self.link.fault(self.host, kind, logging.WARNING, "%s: %s, connection closed",
                        self.client, why)
        self.transport.abort()


class _BinaryServer(BinaryServer):
    def __init__(self, link: OpcUaLink, *args: Any) -> None:
        super().__init__(*args)
        self.link = link

    def _make_protocol(self) -> OPCUAProtocol:
        return _Protocol(self.link, iserver=self.iserver, policies=self._policies,
                         clients=self.clients, closing_tasks=self.closing_tasks,
                         limits=self.limits)

    async def start(self) -> None:
        """asyncua's ``start`` with the gate's accept backlog (counted in the file budget)."""
        self._server = await asyncio.get_running_loop().create_server(
            self._make_protocol, self.hostname, self.port, backlog=self.link.gate.backlog)
        if self.port == 0 and len(self._server.sockets) == 1:
            self.hostname, self.port = self._server.sockets[0].getsockname()[:2]
        self.cleanup_task = asyncio.create_task(self._close_task_loop())


class _Server(Server):
    """``Server.start`` with vgripd's connection class (the rest is asyncua's own)."""

    def __init__(self, link: OpcUaLink, user_manager: UserManager) -> None:
        super().__init__(user_manager=user_manager)
        self.link = link

    async def start(self) -> None:
        await self._setup_server_nodes()
        await self.iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = _BinaryServer(self.link, self.iserver, host, port, self.limits)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except BaseException:
            await self.iserver.stop()
            raise


class _AsyncuaLines(logging.Handler):
    """asyncua's warnings and errors as one rate-limited line each, without tracebacks."""

    def __init__(self, lines: RateLimitedLog) -> None:
        super().__init__(logging.WARNING)
        self.lines = lines

    def emit(self, record: logging.LogRecord) -> None:
        if record.msg in _REPLACED:
            return
        try:
            text = record.getMessage().splitlines()[0] if record.getMessage() else ""
        except Exception:
            text = str(record.msg)
        if record.exc_info and record.exc_info[1] is not None:
            text += f": {type(record.exc_info[1]).__name__}: {record.exc_info[1]}"
        self.lines.log(record.levelno, "asyncua", str(record.msg)[:80], "opcua server: %s", text)


_ASYNCUA_LINES = RateLimitedLog(log, 60.0)


def route_asyncua_logs() -> None:
    """Unless the ``asyncua`` logger was configured (a level or a handler of its own), its
    WARNING and worse go through ``_AsyncuaLines`` and nothing else (no INFO chatter, no
    tracebacks). Idempotent."""
    logger = logging.getLogger("asyncua")
    if any(isinstance(h, _AsyncuaLines) for h in logger.handlers):
        return
    if logger.level != logging.NOTSET or logger.handlers:
        return
    logger.setLevel(logging.WARNING)
    logger.addHandler(_AsyncuaLines(_ASYNCUA_LINES))
    logger.propagate = False


def _version() -> str:
    """vgripd's version for the server's BuildInfo."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("vgripd")
    except PackageNotFoundError:
        return "unknown"


def read_passwords(options: OpcUaOptions) -> dict[str, bytes]:
    """Each user's password from its file or environment variable; ``LinkError`` naming
    the field when it is missing or empty."""
    passwords: dict[str, bytes] = {}
    for i, user in enumerate(options.users):
        where = f"users[{i}] ({user.name!r})"
        if user.password_env is not None:
            value = os.environ.get(user.password_env)
            if not value:
                raise LinkError(f"{where}.password_env: environment variable "
                                f"{user.password_env} is not set or empty")
            passwords[user.name] = value.encode()
            continue
        assert user.password_file is not None
        try:
            text = user.password_file.read_text().splitlines()
        except OSError as err:
            raise LinkError(f"{where}.password_file: cannot read {user.password_file}: "
                            f"{err.strerror or err}") from None
        if not text or not text[0]:
            raise LinkError(f"{where}.password_file: {user.password_file} is empty")
        passwords[user.name] = text[0].encode()
    return passwords


def untrusted(trust: TrustStore | None, rejected: RejectedStore, der: bytes) -> str:
    """Why the client certificate ``der`` is refused ("" when it is trusted, or when no
    trust list is configured). A refused certificate is kept in
    ``certificate_dir/rejected`` (``RejectedStore``: bounded, one file per thumbprint) for
    the integrator to move into the trust list."""
    if trust is None:
        return ""
    from cryptography import x509

    try:
        cert = x509.load_der_x509_certificate(der)
    except ValueError as err:
        return f"client certificate unreadable ({err})"
    now = datetime.datetime.now(datetime.UTC)
    names = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
    name = str(names[0].value) if names else "?"
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        why = "expired or not yet valid"
    elif trust.is_trusted(cert):
        return ""
    else:
        why = "not in trusted_clients_dir"
    path = rejected.keep(der, cert.fingerprint(hashes.SHA256()).hex()[:16])
    kept = f"; kept as {path}" if path is not None else ""
    return f"client certificate CN={name} refused: {why}{kept}"


def exposure_warnings(options: OpcUaOptions) -> list[tuple[str, str, str]]:
    """``vgripd check``'s warnings about what these options open to the cell network:
    ``(level, field, message)``."""
    found = []
    if "None" in options.security:
        who = ", ".join([f"user {u.name}" for u in options.users]
                        + (["anonymous"] if options.allow_anonymous else []))
        found.append(("WARNING", "security", "\"None\" is listed: any client on the "
                      "network opens a session without a certificate, unsigned and "
                      f"unencrypted, as {who}"
                      + (" (passwords travel in clear)" if options.users and
                         options.security == ["None"] else "")))
    elif options.allow_anonymous and options.trusted_clients_dir is None:
        found.append(("WARNING", "allow_anonymous", "anonymous sessions without "
                      "trusted_clients_dir: any client with a certificate it made itself "
                      "opens a session"))
    return found


def render_plan(plan: Sequence[Step], parts: tuple[Part, ...]) -> None:
    """Check that the space's writes that follow carry out the handshake's ``plan``: the
    ``parts`` they write, in this order (the others are not OPC UA variables). A change of the
    rules in ``jobcore`` that these writes do not follow fails here rather than reaching a
    client."""
    carried = tuple(step.part for step in plan if step.part in parts)
    if carried != tuple(p for p in parts if p in carried) or (
            Part.ACK in parts and plan[-1].part is not Part.ACK):
        raise LinkError(f"OPC UA writes {parts} do not carry out the handshake's "
                        f"{tuple(step.part for step in plan)}")


@dataclass
class _Job:
    request_id: int
    recipe: int
    command: Command = Command.TRIGGER


class OpcUaLink(SupervisedLink):
    Options = OpcUaOptions
    capabilities = OPCUA_CAPABILITIES
    listens = True  # `vgripd check` tries its host and port
    options: OpcUaOptions

    def __init__(self, name: str, options: OpcUaOptions) -> None:
        super().__init__(name, options, f"{options.host}:{options.port}")
        self.server: _Server | None = None
        self.space: Space | None = None  # the older namespace ("vgripd" in models)
        self.vision: VisionSpace | None = None  # OPC 40100 ("MachineVision" in models)
        self._on_trigger: TriggerHandler | None = None
        self._job: _Job | None = None
        self._next_request = 0
        self._recipe = 0
        #: OPC 40100's state machines over the request/answer rules (its ``handshake``: busy,
        #: the pick list Next may follow, the write order), shared by both namespaces.
        self.machine = VisionMachine()
        self._config_id: tuple[str, bytes] = ("vgripd", b"")
        #: The configured recipes (``set_recipes``); None: not told, every number is taken
        #: and the daemon judges it at the job.
        self._recipes: dict[int, str] | None = None
        self._warnings = 0
        self._conveyor = False  # a recipe has a conveyor (``set_conveyor``)
        self._refusals: Counter[str] = Counter()
        #: peer faults by kind (garbage, protocol, silent, login, lockout, locked, insecure,
        #: session, untrusted, refused)
        self.faults: Counter[str] = Counter()
        self.throttle = LoginThrottle(options.login_failures, options.login_rate_per_s,
                                      options.login_lockout_s)
        #: (SecurityPolicyUri, MessageSecurityMode) a session may be activated on
        self.channels = allowed_channels([SECURITY_MODES[m] for m in options.security])
        #: a password can travel encrypted (a signed mode is configured: the server has a key)
        self.can_encrypt = any(m != "None" for m in options.security)
        #: the client certificate each session was created with (SessionGuard)
        self.session_certs = SessionCerts()
        self.rejected = RejectedStore(
            (options.certificate_dir or Path(".")) / "rejected", options.rejected_max_files
            if options.certificate_dir is not None else 0)
        self.lines = RateLimitedLog(log, options.log_interval_s)
        #: the connections (in order of arrival), their cap, eviction, allow
        self.gate = Gate(name, options.max_connections, allow=options.allow, lines=self.lines,
                         faults=self.faults)
        self._watch_task: asyncio.Task[None] | None = None
        self._where = f"{options.host}:{options.port}"
        self.certificate: Path | None = None  # the server certificate in use
        self._trust: TrustStore | None = None  # trusted_clients_dir, loaded at open

    # -- RobotLink ---------------------------------------------------------------------------

    async def open(self, on_trigger: TriggerHandler) -> None:
        if self.server is not None:
            raise LinkError(f"link {self.name}: already open")
        self._on_trigger = on_trigger
        route_asyncua_logs()
        mute_asyncua_refusals()
        o = self.options
        try:
            with collector_paused():
                server = await self._make_server(read_passwords(o))
        except LinkError as err:
            self.space = self.vision = None
            self.cell.set(LinkState.FAILED, str(err))
            raise LinkError(f"link {self.name}: {err}") from None
        try:
            await server.start()
        except OSError as err:
            self.space = self.vision = None
            reason = os.strerror(err.errno) if err.errno else str(err)
            error = (f"cannot listen on {o.host}:{o.port}: {reason} (check host and port of "
                     f"this [[links]] entry)")
            self.cell.set(LinkState.FAILED, error)
            raise LinkError(f"link {self.name}: {error}") from None
        self.server = server
        self._where = f"{o.host}:{self.port}"
        self._watch_task = asyncio.create_task(self._watch(), name=f"{self.name}-watch")
        self.cell.set(LinkState.UP)
        logins = [f"user {u.name}" for u in o.users] + (["anonymous"] if o.allow_anonymous else [])
        log.info("%s: OPC UA server on %s (security %s; %s)", self.name, self.endpoint_url,
                 ", ".join(o.security), ", ".join(logins))

    async def close(self) -> None:
        task, self._watch_task = self._watch_task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        if self.vision is not None:
            await self.vision.close()
        server, self.server = self.server, None
        if server is not None:
            try:
                async with asyncio.timeout(CLOSE_TIMEOUT_S):
                    await server.stop()
            except Exception as err:  # closing must go on; say why once
                log.warning("%s: stopping the OPC UA server: %r", self.name, err)
            await self.session_certs.end(self.name)
        for conn in self.gate.connections():
            self.gate.forget(conn)
        self._job = None
        self.machine = VisionMachine()
        self.machine.handshake.queue = self._conveyor
        self.space = self.vision = None
        self.lines.flush(force=True)
        self.cell.set(LinkState.STOPPED)

    #: ``vgripd check``'s warnings about these options (``exposure_warnings``)
    exposure = staticmethod(exposure_warnings)

    def health(self) -> LinkHealth:
        return self.cell.health(peer=self._where, peers=len(self.gate))

    @property
    def port(self) -> int:
        """The bound port (the configured one, or the one chosen for port 0)."""
        if self.server is not None and self.server.bserver is not None:
            return int(self.server.bserver.port)
        return self.options.port

    @property
    def endpoint_url(self) -> str:
        """The URL clients connect to (the host name for a wildcard address)."""
        o = self.options
        host = socket.gethostname() if o.host in WILDCARD_HOSTS else o.host
        host = f"[{host}]" if ":" in host else host
        return f"opc.tcp://{host}:{self.port}{o.path}"

    async def image_captured(self, seq: int, job_id: int) -> None:
        self._running(seq, "image_captured")
        self._open()
        render_plan(self.machine.captured(seq, job_id), (Part.CAPTURED,))
        if self.space is not None:
            await self.space.captured(seq, job_id)
        if self.vision is not None:
            await self.vision.captured(seq, job_id)

    async def publish(self, seq: int, result: JobResult) -> Status:
        """Write the result (data, RequestId, Sequence, state) and raise the event; the status
        shown. The server holds it, so it is never undelivered while the link is open."""
        job = self._running(seq, "publish")
        self._open()
        plan, result, moves = self.machine.publish(seq, result)
        self._job = None
        t_done = result.t_done_mono_ns or time.monotonic_ns()
        stamp = datetime.datetime.now(datetime.UTC) - datetime.timedelta(
            microseconds=max(0, time.monotonic_ns() - t_done) / 1000)
        # a NEXT (PREDICT) answer carries its job's recipe; the selected one may have changed
        recipe = result.recipe if job.command in (Command.NEXT, Command.PREDICT) else job.recipe
        shown, sent = result_values(seq, recipe, result, stamp)
        if sent.status is not result.status:
            log.warning("%s: request %d answered %s instead of %s: %s", self.name, seq,
                        sent.status.name, result.status.name, sent.message)
        # RESULT and ACK: the data, then RequestId and Sequence; the state machine and the
        # event announce the answer after it (publish_result)
        render_plan(plan, (Part.RESULT, Part.ACK))
        if self.space is not None:
            await self.space.publish_result(shown)
        if self.vision is not None:
            await self.vision.publish(seq, shown, t_done, moves)
            self.vision.continue_later()  # ContinuousExecution: the next job, after this return
        return sent.status

    def refusals(self) -> Mapping[str, int]:
        return dict(self._refusals)

    def set_recipes(self, recipes: Mapping[int, str]) -> None:
        self._recipes = dict(recipes)
        if self.vision is not None:
            self.vision.set_recipes(recipes)

    def set_configuration(self, name: str, digest: bytes) -> None:
        self._config_id = (name, digest)
        if self.vision is not None:
            self.vision.set_configuration(name, digest)

    def set_conveyor(self, on: bool) -> None:
        self._conveyor = self.machine.handshake.queue = on  # NEXT and Predict: the queue's

    async def set_warnings(self, bits: int) -> None:
        self._warnings = checked_warnings(bits)
        if self.space is not None:
            await self.space.write([("Warnings", self._warnings)])

    # -- methods -----------------------------------------------------------------------------

    async def _start_single_job(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        if args:
            return self._refuse(Status.BAD_REQUEST, ua.StatusCodes.BadTooManyArguments,
                                "StartSingleJob takes no arguments (SelectRecipe sets the "
                                "recipe)")
        return await self._request(Command.TRIGGER, "StartSingleJob")

    async def _request(self, command: Command, method: str, count: int | None = None) -> Any:
        """A request of the older namespace (a job, a NEXT, a PREDICT for ``count``) with a
        new RequestId, or refused as the handshake says (BUSY while a request runs,
        BAD_REQUEST for a Next without a list or a Predict without a conveyor); its own
        rules, whatever the OPC 40100 state. A job or NEXT takes the latch variables."""
        latch = (count, None) if command == Command.PREDICT or self.space is None else \
            self.space.latch()
        verdict, request_id = await self._begin(
            command, lambda seq: self.machine.request(command, seq, self._recipe),
            JobInfo(count=latch[0], frame=latch[1]))
        if verdict.decision is None or verdict.decision.code is Status.BUSY:
            running = self._job.request_id if self._job is not None else "-"
            return self._refuse(Status.BUSY, ua.StatusCodes.BadInvalidState,
                                f"{method} while request {running} runs")
        if not verdict.ok:
            return self._refuse_named(Status.BAD_REQUEST, verdict.refused, f"{method}: " + (
                "no recipe has a [conveyor]" if command == Command.PREDICT else "no pick list "
                "(no result yet, or the last one had no pickable object)"))
        return [ua.Variant(request_id, ua.VariantType.UInt32)]

    async def _begin(self, command: int, verdict_for: Any, info: JobInfo) -> tuple[Verdict, int]:
        """Start a request with a new id if ``verdict_for(id)`` (the state machine's answer)
        lets it; the daemon is told after this call returns."""
        request_id = 1 if self._next_request >= 0xFFFFFFFF else self._next_request + 1
        if self.space is None and self.vision is None:
            return Verdict("BadInvalidState", "not open"), request_id
        verdict: Verdict = verdict_for(request_id)
        decision = verdict.decision
        if not verdict.ok or decision is None:
            return verdict, request_id
        self._next_request = request_id
        job = self._job = _Job(request_id, decision.recipe, Command(command))
        # RETRACT (the data turns uncertain, then RequestId 0); CLEAR keeps the values (they
        # are uncertain now); STATE: a job's SingleExecution, a Next takes no image
        render_plan(decision.steps, (Part.RETRACT, Part.CLEAR, Part.STATE))
        if self.space is not None:
            await self.space.retract(executing=command == Command.TRIGGER)
        if self.vision is not None:
            self.vision.begin(request_id, info)
            await self.vision.retract(request_id)
        assert self._on_trigger is not None
        trigger = Trigger(link=self.name, seq=job.request_id, command=int(command),
                          t_mono_ns=time.monotonic_ns(), recipe=job.recipe,
                          latch_count=info.count, latch_frame=info.frame)
        asyncio.get_running_loop().call_soon(self._on_trigger, trigger)
        return verdict, request_id

    def _refuse_named(self, status: Status, code: str, why: str) -> ua.StatusCode:
        return self._refuse(status, int(getattr(ua.StatusCodes, code)), why)

    async def _next(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """The next object of the last job's pick list: a request like StartSingleJob's (a new
        RequestId, the result through ``Result.*``) that the daemon answers from the list."""
        if args:
            return self._refuse(Status.BAD_REQUEST, ua.StatusCodes.BadTooManyArguments,
                                "Next takes no arguments")
        return await self._request(Command.NEXT, "Next")

    async def _predict(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """Where the part last served to this link will be at the argument's count (a
        conveyor's PREDICT): a request like Next's."""
        count = count_argument("Predict", args)
        if isinstance(count, tuple):
            return self._refuse_named(Status.BAD_REQUEST, *count)
        return await self._request(Command.PREDICT, "Predict", count)

    async def _select_recipe(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        if not args:
            return self._refuse(Status.BAD_REQUEST, ua.StatusCodes.BadArgumentsMissing,
                                "SelectRecipe needs RecipeId")
        if len(args) > 1:
            return self._refuse(Status.BAD_REQUEST, ua.StatusCodes.BadTooManyArguments,
                                "SelectRecipe takes one argument (RecipeId)")
        value = args[0].Value
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFF:
            return self._refuse(Status.BAD_REQUEST, ua.StatusCodes.BadInvalidArgument,
                                f"SelectRecipe: RecipeId {value!r} is not 0..65535")
        if self._recipes is not None and value not in self._recipes:
            known = ", ".join(f"{n} {name}" for n, name in sorted(self._recipes.items()))
            return self._refuse(Status.BAD_REQUEST, ua.StatusCodes.BadInvalidArgument,
                                f"SelectRecipe: recipe {value} is not configured "
                                f"(configured: {known})")
        self._recipe = value
        await self._space().write([("SelectedRecipe", value)])
        return []

    async def _reset(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        if args:
            return self._refuse(Status.BAD_REQUEST, ua.StatusCodes.BadTooManyArguments,
                                "Reset takes no arguments")
        if self.machine.busy or self.space is None:
            return self._refuse(Status.BUSY, ua.StatusCodes.BadInvalidState,
                                "Reset while a job runs")
        await self.space.set_state("Ready")
        return []

    def _refuse(self, status: Status, code: int, why: str) -> ua.StatusCode:
        self._refusals[status.name] += 1
        self.lines.info("method", f"refused {status.name}", "%s: %s: refused %s (%s)",
                        self.name, why, status.name, ua.StatusCode(ua.UInt32(code)).name)
        return ua.StatusCode(ua.UInt32(code))

    def _untrusted(self, der: bytes) -> str:
        return untrusted(self._trust, self.rejected, der)

    def _space(self) -> Space:
        if self.space is None:
            raise LinkError(f"link {self.name}: not open")
        return self.space

    def _open(self) -> None:
        if self.space is None and self.vision is None:
            raise LinkError(f"link {self.name}: not open")

    def _running(self, seq: int, what: str) -> _Job:
        job = self._job
        if job is None or job.request_id != seq:
            running = "none" if job is None else job.request_id
            raise LinkError(f"link {self.name}: {what} for request {seq}, but the running "
                            f"request is {running}")
        return job

    # -- connections -------------------------------------------------------------------------

    def fault(self, client: str, kind: str, level: int, msg: str, *args: Any) -> None:
        """Count a peer fault and log it, at most once per client and kind per interval."""
        self.faults[kind] += 1
        self.lines.log(level, client, kind, f"%s: {msg}", self.name, *args)

    def _admit(self, conn: _Protocol) -> None:
        self.lines.info(conn.host, "connected", "%s: client %s connected (%d open)", self.name,
                        conn.client, len(self.gate))

    def _forget(self, conn: _Protocol, ex: BaseException | None) -> None:
        if not self.gate.forget(conn):
            return  # refused or evicted by the gate, or the link is closed
        if not conn.reason:
            why = f"{ex}" if ex is not None else "closed the connection"
            self.lines.info(conn.host, "disconnected", "%s: client %s %s (%d open)", self.name,
                            conn.client, why, len(self.gate))

    async def _watch(self) -> None:
        """Close silent connections: no session within ``activation_timeout_s``, or no message
        for longer than the session's timeout (asyncua closes the session then, not the
        socket). Also writes held log lines."""
        o = self.options
        period = min(0.5, o.activation_timeout_s / 4)
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            for conn in self.gate.connections():
                timeout_s = conn.session_timeout_s()
                if timeout_s is None:
                    if now - conn.last_data > o.activation_timeout_s and (
                            now - conn.opened > o.activation_timeout_s):
                        conn.drop("silent", f"no session within {o.activation_timeout_s:g} s "
                                  "(activation_timeout_s)")
                elif now - conn.last_data > timeout_s + 0.5:
                    conn.drop("silent", f"silent for {now - conn.last_data:.1f} s (session "
                              f"timeout {timeout_s:g} s)")
            self.lines.flush()

    # -- set-up ------------------------------------------------------------------------------

    async def _make_server(self, passwords: dict[str, bytes]) -> _Server:
        o = self.options
        server = _Server(self, _Users(passwords, o.allow_anonymous))
        await server.init()
        bind = None if o.host in WILDCARD_HOSTS else o.host
        server.set_endpoint(f"opc.tcp://{o.host or '0.0.0.0'}:{o.port}{o.path}")
        server.socket_address = (bind or "0.0.0.0", o.port)
        server.set_server_name(f"vgripd {self.name}")
        app_uri = f"urn:vgripd:{socket.gethostname()}:{self.name}"
        await server.set_application_uri(app_uri)
        server.product_uri = "urn:vgripd"
        server.manufacturer_name = "vgripd"
        await server.set_build_info("urn:vgripd", "vgripd", "vgripd", _version(), "0",
                                    datetime.datetime.now(datetime.UTC))
        server.set_security_policy([SECURITY_MODES[m] for m in o.security])
        if any(m != "None" for m in o.security):
            assert o.certificate_dir is not None
            hosts = [socket.gethostname(), "localhost"] + ([o.host] if bind else [])
            try:
                cert, key, made = await asyncio.to_thread(
                    ensure_certificate, o.certificate_dir, app_uri, hosts, o.certificate_days)
            except (OSError, ValueError) as err:
                raise LinkError(f"certificate_dir {o.certificate_dir}: {err}") from None
            if made:
                log.info("%s: generated the server certificate %s (clients must trust it)",
                         self.name, cert)
            await server.load_certificate(str(cert))
            await server.load_private_key(str(key))
            self.certificate = cert
        if o.trusted_clients_dir is not None:
            if not o.trusted_clients_dir.is_dir():
                raise LinkError(f"trusted_clients_dir: {o.trusted_clients_dir} is not a folder")
            self._trust = TrustStore([o.trusted_clients_dir], [])
            if any(o.trusted_clients_dir.iterdir()):
                try:
                    await self._trust.load_trust()
                except (OSError, ValueError) as err:
                    raise LinkError(f"trusted_clients_dir {o.trusted_clients_dir}: {err}") \
                        from None
            else:  # an unloaded store trusts nobody
                log.warning("%s: trusted_clients_dir %s is empty: every client is refused "
                            "(refused certificates are kept in %s)", self.name,
                            o.trusted_clients_dir, o.certificate_dir / "rejected"
                            if o.certificate_dir else "-")
        tokens: list[type] = []
        if o.allow_anonymous:
            tokens.append(ua.AnonymousIdentityToken)
        if o.users:
            tokens.append(ua.UserNameIdentityToken)
        server.set_identity_tokens(tokens)
        iserver = server.iserver
        # The gate bounds connections before asyncua sees them; an evicted connection is
        # still in asyncua's list until its close completes, so asyncua's own cap sits above.
        iserver.max_connections = 2 * o.max_connections + 64
        iserver.max_pending_activation_seconds = 0  # the link's own watch says why it closes
        iserver.max_session_timeout_ms = o.max_session_timeout_s * 1000
        iserver.min_session_timeout_ms = min(iserver.min_session_timeout_ms,
                                             o.max_session_timeout_s * 1000)
        if "vgripd" in o.models:  # registered first: the index (2) its clients hard-code
            idx = await server.register_namespace(o.namespace_uri)
            space = Space(server, idx)
            await space.build(self._start_single_job, self._select_recipe, self._reset,
                              self._next, self._predict)
            self.space = space
        if "MachineVision" in o.models:
            vision = VisionSpace(server, self.machine, self._begin, self._refuse_named)
            vision.set_recipes(self._recipes or {0: "default"})
            vision.set_configuration(*self._config_id)
            await vision.build()
            self.vision = vision
        return server

