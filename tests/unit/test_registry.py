"""The registry's link traits are data the config is judged by without importing a driver:
each entry is checked here against its class (what it declares, its options' defaults) and
the capability texts against the wire layouts they name."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO
from vgripd.geometry.vendors import CONVENTIONS
from vgripd.peer import socket_frames
from vgripd.peer.registers import MAX_VALUES, Reg
from vgripd.registry import (
    LINK_TRAITS,
    LINKS,
    OPCUA_CAPABILITIES,
    REGISTER_CAPABILITIES,
    S7_CAPABILITIES,
    SOCKET_CAPABILITIES,
    UR_CAPABILITIES,
    load_class,
)


@pytest.mark.parametrize("name", sorted(LINK_TRAITS))
def test_each_entry_is_what_its_class_declares(name: str) -> None:
    traits = LINK_TRAITS[name]
    cls = load_class(LINKS, "link", name)
    assert f"{cls.__module__}:{cls.__name__}" == traits.path
    assert cls.capabilities == traits.capabilities
    assert cls.takes_views is traits.takes_views
    assert cls.publishes_count is traits.publishes_count
    field = cls.Options.model_fields.get("map_version")
    assert (None if field is None else field.default) == traits.map_version


def test_the_capability_texts_name_the_wire_layouts() -> None:
    first, last = Reg.VALUES, Reg.VALUES + 2 * MAX_VALUES - 1  # float32: two registers a value
    assert REGISTER_CAPABILITIES.max_values == MAX_VALUES
    assert f"registers {first}-{last}" in REGISTER_CAPABILITIES.units
    assert S7_CAPABILITIES.max_values == MAX_VALUES
    assert f"bytes {2 * Reg.VALUES}-{2 * Reg.FIT_RMS - 1}" in S7_CAPABILITIES.units
    assert SOCKET_CAPABILITIES.max_values == socket_frames.N_VALUES
    assert OPCUA_CAPABILITIES.max_values == max(len(c.fields) for c in CONVENTIONS.values())
    assert UR_CAPABILITIES.conventions == frozenset({"ur"})
    assert UR_CAPABILITIES.max_values == len(CONVENTIONS["ur"].fields)


def test_a_config_is_judged_without_importing_a_link_driver() -> None:
    """Loading and judging a config with every link type, views > 1 and a conveyor imports no
    driver module (a missing optional SDK, asyncua or snap7, is no config error)."""
    code = (
        "import sys\n"
        "from vgripd.configbase import DriverSection\n"
        "from vgripd.registry import LINK_TRAITS, latch_problems, link_problems, "
        "travel_problems, views_problems\n"
        "links = [DriverSection(type=t) for t in LINK_TRAITS]\n"
        "assert views_problems(links, 2) and latch_problems(links)\n"
        "travel_problems(links, 1); link_problems(links, 'kuka')\n"
        "print(sorted(m for m in sys.modules if m.startswith('drivers')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=120, check=True).stdout
    assert out.strip() == "[]"
