"""``vgripd run`` with an encrypted, password-protected OPC UA link, probed as an attacker on
the cell network would: a raw client (``vgripd.sim.opcua_raw``, asyncua's lower
layer, which does not refuse on its own what the server must refuse) opens a SecurityPolicy
None channel and asks for a session, a job and the result; then guesses passwords on an
encrypted channel. A real client's jobs before it complete; the daemon's log holds one line
per kind of refusal and no ERROR or traceback. The daemon keeps the default models (OPC 40100's
NodeSet served too): the probes hold against the server as it ships.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from tests.integration.test_daemon_opcua import encrypted_opcua_daemon
from vgripd.sim.opcua_client import OpcUaClientProcess

asyncua = pytest.importorskip("asyncua")
from asyncua import ua  # noqa: E402

from vgripd.sim.opcua_raw import RawOpcUa, client_policy, status_of  # noqa: E402

pytestmark = pytest.mark.timeout(180)


async def refused(coro: object) -> str:
    try:
        await coro  # type: ignore[misc]
    except ua.UaStatusCodeError as err:
        return status_of(err)
    return ""


async def test_raw_attacks_on_a_running_daemon_are_refused(tmp_path: Path) -> None:
    job = "ns=2;s=VisionSystem.StartSingleJob"
    async with encrypted_opcua_daemon(tmp_path) as daemon:
        port, cert = daemon.port, daemon.cert
        async with OpcUaClientProcess(daemon.url, *daemon.client_args,
                                      env={"PW": "cell-pw-1"}) as client:
            assert client.connected["event"] == "connected", client.connected
            assert (await client.send("job"))["request_id"] == 1

        # SecurityPolicy None: endpoint discovery only
        async with RawOpcUa("127.0.0.1", port) as raw:
            assert len(await raw.get_endpoints()) == 1
            assert await refused(raw.create_session()) == "BadSecurityPolicyRejected"
        async with RawOpcUa("127.0.0.1", port) as raw:
            assert await refused(raw.activate("cell", "cell-pw-1")) == \
                "BadSecurityPolicyRejected"
        async with RawOpcUa("127.0.0.1", port) as raw:
            assert await refused(raw.call("ns=2;s=VisionSystem", job)) == \
                "BadSecurityPolicyRejected"
        async with RawOpcUa("127.0.0.1", port) as raw:
            assert await refused(raw.read("ns=2;s=VisionSystem.Result.Values")) == \
                "BadSecurityPolicyRejected"

        # password guessing on one encrypted connection: 10 checked, then locked out
        policy = await asyncio.to_thread(client_policy, cert.read_bytes(),
                                         ua.MessageSecurityMode.SignAndEncrypt)
        async with RawOpcUa("127.0.0.1", port, policy=policy) as raw:
            await raw.create_session()
            answers = [await refused(raw.activate("cell", f"guess-{n}")) for n in range(30)]
            assert answers == ["BadUserAccessDenied"] * 10 + ["BadRequestNotAllowed"] * 20
            assert await refused(raw.activate("cell", "cell-pw-1")) == "BadRequestNotAllowed"
            assert await refused(raw.call("ns=2;s=VisionSystem", job)) == \
                "BadSessionNotActivated"
    stderr = daemon.stderr
    assert daemon.returncode == 0, stderr
    assert "Traceback" not in stderr
    assert not [line for line in stderr.splitlines() if " ERROR " in line], stderr
    assert stderr.count("CreateSession on a channel with SecurityPolicy None") == 1, stderr
    assert stderr.count("failed logins in a row") == 1, stderr
    assert "job 2:" not in stderr  # only the real client's job ran
