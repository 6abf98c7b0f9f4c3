"""The OPC 40100 side of OpcUaLink against node-opcua's client, a second OPC UA stack that
shares no code with the server (asyncua): ``opcua_node_client.js`` browses the type hierarchy of
the official NodeSet, runs the PLC sequence (SelectModeAutomatic -> PrepareRecipe ->
StartSingleJob per part -> ResultReady event -> GetResultById), has wrong-state calls refused,
and prints what it saw; the pose is compared with what test_opcua's stand-in daemon published.

node-opcua-client is installed outside the repository (``NODE_OPCUA_DIR``, by default
``~/.cache/vgripd-node``; ``.ci/run`` installs the pinned version there).
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from drivers.links.opcua import OpcUaLink
from tests.conftest import need
from tests.drivers.links.test_opcua import POSE, Daemon, open_link, options, url

pytestmark = pytest.mark.timeout(180)

#: the version .ci/run installs
NODE_OPCUA_VERSION = "2.182.0"
NODE_DIR = Path(os.environ.get("NODE_OPCUA_DIR", Path.home() / ".cache" / "vgripd-node"))
SCRIPT = Path(__file__).with_name("opcua_node_client.js")


def node_modules() -> Path:
    modules = NODE_DIR / "node_modules"
    need(shutil.which("node") is not None and (modules / "node-opcua-client").is_dir(),
         f"needs node and node-opcua-client: npm install --prefix {NODE_DIR} "
         f"node-opcua-client@{NODE_OPCUA_VERSION}")
    return modules


@pytest.fixture
async def link() -> AsyncIterator[tuple[OpcUaLink, Daemon]]:
    daemon = Daemon()
    lk = await open_link(daemon, options(old_only=False))  # the default models
    yield lk, daemon
    await lk.close()
    for task in list(daemon.tasks):
        task.cancel()


async def test_node_opcua_runs_the_plc_sequence(link: tuple[OpcUaLink, Daemon]) -> None:
    modules = node_modules()
    lk, daemon = link
    proc = await asyncio.create_subprocess_exec(
        "node", str(SCRIPT), url(lk), "3", stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE, env={**os.environ, "NODE_PATH": str(modules)})
    async with asyncio.timeout(150):
        stdout, stderr = await proc.communicate()
    assert proc.returncode == 0, stderr.decode()[-3000:]
    found = [line for line in stdout.decode().splitlines() if line.startswith("RESULT ")]
    assert found, stdout.decode()[-3000:]
    out = json.loads(found[-1].removeprefix("RESULT "))
    assert out["ok"], out
    mv = out["namespaces"]["mv"]
    assert out["visionSystemType"] == out["instanceType"] == f"ns={mv};i=1003"
    assert out["states"] == [["Preoperational", ""], ["Operational", "Initialized"],
                             ["Operational", "Ready"], ["Operational", "Ready"]]
    assert out["refused"] == {"preoperational": "BadInvalidState",
                              "initialized": "BadInvalidState",
                              "stopInReady": "BadInvalidState"}
    assert (out["select"], out["prepare"]) == ("Good", "Good")
    # decoded as the NodeSet's own type (not the abstract BinaryIdBaseDataType)
    assert out["prepared"] == {"id": "0", "type": "RecipeIdInternalDataType"}
    assert len(out["jobs"]) == 3
    for n, job in enumerate(out["jobs"], start=1):
        trigger = daemon.triggers[n - 1]
        assert job["status"] == job["resultStatus"] == "Good"
        assert job["jobId"] == job["eventJobId"] == job["resultJobId"] == str(trigger.seq)
        assert (job["eventMeasId"], job["eventPartId"], job["partId"]) == (
            f"m{n}", f"p{n}", f"p{n}")
        assert job["eventResultState"] == job["resultState"] == 1
        assert (job["statusName"], job["daemonJobId"]) == ("OK", 100 + trigger.seq)
        assert tuple(job["values"]) == POSE
