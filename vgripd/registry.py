"""Driver registry: a config ``type`` name -> the class that implements it, imported lazily.

A missing optional SDK breaks only the driver that needs it, with a clear ``DriverError``.
``vgripd`` reaches ``drivers/`` only through this table. What the config judges of a link type
(the pose it carries, CAPTURE, the belt's count, its register map) is data here
(``LINK_TRAITS``), so ``link_problems`` and the rules beside it judge the link sections when a
config is loaded without importing ``drivers/``; this module takes what it needs of the config from
``vgripd.configbase``, below both, so the two do not import each other.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from vgripd.configbase import DriverSection, format_validation_error
from vgripd.errors import ConfigError, DriverError
from vgripd.geometry.vendors import CONVENTIONS, Convention


@dataclass(frozen=True)
class LinkCapabilities:
    """What a link can hand its peer as a pose, declared by each link class (``capabilities``).

    A config is judged against it when it is loaded (``vgripd.registry.link_problems``): a link
    that cannot carry ``output.vendor`` is a config error, not a failure of every job.

    ``max_values``: the most pose values one result can carry.
    ``conventions``: the vendor conventions (``vgripd.geometry.vendors``) the peer understands;
    ``None``: any convention of at most ``max_values`` values (the link carries plain numbers).
    ``units``: what the peer receives, in words (for messages and docs).
    ``flange_pose``: how a request brings the robot's flange pose with it (a walked hand-eye
    calibration needs it); empty when it cannot.
    """

    max_values: int
    conventions: frozenset[str] | None = None
    units: str = "the convention's own fields and units"
    flange_pose: str = ""

    def refusal(self, conv: Convention) -> str | None:
        """Why a pose in ``conv`` cannot be carried; None when it can."""
        if self.conventions is not None and conv.name not in self.conventions:
            names = " or ".join(f'"{n}"' for n in sorted(self.conventions))
            return f"it carries only the {names} convention ({self.units})"
        if len(conv.fields) > self.max_values:
            return (f"it carries at most {self.max_values} pose values ({self.units}), "
                    f'"{conv.name}" has {len(conv.fields)} ({conv.fields[0]} .. {conv.fields[-1]})')
        return None


CAMERAS: dict[str, str] = {
    "replay": "drivers.cameras.replay:ReplayCamera",
    "synthetic": "drivers.cameras.synthetic:SyntheticCamera",
    "opencv": "drivers.cameras.opencv:OpenCVCamera",
    "genicam": "drivers.cameras.genicam:GenICamCamera",
    "pylon": "drivers.cameras.pylon:PylonCamera",
    "aravis": "drivers.cameras.aravis:AravisCamera",
    "multi": "drivers.cameras.multi:MultiCamera",
    "board": "drivers.cameras.board:BoardCamera",
}

#: The pose each link type carries (``LinkCapabilities``), declared here and taken by the link
#: classes, so that the config is judged without importing a driver. The texts name the wire
#: layout; tests/unit/test_registry.py checks them against it.
REGISTER_CAPABILITIES = LinkCapabilities(
    7, None, "VALUES registers 24-37, the convention's fields in its own units")
S7_CAPABILITIES = LinkCapabilities(
    7, None, "VALUES at block bytes 48-75, the convention's fields in its own units")
SOCKET_CAPABILITIES = LinkCapabilities(
    7, None, "answer words 6-12, the convention's fields in its own units",
    flange_pose="request CAPTURE_AT (4), words 4-10")
UR_CAPABILITIES = LinkCapabilities(
    6, frozenset({"ur"}), "x, y, z in m and rotation vector rx, ry, rz in rad: the robot "
    "program's p[x, y, z, rx, ry, rz]",
    flange_pose="RTDE's actual_TCP_pose, read with the request")
OPCUA_CAPABILITIES = LinkCapabilities(
    max(len(c.fields) for c in CONVENTIONS.values()), None,
    "Result.Values (Double array) with Result.ValueNames, the convention's fields in its own "
    "units")


@dataclass(frozen=True)
class LinkTraits:
    """A link type as the config judges it, without importing its driver.

    ``path``: ``"module:Class"``. ``capabilities``: the pose it carries (the class takes it from
    here). ``takes_views``: it can send CAPTURE, so it serves ``vision.views`` > 1.
    ``publishes_count``: it reads the belt's encoder count from its peer (``conveyor.trigger =
    "travel"``). ``map_version``: a register link's default map version (the latch area comes
    with 4); None for a link without a register map. tests/unit/test_registry.py checks every
    entry against its class.
    """

    path: str
    capabilities: LinkCapabilities
    takes_views: bool = False
    publishes_count: bool = False
    map_version: int | None = None


LINK_TRAITS: dict[str, LinkTraits] = {
    "modbus_server": LinkTraits("drivers.links.modbus_server:ModbusServerLink",
                                REGISTER_CAPABILITIES, True, True, 3),
    "modbus_client": LinkTraits("drivers.links.modbus_client:ModbusClientLink",
                                REGISTER_CAPABILITIES, True, True, 3),
    "modbus_rtu": LinkTraits("drivers.links.modbus_rtu:ModbusRtuLink",
                             REGISTER_CAPABILITIES, True, True, 3),
    "ur_rtde": LinkTraits("drivers.links.ur_rtde:URRtdeLink", UR_CAPABILITIES, True, False, 3),
    "s7": LinkTraits("drivers.links.s7:S7Link", S7_CAPABILITIES, True, True, 3),
    "robot_socket": LinkTraits("drivers.links.robot_socket:RobotSocketLink",
                               SOCKET_CAPABILITIES),
    "opcua": LinkTraits("drivers.links.opcua:OpcUaLink", OPCUA_CAPABILITIES),
}

LINKS: dict[str, str] = {name: traits.path for name, traits in LINK_TRAITS.items()}

#: What a link asks of its peer, where a table says more than the docs (the OPC UA nodes a PLC
#: reads and calls): a function of the driver's module, loaded as the classes are.
CONTRACTS: dict[str, str] = {
    "opcua": "drivers.links.opcua_vision:plc_contract",
}


def load_class(table: dict[str, str], kind: str, type_name: str) -> type[Any]:
    try:
        target = table[type_name]
    except KeyError:
        known = ", ".join(sorted(table))
        raise ConfigError(f"unknown {kind} type {type_name!r} (known: {known})") from None
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DriverError(f"{kind} driver {type_name!r} is not available: {err}") from None
    cls: type[Any] = getattr(module, attr)
    return cls


def validate_options(cls: type[Any], section: DriverSection, where: str) -> Any:
    """Validate a section's options against ``cls.Options`` (a pydantic model)."""
    try:
        return cls.Options.model_validate(section.options())
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, where)) from None


