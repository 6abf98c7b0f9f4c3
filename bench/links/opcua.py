"""OPC UA link: trigger to result vs a bare asyncua server, same run.

Servers in this process, on one event loop: vgripd's ``OpcUaLink`` (security None, anonymous;
a daemon stand-in that answers each trigger at once: image_captured, then publish, no vision
work) and the named peer, a bare asyncua ``Server`` with one method that returns a constant
result (status and six values) as its output arguments: the least an OPC UA server can do for
"locate and tell me". The client is asyncua's ``Client`` in a child process (this script with
``python -m bench.links.opcua --client``), one session to each server, jobs in alternating blocks so load changes hit both.

What a job is, measured in the client from the call to having the result:

- link: ``StartSingleJob`` (returns the RequestId), then Read requests of ``Result.RequestId``
  with the result variables, back to back, until the RequestId is the new one (the job
  sequence of docs/opcua.md for a polling client); ``reads`` counts them;
- bare: one ``Call`` whose output arguments are the result (one round trip).

So the link's figure holds at least two round trips and the trigger hand-off to the daemon;
the ratio says what the job sequence costs against the least possible exchange. Both
security modes are measured: None, and Basic256Sha256 SignAndEncrypt (the peer then uses the
link's generated certificate).
"""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from asyncua import Client, Server, ua

from bench.harness import REPO
from bench.links import LinkRun, Series, answer_at_once
from drivers.links.opcua import OpcUaLink, OpcUaOptions
from vgripd.types import RobotTarget, Status

DEFAULT_JOBS = 1000
POSE = (412.5, -133.25, 287.0625, 0.1234, -2.9, 179.5)
BLOCK = 100
NS = "urn:vgripd:machine-vision"


# -- servers (this process) ----------------------------------------------------------------


async def link_server(pki: Path | None) -> OpcUaLink:
    security = ["Basic256Sha256_SignAndEncrypt"] if pki else ["None"]
    link = OpcUaLink("bench", OpcUaOptions.model_validate({
        "host": "127.0.0.1", "port": 0, "security": security, "allow_anonymous": True,
        "certificate_dir": str(pki) if pki else None}))
    target = RobotTarget("kuka", ("x", "y", "z", "a", "b", "c"), POSE)
    await link.open(answer_at_once(link, target, residuals={"fit_rms_mm": 0.01}))
    return link


async def bare_server(link: OpcUaLink) -> Server:
    """The peer, with the link's security: the same certificate, anonymous sessions."""
    server = Server()
    await server.init()
    server.set_endpoint("opc.tcp://127.0.0.1:0/bare")
    if link.certificate is not None:
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        await server.load_certificate(str(link.certificate))
        await server.load_private_key(str(link.certificate.parent / "vgripd-server-key.pem"))
    else:
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    server.set_identity_tokens([ua.AnonymousIdentityToken])
    idx = await server.register_namespace("urn:bench:bare")
    obj = await server.nodes.objects.add_object(ua.NodeId(ua.String("Bare"), ua.Int16(idx)),
                                                "Bare")
    out = [ua.Variant(int(Status.OK), ua.VariantType.UInt16),
           ua.Variant(list(POSE), ua.VariantType.Double)]

    async def locate(parent: ua.NodeId) -> list[ua.Variant]:
        return out

    await obj.add_method(ua.NodeId(ua.String("Bare.Locate"), ua.Int16(idx)), "Locate", locate,
                         [], [ua.VariantType.UInt16, ua.VariantType.Double])
    await server.start()
    return server


# -- client (child process) ------------------------------------------------------------------


async def secure(client: Client, server_cert: str, folder: Path) -> Client:
    from asyncua.crypto import security_policies

    client.application_uri = "urn:vgripd:bench:client"
    cert, key = await client.setup_self_signed_certificate(
        folder / "client-key.pem", folder / "client-cert.der", host_name="localhost")
    await client.set_security(security_policies.SecurityPolicyBasic256Sha256, str(cert),
                              str(key), server_certificate=server_cert,
                              mode=ua.MessageSecurityMode.SignAndEncrypt)
    return client


