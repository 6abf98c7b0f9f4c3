"""Driver registry: a config ``type`` name -> the class that implements it, imported lazily.

A missing optional SDK breaks only the driver that needs it, with a clear ``DriverError``.
``vgripd`` reaches ``drivers/`` only through this table. ``link_problems`` is how the config
model (``vgripd.config``) judges the link sections against ``output.vendor`` when a config is
loaded, without importing ``drivers/`` itself; this module takes what it needs of the config from
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

LINKS: dict[str, str] = {
    "modbus_server": "drivers.links.modbus_server:ModbusServerLink",
    "modbus_client": "drivers.links.modbus_client:ModbusClientLink",
    "modbus_rtu": "drivers.links.modbus_rtu:ModbusRtuLink",
    "ur_rtde": "drivers.links.ur_rtde:URRtdeLink",
    "s7": "drivers.links.s7:S7Link",
    "robot_socket": "drivers.links.robot_socket:RobotSocketLink",
    "opcua": "drivers.links.opcua:OpcUaLink",
}

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
    link type whose class cannot send a CAPTURE (``takes_views`` is not set), since every
    job there is N CAPTUREs and such a link could only ever be refused."""
    if views == 1:
        return []
    able = sorted(t for t in LINKS if getattr(load_class(LINKS, "link", t), "takes_views",
                                              False))
    return [f'links[{i}].type = "{s.type}" cannot send CAPTURE, and vision.views = {views} '
            f"makes every job {views} CAPTUREs: use {', '.join(able)}"
            for i, s in enumerate(links)
            if s.type in LINKS and not getattr(load_class(LINKS, "link", s.type),
                                               "takes_views", False)]


def latch_problems(links: Sequence[DriverSection]) -> list[str]:
    """Why the link sections cannot serve a ``[conveyor]``: one line per register link (a link
    whose options have ``map_version``) left at a map version without the latch area (below
    4), whose every job would end BAD_REQUEST for want of the encoder count. Each line names
    the field; a value that is no map version at all is left to the link's own options."""
    problems = []
    for i, section in enumerate(links):
        if section.type not in LINKS:
            continue  # link_problems names it
        fields = load_class(LINKS, "link", section.type).Options.model_fields
        if "map_version" not in fields:
            continue
        given = section.options().get("map_version")
        version = fields["map_version"].default if given is None else given
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
    able = sorted(t for t in LINKS if getattr(load_class(LINKS, "link", t), "publishes_count",
                                              False))
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
    (its ``capabilities``), is a problem; each line names both fields. The driver options are
    not judged here (the daemon validates them when it builds the link). ``DriverError`` when
    a link's module cannot be imported.
    """
    conv = CONVENTIONS[vendor]
    shown = f'output.vendor = "{vendor}"' + (" (the default)" if vendor_is_default else "")
    problems = []
    for i, section in enumerate(links):
        field = f'links[{i}].type = "{section.type}"'
        if section.type not in LINKS:
            problems.append(f"{field}: unknown link type (known: {', '.join(sorted(LINKS))})")
            continue
        caps: LinkCapabilities = load_class(LINKS, "link", section.type).capabilities
        why = caps.refusal(conv)
        if why is None:
            continue
        carried = [name for name, c in CONVENTIONS.items() if caps.refusal(c) is None]
        hint = (f'set output.vendor = "{carried[0]}"' if len(carried) == 1
                else f"output.vendor may be {', '.join(carried)}")
        problems.append(f"{field} cannot carry {shown}: {why}; {hint}")
    return problems
