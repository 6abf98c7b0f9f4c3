"""Imports run downwards only (README "Layout"): each room of vgripd/ imports only the rooms
below it, geometry nothing but the vocabulary, and vgripd/ never imports drivers/ (the registry
names driver classes as strings and imports them lazily)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO

# Bottom first. A module may import its own room and any room listed before it.
LAYERS = [
    {"types", "errors"},
    {"geometry"},
    {"serialize", "imagefiles", "config", "registry"},
    {"vision"},
    {"calib"},
    {"service"},
    {"sim"},
    {"cli", "__main__"},
]
LEVEL = {room: i for i, rooms in enumerate(LAYERS) for room in rooms}


def _room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "vgripd":
                out += [(node.lineno, f"vgripd.{alias.name}") for alias in node.names]
            else:
                out.append((node.lineno, node.module))
    return out


MODULES = sorted((REPO / "vgripd").rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(REPO)))
def test_imports_run_downwards(path: Path) -> None:
    here = _room("." .join(path.relative_to(REPO).with_suffix("").parts))
    if here == "__init__":
        return
    level = LEVEL[here]
    bad = []
    for line, name in _imports(path):
        if name.split(".")[0] == "drivers":
            bad.append(f"line {line}: {name} (vgripd reaches drivers/ only through the registry)")
        elif name.startswith("vgripd."):
            room = _room(name)
            if room != here and LEVEL.get(room, -1) > level:
                bad.append(f"line {line}: {name} ({here} is below {room})")
    assert not bad, f"{path.relative_to(REPO)} imports upwards:\n" + "\n".join(bad)


def test_every_room_has_a_level() -> None:
    rooms = {_room("vgripd." + p.relative_to(REPO / "vgripd").with_suffix("").parts[0])
             for p in MODULES}
    assert rooms - {"__init__"} <= set(LEVEL), rooms - set(LEVEL)


@pytest.mark.parametrize("path", sorted((REPO / "drivers").rglob("*.py")),
                         ids=lambda p: str(p.relative_to(REPO)))
def test_drivers_do_not_use_the_service_or_cli(path: Path) -> None:
    """Drivers build on the core (vocabulary, geometry, config, vision, the link contract and
    its helpers); they never reach into the daemon, the simulators or the CLI."""
    forbidden_service = {"vgripd.service.daemon", "vgripd.service.statusapi"}
    bad = [f"line {line}: {name}" for line, name in _imports(path)
           if name.startswith("vgripd.") and (
               _room(name) in {"cli", "sim", "__main__"} or name in forbidden_service)]
    assert not bad, "\n".join(bad)
