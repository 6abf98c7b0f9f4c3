"""A raw OPC UA client that does what an attacker on the cell network does, for tests.

asyncua's high-level ``Client`` refuses on its own what a server should refuse (a security
policy the server does not offer, a password in clear), so it cannot show whether the server
refuses it. ``RawOpcUa`` drives asyncua's lower layer (``UaClient``: Hello, OpenSecureChannel,
then any request) and builds the session requests itself: CreateSession and ActivateSession on
a channel of any policy (SecurityPolicy None by default), with an anonymous or a UserName token
whose password travels in clear, then Read and Call by node id. A refused request raises
asyncua's ``UaStatusCodeError`` subclass for its status (``BadUserAccessDenied``, ...);
``status_of`` gives its name.
"""

from __future__ import annotations

import logging
from types import TracebackType
from typing import Any

from asyncua import ua
from asyncua.client.ua_client import UaClient, UASocketState
from asyncua.common.utils import create_nonce


def status_of(err: BaseException) -> str:
    """The OPC UA status name of a refused request (``BadUserAccessDenied``)."""
    code = getattr(err, "code", None)
    if isinstance(code, int):
        return str(ua.StatusCode(ua.UInt32(code)).name)
    return type(err).__name__


def client_policy(server_cert_der: bytes, mode: ua.MessageSecurityMode,
                  common_name: str = "raw", key: Any = None) -> Any:
    """A Basic256Sha256 client policy with a fresh self-signed client certificate named
    ``common_name``, for ``key`` (a new RSA 2048 key when None); each call makes a certificate
    with a new thumbprint (a new serial number), so one key serves many certificates."""
    from asyncua.crypto import cert_gen
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = key or cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key, common_name, {"organizationName": "raw"},
        [x509.UniformResourceIdentifier("urn:raw:attacker"), x509.DNSName("localhost")],
        [ExtendedKeyUsageOID.CLIENT_AUTH], days=30)
    return SecurityPolicyBasic256Sha256(server_cert_der, cert, key, mode)


class RawOpcUa:
    """One TCP connection and one secure channel to ``opc.tcp://host:port/path``; ``policy``
    an asyncua security policy object (None: SecurityPolicy None, mode None)."""

    def __init__(self, host: str, port: int, path: str = "/vgripd", timeout_s: float = 10.0,
                 policy: Any = None) -> None:
        self.host = host
        self.port = port
        self.url = f"opc.tcp://{host}:{port}{path}"
        # each refusal is the point of a probe, not a warning of the prober's
        logging.getLogger("asyncua.client.ua_client.UASocketProtocol").setLevel(logging.ERROR)
        self.client = UaClient(timeout=timeout_s)
        if policy is not None:
            self.client.set_security(policy)
        self.session: ua.CreateSessionResult | None = None
        self.nonce: bytes | None = None

    async def __aenter__(self) -> RawOpcUa:
        await self.client.connect_socket(self.host, self.port)
        await self.client.send_hello(self.url)
        params = ua.OpenSecureChannelParameters()
        params.ClientProtocolVersion = 0
        params.RequestType = ua.SecurityTokenRequestType.Issue
        params.SecurityMode = self.client.security_policy.Mode
        params.ClientNonce = create_nonce(self.client.security_policy.secure_channel_nonce_length)
        params.RequestedLifetime = 3_600_000
        await self.client.open_secure_channel(params)
        return self

    async def __aexit__(self, kind: type[BaseException] | None, err: BaseException | None,
                        tb: TracebackType | None) -> None:
        self.client.disconnect_socket()

    @property
    def closed(self) -> bool:
        """The server closed the connection (or it was never opened)."""
        protocol = self.client.protocol
        return protocol is None or protocol.state is UASocketState.CLOSED

    async def get_endpoints(self) -> list[ua.EndpointDescription]:
        params = ua.GetEndpointsParameters()
        params.EndpointUrl = self.url
        return await self.client.get_endpoints(params)

    async def create_session(self) -> ua.CreateSessionResult:
        params = ua.CreateSessionParameters()
        params.ClientDescription = ua.ApplicationDescription(
            ApplicationUri="urn:raw:attacker", ApplicationName=ua.LocalizedText("raw"),
            ApplicationType=ua.ApplicationType.Client)
        params.ServerUri = ""
        params.EndpointUrl = self.url
        params.SessionName = "raw"
        params.ClientNonce = create_nonce(32)
        params.ClientCertificate = self.client.security_policy.host_certificate
        params.RequestedSessionTimeout = 30_000
        params.MaxResponseMessageSize = 0
        self.session = await self.client.create_session(params)
        self.nonce = self.session.ServerNonce
        return self.session

    def adopt(self, other: RawOpcUa) -> None:
        """Use ``other``'s session (its AuthenticationToken and nonce) on this connection, as a
        client taking a session over to a new channel does, or one that stole the token."""
        assert other.session is not None
        self.session, self.nonce = other.session, other.nonce
        self.client.session.restore_authentication_token(other.session.AuthenticationToken)

    async def activate(self, user: str | None = None, password: str = "") -> None:
        """ActivateSession with an anonymous token, or a UserName token with the password in
        clear (no EncryptionAlgorithm), whatever the server's endpoints ask for. On a signed
        channel the ClientSignature is made as the protocol asks (server certificate and
        nonce of the last CreateSession or successful ActivateSession)."""
        params = ua.ActivateSessionParameters()
        params.LocaleIds = ["en"]
        policy = self.client.security_policy
        if self.session is not None and policy.host_certificate is not None:
            challenge = (self.session.ServerCertificate or b"") + (self.nonce or b"")
            params.ClientSignature.Algorithm = policy.AsymmetricSignatureURI
            params.ClientSignature.Signature = policy.asymmetric_cryptography.signature(
                challenge)
        token: Any
        if user is None:
            token = ua.AnonymousIdentityToken()
            token.PolicyId = "anonymous"
        else:
            token = ua.UserNameIdentityToken()
            token.PolicyId = "username"
            token.UserName = user
            token.Password = password.encode()
            token.EncryptionAlgorithm = None
        params.UserIdentityToken = token
        result = await self.client.activate_session(params)
        self.nonce = result.ServerNonce

    async def read(self, *node_ids: str) -> list[ua.DataValue]:
        """Read the Value attribute of each node (``ns=2;s=VisionSystem.Result.Status``)."""
        params = ua.ReadParameters()
        for text in node_ids:
            rv = ua.ReadValueId()
            rv.NodeId = ua.NodeId.from_string(text)
            rv.AttributeId = ua.AttributeIds.Value
            params.NodesToRead.append(rv)
        return await self.client.read(params)

    async def call(self, object_id: str, method_id: str,
                   *args: ua.Variant) -> ua.CallMethodResult:
        request = ua.CallMethodRequest()
        request.ObjectId = ua.NodeId.from_string(object_id)
        request.MethodId = ua.NodeId.from_string(method_id)
        request.InputArguments = list(args)
        results: list[ua.CallMethodResult] = await self.client.call([request])
        return results[0]
