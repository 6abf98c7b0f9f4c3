"""``vgripd run`` with an encrypted, password-protected OPC UA link, probed as an attacker on
the cell network would (issue 20): a raw client (``vgripd.sim.opcua_raw``, asyncua's lower
layer, which does not refuse on its own what the server must refuse) opens a SecurityPolicy
None channel and asks for a session, a job and the result; then guesses passwords on an
encrypted channel. A real client's jobs before it complete; the daemon's log holds one line
per kind of refusal and no ERROR or traceback.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.integration.test_daemon_opcua import free_port
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
    port = free_port()
    cfg = tmp_path / "vgripd.toml"
    cfg.write_text(f"""
[camera]
type = "synthetic"
seed = 3

[[links]]
type = "opcua"
host = "127.0.0.1"
port = {port}
certificate_dir = "{tmp_path / 'pki'}"
users = [{{ name = "cell", password_env = "VGRIPD_OPCUA_PASSWORD" }}]

[status]
enabled = false
""")
    env = {**os.environ, "PYTHONPATH": str(REPO), "VGRIPD_OPCUA_PASSWORD": "cell-pw-1"}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "vgripd", "run", "-c", str(cfg), cwd=REPO, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    job = "ns=2;s=VisionSystem.StartSingleJob"
    try:
        cert = tmp_path / "pki" / "vgripd-server-cert.der"
        url = f"opc.tcp://127.0.0.1:{port}/vgripd"
        async with asyncio.timeout(60):
            while True:  # the daemon is up when its certificate exists and the port answers
                if cert.exists():
                    try:
                        _, w = await asyncio.open_connection("127.0.0.1", port)
                        w.close()
                        break
                    except OSError:
                        pass
                await asyncio.sleep(0.1)
        args = ["--security", "Basic256Sha256_SignAndEncrypt", "--server-cert", str(cert),
                "--client-cert-dir", str(tmp_path / "client"), "--user", "cell",
                "--password-env", "PW"]
        async with OpcUaClientProcess(url, *args, env={"PW": "cell-pw-1"}) as client:
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
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(60):
            _, err = await proc.communicate()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    stderr = err.decode()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    assert not [line for line in stderr.splitlines() if " ERROR " in line], stderr
    assert stderr.count("CreateSession on a channel with SecurityPolicy None") == 1, stderr
    assert stderr.count("failed logins in a row") == 1, stderr
    assert "job 2:" not in stderr  # only the real client's job ran