async def client_main(link_url: str, bare_url: str, jobs: int, server_cert: str) -> None:
    # a probe every 30 s (asyncua: every 1 s, 1 s to answer, which drops a loaded connection)
    lc, bc = Client(link_url, watchdog_intervall=30), Client(bare_url, watchdog_intervall=30)
    if server_cert:
        folder = Path(server_cert).parent.parent / "client"
        await secure(lc, server_cert, folder)
        await secure(bc, server_cert, folder)
    async with lc, bc:
        li = await lc.get_namespace_index(NS)
        bi = await bc.get_namespace_index("urn:bench:bare")

        def nid(path: str, idx: int) -> ua.NodeId:
            return ua.NodeId(ua.String(path), ua.Int16(idx))

        vs = lc.get_node(nid("VisionSystem", li))
        start = nid("VisionSystem.StartSingleJob", li)
        result = [lc.get_node(nid(f"VisionSystem.Result.{n}", li))
                  for n in ("RequestId", "Status", "Values", "JobId")]
        bare = bc.get_node(nid("Bare", bi))
        locate = nid("Bare.Locate", bi)

        async def link_job() -> tuple[float, int]:
            t0 = time.perf_counter()
            rid = await vs.call_method(start)
            reads = 0
            while True:
                reads += 1
                got = await lc.read_values(result)
                if got[0] == rid:
                    break
            dt = (time.perf_counter() - t0) * 1e3
            assert got[1] == Status.OK, got
            assert tuple(got[2]) == POSE, got
            return dt, reads

        async def bare_job() -> tuple[float, int]:
            t0 = time.perf_counter()
            status, values = await bare.call_method(locate)
            dt = (time.perf_counter() - t0) * 1e3
            assert status == Status.OK
            assert tuple(values) == POSE
            return dt, 0

        times: dict[str, list[float]] = {"link": [], "bare": []}
        reads: list[int] = []
        for job in (link_job, bare_job):  # warm-up, not counted
            for _ in range(20):
                await job()
        done = 0
        while done < jobs:
            n = min(BLOCK, jobs - done)
            for _ in range(n):
                dt, r = await link_job()
                times["link"].append(dt)
                reads.append(r)
            for _ in range(n):
                times["bare"].append((await bare_job())[0])
            done += n
    print(json.dumps({"times": times, "reads": reads}))


# -- report ----------------------------------------------------------------------------------


async def measure_mode(jobs: int, pki: Path | None) -> dict[str, Any]:
    link = await link_server(pki)
    bare = await bare_server(link)
    assert bare.bserver is not None
    link_url = f"opc.tcp://127.0.0.1:{link.port}/vgripd"
    bare_url = f"opc.tcp://127.0.0.1:{bare.bserver.port}/bare"
    cert = str(link.certificate) if link.certificate is not None else ""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "bench.links.opcua", "--client", link_url, bare_url, str(jobs),
        cert, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE)
    out, _ = await proc.communicate()
    await link.close()
    await bare.stop()
    assert proc.returncode == 0, "client failed"
    data: dict[str, Any] = json.loads(out)
    return data


async def measure(jobs: int) -> LinkRun:
    import asyncua

    runs: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        runs["None"] = await measure_mode(jobs, None)
        runs["Basic256Sha256 SignAndEncrypt"] = await measure_mode(jobs, Path(tmp) / "pki")
    series, notes = [], []
    for mode, data in runs.items():
        reads = data["reads"]
        peer = f"bare asyncua server, {mode}: one method call returning the result"
        series += [Series(f"vgripd opcua link, {mode}: StartSingleJob, poll Result until "
                          "RequestId", data["times"]["link"], against=peer),
                   Series(peer, data["times"]["bare"])]
        notes.append(f"{statistics.mean(reads):.2f} Read requests on average with {mode} "
                     f"(min {min(reads)}, max {max(reads)})")
    return LinkRun(
        heading="OPC UA link",
        setup=(f"{jobs} jobs per row, blocks of {BLOCK} alternating link and peer, both "
               "servers on one event loop in the bench process (anonymous sessions), asyncua "
               f"{getattr(asyncua, '__version__', '?')}'s client in a child process; the daemon "
               "side answers each trigger at once. Client, job sequence and peer: "
               "bench/links/opcua.py's docstring."),
        series=series,
        notes=[f"The link's job is the call plus the reads ({'; '.join(notes)}; one read means "
               "the stand-in had published before the first Read arrived): two round trips, "
               "the hand-off to the daemon's handler and the publish, against one round trip "
               "for the bare method. A client that waits on the ResultReady event or a "
               "subscription instead of polling pays its publishing interval instead of the "
               "reads."])


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--client":
        asyncio.run(client_main(sys.argv[2], sys.argv[3], int(sys.argv[4]),
                                sys.argv[5] if len(sys.argv) > 5 else ""))
    else:
        sys.exit("usage: python -m bench.links.opcua --client LINK_URL BARE_URL JOBS [CERT]")
