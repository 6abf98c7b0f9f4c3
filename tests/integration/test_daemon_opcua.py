"""The daemon with an ``opcua`` link, end to end: the synthetic camera, the whole pipeline, and
asyncua's client in another process (``vgripd.sim.opcua_client``) starting jobs the way
docs/opcua.md tells a cell's client to.

- In-process daemon: the client reads exactly the vendor values and the 4x4 offset the pipeline
  computed (OPC UA Doubles: bit-exact), with the daemon's job ids; a job the daemon refuses
  because another link's job runs comes back as a BUSY result.
- ``vgripd run`` as a process (what systemd starts) with an encrypted, password-protected
  endpoint and a certificate generated at its first start: jobs complete, SIGTERM ends it
  cleanly, no traceback.

The in-process daemons serve the older namespace alone (``models = ["vgripd"]``: its client is
what these tests are about); ``vgripd run`` keeps the default models, the NodeSet included.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO
from tests.integration.test_daemon import Plc, Run, running
from vgripd.config import config_from_dict
from vgripd.peer.registers import Reg
from vgripd.service.daemon import Daemon
from vgripd.service.links.protocol import LinkState
from vgripd.sim.opcua_client import OpcUaClientProcess
from vgripd.types import ImagePair, JobResult, Status

pytestmark = pytest.mark.timeout(180)

OPEN_LINK = {"type": "opcua", "host": "127.0.0.1", "port": 0, "security": ["None"],
             "allow_anonymous": True, "models": ["vgripd"]}


async def test_jobs_through_the_opcua_link_carry_the_computed_pose() -> None:
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [OPEN_LINK],
        "status": {"port": 0},
    })
    async with running(config) as run:
        await run.daemon.wait_for(
            lambda: all(link.health().state is LinkState.UP
                        for link in run.daemon.rooms.links.links.values()), 30)
        url = f"opc.tcp://127.0.0.1:{run.port(0)}/vgripd"
        async with OpcUaClientProcess(url) as client:
            assert client.connected["event"] == "connected", client.connected
            seen = [await client.send("job") for _ in range(2)]
            # A recipe the config does not have: the daemon told the link its recipes, so
            # SelectRecipe refuses it at once and the selection stays recipe 0.
            assert (await client.send("recipe 9")) == {"event": "refused",
                                                       "code": "BadInvalidArgument"}
            seen.append(await client.send("job"))
        records = [(await run.job_done(n))[1] for n in (1, 2, 3)]
        snapshot = run.daemon.snapshot()
    assert seen[2]["RecipeId"] == 0
    for r, rec in zip(seen, records, strict=True):
        assert rec.result.status is Status.OK
        assert rec.result.target is not None
        assert rec.result.offset is not None
        assert (r["Status"], r["JobId"], r["request_id"]) == (1, rec.job_id, rec.seq)
        assert tuple(r["Values"]) == rec.result.target.values
        assert r["ValueNames"] == list(rec.result.target.fields)
        assert np.array_equal(np.array(r["Pose"]).reshape(4, 4), rec.result.offset)
        assert r["ev"]["Values"] == r["Values"]
        assert r["captured"] == rec.seq
    assert snapshot["links"][0]["state"] == "up"
    assert snapshot["counters"]["OK"] == 3
    assert snapshot["counters"]["BAD_REQUEST"] == 1  # the link's refusal of SelectRecipe


class HeldPipeline:
    """A processor that holds each job until released: the job runs as long as the test
    needs, without a timed wait."""

    def __init__(self) -> None:
        self.release = threading.Event()

    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        self.release.wait(60)
        return JobResult(job_id=job_id, status=Status.NOT_FOUND, message="held")


async def test_a_start_while_another_link_runs_a_job_is_a_busy_result() -> None:
    config = config_from_dict({
        "camera": {"type": "synthetic", "seed": 11, "max_tilt_deg": 2.0},
        "links": [{"type": "modbus_server", "host": "127.0.0.1", "port": 0}, OPEN_LINK],
        "status": {"enabled": False},
    })
    held = HeldPipeline()
    daemon = Daemon(config, pipeline=held)
    run = Run(daemon)
    await daemon.start()
    try:
        url = f"opc.tcp://127.0.0.1:{run.port(1)}/vgripd"
        async with Plc(run.port(0)) as plc, OpcUaClientProcess(url) as client:
            await plc.trigger(1)
            await run.busy()
            busy = await client.send("job")
            held.release.set()
            assert (await plc.result(1))[Reg.STATUS] == Status.NOT_FOUND
            ok = await client.send("job")
    finally:
        held.release.set()
        await daemon.stop()
    assert (busy["Status"], busy["StatusName"], busy["JobId"], busy["Values"]) == (
        40, "BUSY", 0, [])
    assert busy["state"] == "Ready"
    assert ok["Status"] == Status.NOT_FOUND
    assert ok["request_id"] == busy["request_id"] + 1


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclasses.dataclass
class EncryptedDaemon:
    """A ``vgripd run`` process with an encrypted OPC UA link (``encrypted_opcua_daemon``)."""

    port: int
    url: str
    cert: Path  # the server certificate it generated at its start
    client_args: list[str]  # OpcUaClientProcess arguments of the right user (password in $PW)
    returncode: int | None = None  # after the stop
    stderr: str = ""


@contextlib.asynccontextmanager
async def encrypted_opcua_daemon(tmp_path: Path) -> AsyncIterator[EncryptedDaemon]:
    """``vgripd run`` (synthetic camera; opcua link with Basic256Sha256 SignAndEncrypt only,
    user "cell", password "cell-pw-1" from the environment), entered once it is up (its
    certificate exists and the port answers); ended with SIGTERM, its exit code and stderr kept
    on the yielded object. Killed when the body fails."""
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
    cert = tmp_path / "pki" / "vgripd-server-cert.der"
    daemon = EncryptedDaemon(port, f"opc.tcp://127.0.0.1:{port}/vgripd", cert, [
        "--security", "Basic256Sha256_SignAndEncrypt", "--server-cert", str(cert),
        "--client-cert-dir", str(tmp_path / "client"), "--user", "cell", "--password-env", "PW"])
    try:
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
        yield daemon
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(60):
            _, err = await proc.communicate()
        daemon.returncode, daemon.stderr = proc.returncode, err.decode()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_vgripd_run_completes_jobs_with_an_encrypted_opcua_link(tmp_path: Path) -> None:
    async with (encrypted_opcua_daemon(tmp_path) as daemon,
                OpcUaClientProcess(daemon.url, *daemon.client_args,
                                   env={"PW": "cell-pw-1"}) as client):
        assert client.connected["event"] == "connected", client.connected
        for n in (1, 2):
            r = await client.send("job")
            assert (r["Status"], r["request_id"], r["JobId"]) == (1, n, n), r
            assert len(r["Values"]) == 6
            assert all(abs(v) < 1000 for v in r["Values"])
    assert daemon.returncode == 0, daemon.stderr
    assert "Traceback" not in daemon.stderr