def views_problems(links: Sequence[DriverSection], views: int) -> list[str]:
    """Why the link sections cannot serve a cell of ``vision.views`` > 1: one line per known
    link type that cannot send a CAPTURE (``LinkTraits.takes_views``), since every job there is
    N CAPTUREs and such a link could only ever be refused."""
    if views == 1:
        return []
    able = sorted(t for t, traits in LINK_TRAITS.items() if traits.takes_views)
    return [f'links[{i}].type = "{s.type}" cannot send CAPTURE, and vision.views = {views} '
            f"makes every job {views} CAPTUREs: use {', '.join(able)}"
            for i, s in enumerate(links)
            if s.type in LINK_TRAITS and not LINK_TRAITS[s.type].takes_views]


def latch_problems(links: Sequence[DriverSection]) -> list[str]:
    """Why the link sections cannot serve a ``[conveyor]``: one line per register link (a link
    whose options have ``map_version``) left at a map version without the latch area (below
    4), whose every job would end BAD_REQUEST for want of the encoder count. Each line names
    the field; a value that is no map version at all is left to the link's own options."""
    problems = []
    for i, section in enumerate(links):
        if section.type not in LINK_TRAITS:
            continue  # link_problems names it
        default = LINK_TRAITS[section.type].map_version
        if default is None:
            continue
        given = section.options().get("map_version")
        version = default if given is None else given
        if isinstance(version, int) and not isinstance(version, bool) and version < 4:
            shown = f"{version}" + (" (the default)" if given is None else "")
            problems.append(
                f"links[{i}].map_version = {shown}: the {section.type} link then carries no "
                "encoder count, and [conveyor] needs the count latched with every request: "
                'set map_version = 4 (docs/registers.md, "Conveyor: map version 4")')
    return problems


def travel_problems(links: Sequence[DriverSection], views: int) -> list[str]:
    """Why the link sections cannot serve ``conveyor.trigger = "travel"``: no link publishes
    the belt's encoder count (a link class with ``publishes_count``: the register links, read
    at map version 4, which ``latch_problems`` asks for), or every job would be N views."""
    able = sorted(t for t, traits in LINK_TRAITS.items() if traits.publishes_count)
    problems = []
    if not any(s.type in able for s in links):
        have = ", ".join(f'links[{i}].type = "{s.type}"' for i, s in enumerate(links)) or "none"
        problems.append(f'conveyor.trigger = "travel": no link publishes the belt\'s encoder '
                        f"count (links: {have}): add one of {', '.join(able)} with "
                        "map_version = 4, the PLC writing LATCH_COUNT")
    if views > 1:
        problems.append(f'conveyor.trigger = "travel" with vision.views = {views}: a job started '
                        "by the belt's travel is one image")
    return problems


def link_problems(links: Sequence[DriverSection], vendor: str,
                  vendor_is_default: bool = False) -> list[str]:
    """Why the link sections cannot work with ``output.vendor = vendor``, one line per section.

    A section of an unknown type, or whose link class cannot carry the vendor's convention
    (``LinkTraits.capabilities``), is a problem; each line names both fields. The driver
    options are not judged here (the daemon validates them when it builds the link); no driver
    is imported, so a link whose optional SDK is missing is judged all the same.
    """
    conv = CONVENTIONS[vendor]
    shown = f'output.vendor = "{vendor}"' + (" (the default)" if vendor_is_default else "")
    problems = []
    for i, section in enumerate(links):
        field = f'links[{i}].type = "{section.type}"'
        if section.type not in LINKS:
            problems.append(f"{field}: unknown link type (known: {', '.join(sorted(LINKS))})")
            continue
        caps = LINK_TRAITS[section.type].capabilities
        why = caps.refusal(conv)
        if why is None:
            continue
        carried = [name for name, c in CONVENTIONS.items() if caps.refusal(c) is None]
        hint = (f'set output.vendor = "{carried[0]}"' if len(carried) == 1
                else f"output.vendor may be {', '.join(carried)}")
        problems.append(f"{field} cannot carry {shown}: {why}; {hint}")
    return problems
