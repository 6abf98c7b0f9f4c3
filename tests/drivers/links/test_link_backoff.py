"""The back-off options every reconnecting link shares (``BackoffOptions``): each link's
documented defaults, and one check that names the field when the bounds cannot work."""

from __future__ import annotations

import pytest

from vgripd.configbase import DriverSection
from vgripd.errors import ConfigError
from vgripd.registry import LINKS, load_class, validate_options

#: type, the options it needs, its documented (initial, max) back-off in s
LINKS_THAT_RECONNECT = [
    ("modbus_client", {"host": "127.0.0.1"}, (0.1, 5.0)),  # docs/modbus_client.md
    ("s7", {"host": "127.0.0.1", "db": 1}, (0.1, 5.0)),  # docs/s7.md
    ("robot_socket", {"mode": "client", "host": "127.0.0.1"}, (0.2, 10.0)),  # docs/robot_socket.md
    ("ur_rtde", {"host": "127.0.0.1"}, (0.2, 10.0)),  # docs/ur_rtde.md
    ("modbus_rtu", {"port": "/dev/ttyUSB0"}, (0.5, 10.0)),  # a serial adapter
]


def section(kind: str, options: dict[str, object]) -> DriverSection:
    return DriverSection.model_validate({"type": kind, **options})


@pytest.mark.parametrize(("kind", "needs", "defaults"), LINKS_THAT_RECONNECT,
                         ids=[t[0] for t in LINKS_THAT_RECONNECT])
def test_each_link_keeps_its_documented_back_off(
        kind: str, needs: dict[str, object], defaults: tuple[float, float]) -> None:
    options = validate_options(load_class(LINKS, "link", kind), section(kind, needs), "links.0")
    assert (options.backoff_initial_s, options.backoff_max_s) == defaults


@pytest.mark.parametrize(("kind", "needs", "defaults"), LINKS_THAT_RECONNECT,
                         ids=[t[0] for t in LINKS_THAT_RECONNECT])
def test_a_max_below_the_initial_back_off_is_refused_naming_the_field(
        kind: str, needs: dict[str, object], defaults: tuple[float, float]) -> None:
    bad = section(kind, {**needs, "backoff_initial_s": 2.0, "backoff_max_s": 1.0})
    with pytest.raises(ConfigError) as err:
        validate_options(load_class(LINKS, "link", kind), bad, "links.3")
    assert "links.3: backoff_max_s: Value error, 1 is below backoff_initial_s = 2" in str(err.value)
