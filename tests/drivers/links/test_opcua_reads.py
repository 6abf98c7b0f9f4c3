"""OpcUaLink: what a client reads before the first result, through asyncua's own client over
TCP on 127.0.0.1 (a Read naming ``Result.Timestamp`` before the first result failed
whole with BadInternalError and an AttributeError logged at ERROR). The older namespace alone
(``models = ["vgripd"]``): these are its variables."""

from __future__ import annotations

import datetime
import logging

import pytest
from asyncua import ua

from drivers.links.opcua import OpcUaLink, OpcUaOptions
from drivers.links.opcua_space import RESULT_DATA, RESULT_LAST
from tests.conftest import ua_client

pytestmark = pytest.mark.timeout(60)


async def test_every_result_variable_reads_before_the_first_result(
        caplog: pytest.LogCaptureFixture) -> None:
    link = OpcUaLink("cell", OpcUaOptions.model_validate({
        "host": "127.0.0.1", "port": 0, "security": ["None"], "allow_anonymous": True,
        "models": ["vgripd"]}))
    await link.open(lambda trigger: None)
    names = [name for name, *_ in RESULT_DATA + RESULT_LAST]
    try:
        with caplog.at_level(logging.ERROR):
            async with ua_client(f"opc.tcp://127.0.0.1:{link.port}/vgripd") as client:
                nodes = [client.get_node(ua.NodeId(ua.String(f"VisionSystem.Result.{name}"),
                                                   ua.Int16(2))) for name in names]
                values = await client.read_values(nodes)  # one Read request for all of them
    finally:
        await link.close()
    got = dict(zip(names, values, strict=True))
    assert got["Timestamp"] == datetime.datetime(1601, 1, 1, tzinfo=datetime.UTC)
    assert (got["RequestId"], got["Status"], got["Count"], got["Index"]) == (0, 0, 0, 0)
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []
