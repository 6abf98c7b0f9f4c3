"""Imports run downwards only (README "Layout"): each room of vgripd/ imports only the rooms
below it, geometry nothing but the vocabulary, and vgripd/ never imports drivers/ (the registry
names driver classes as strings and imports them lazily); and no module of vgripd/ or drivers/
reaches itself again through its imports (no import circles). Every import statement counts,
wherever it stands: a function-level import or one under ``if TYPE_CHECKING:`` closes a circle
just as a top-level one does."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO

# Bottom first. A module may import its own room and any room listed before it.
LAYERS = [
    {"types", "errors"},
    {"geometry"},
    {"serialize", "imagefiles", "redaction", "resources", "configbase", "configsnapshot",
     "config", "registry"},
    {"vision"},
    {"calib"},
    {"peer"},
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



# The rooms of vgripd/service/, bottom first (README "Layout"): the same rule one level down.
SERVICE_ROOMS = ["host", "links", "worker", "jobs", "ops", "web", "daemon"]
SERVICE_LEVEL = {room: i for i, room in enumerate(SERVICE_ROOMS)}
SERVICE_MODULES = sorted((REPO / "vgripd" / "service").rglob("*.py"))


def _service_room(module: str) -> str:
    """``vgripd.service.jobs.runner`` -> ``jobs``; ``vgripd.service`` -> ``__init__``."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 else "__init__"


@pytest.mark.parametrize("path", SERVICE_MODULES, ids=lambda p: str(p.relative_to(REPO)))
def test_service_rooms_import_downwards(path: Path) -> None:
    here = _service_room(".".join(path.relative_to(REPO).with_suffix("").parts))
    if here == "__init__":
        return
    bad = [f"line {line}: {name} ({here} is below {_service_room(name)})"
           for line, name in _imports(path)
           if name.startswith("vgripd.service.")
           and SERVICE_LEVEL.get(_service_room(name), len(SERVICE_ROOMS)) > SERVICE_LEVEL[here]]
    assert not bad, f"{path.relative_to(REPO)} imports upwards:\n" + "\n".join(bad)


def test_every_service_room_has_a_level() -> None:
    rooms = {_service_room(".".join(p.relative_to(REPO).with_suffix("").parts))
             for p in SERVICE_MODULES}
    assert rooms - {"__init__"} <= set(SERVICE_LEVEL), rooms - set(SERVICE_LEVEL)

@pytest.mark.parametrize("path", sorted((REPO / "drivers").rglob("*.py")),
                         ids=lambda p: str(p.relative_to(REPO)))
def test_drivers_do_not_use_the_service_or_cli(path: Path) -> None:
    """Drivers build on the core (vocabulary, geometry, config, vision, the link contract and
    its helpers); they never reach into the daemon, the simulators or the CLI."""
    forbidden_service = {"vgripd.service.daemon"}
    bad = [f"line {line}: {name}" for line, name in _imports(path)
           if name.startswith("vgripd.") and (
               _room(name) in {"cli", "sim", "__main__"} or name in forbidden_service)]
    assert not bad, "\n".join(bad)


# --- import circles -------------------------------------------------------------------------

PACKAGES = ("vgripd", "drivers")


def module_name(path: Path, root: Path = REPO) -> str:
    """``vgripd/service/web/__init__.py`` -> ``vgripd.service.web``."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(source: str, name: str, is_package: bool, known: set[str]) -> set[str]:
    """The modules among ``known`` that module ``name`` imports anywhere in ``source``.

    Every Import/ImportFrom node counts, nested ones included (function bodies,
    ``if TYPE_CHECKING:``, try blocks). Relative imports are resolved against ``name``;
    ``from pkg import x`` is an import of ``pkg.x`` when that is a module and of ``pkg`` (its
    ``__init__``) otherwise; importing a package is importing its ``__init__``."""
    package = name if is_package else name.rpartition(".")[0]
    out: set[str] = set()

    def add(target: str) -> None:
        # The nearest known module at or above ``target`` (``a.b.func`` is not a module).
        while target and target not in known:
            target = target.rpartition(".")[0]
        if target and target != name:
            out.add(target)

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                full = f"{base}.{alias.name}"
                add(full if full in known else base)
    return out


def import_graph(sources: dict[str, tuple[str, bool]]) -> dict[str, set[str]]:
    """``{module: (source, is_package)}`` -> ``{module: modules it imports among them}``."""
    known = set(sources)
    return {name: imported_modules(src, name, is_pkg, known)
            for name, (src, is_pkg) in sources.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One circle through each strongly connected component of more than one module (or a
    module importing itself), as ``[a, b, ..., a]``; empty when the graph is acyclic."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0

    def strongconnect(v: str) -> None:  # Tarjan; the graph is a few hundred modules deep at most
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)

    cycles = []
    for comp in components:
        # Shortest path back to the start inside the component, for a readable message.
        members, start = set(comp), comp[0]
        prev: dict[str, str] = {}
        frontier = [start]
        found = None
        while frontier and found is None:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & members):
                    if w == start:
                        found = v
                        break
                    if w not in prev:
                        prev[w] = v
                        nxt.append(w)
                if found is not None:
                    break
            frontier = nxt
        path = [start]
        v = found
        while v is not None and v != start:
            path.append(v)
            v = prev.get(v)
        cycles.append([start, *reversed(path[1:]), start])
    return sorted(cycles)


def repo_sources(root: Path = REPO) -> dict[str, tuple[str, bool]]:
    return {module_name(p, root): (p.read_text(), p.name == "__init__.py")
            for pkg in PACKAGES for p in sorted((root / pkg).rglob("*.py"))}


def test_no_import_circles() -> None:
    cycles = find_cycles(import_graph(repo_sources()))
    assert not cycles, "import circles (move the shared part down into its own module):\n" + \
        "\n".join(" -> ".join(c) for c in cycles)


def test_circle_finder_sees_hidden_imports() -> None:
    """The checker itself: circles closed by a TYPE_CHECKING import, a function-level import,
    a relative import and an import of a package's ``__init__`` are all found."""
    sources = {
        "vgripd": ("", True),
        "vgripd.config": ("from vgripd.registry import lookup\n", False),
        "vgripd.registry": ("from typing import TYPE_CHECKING\n"
                            "if TYPE_CHECKING:\n    from vgripd.config import Config\n", False),
        "vgripd.service": ("", True),
        "vgripd.service.daemon": ("from vgripd.service.web import WebServer\n", False),
        "vgripd.service.web": ("from vgripd.service.web.app import WebServer\n", True),
        "vgripd.service.web.app": ("def f():\n    from ..daemon import configure_logging\n",
                                   False),
        "vgripd.vision": ("", True),
        "vgripd.vision.pipeline": ("from . import diagnosis\n", False),
        "vgripd.vision.diagnosis": ("import vgripd.vision.pipeline as p\n", False),
        "vgripd.vision.found": ("import numpy\n", False),
        "vgripd.vision.picklist": ("from vgripd.vision.found import Found\n", False),
    }
    graph = import_graph(sources)
    assert graph["vgripd.service.web.app"] == {"vgripd.service.daemon"}
    assert graph["vgripd.vision.pipeline"] == {"vgripd.vision.diagnosis"}
    assert graph["vgripd.service.daemon"] == {"vgripd.service.web"}
    assert find_cycles(graph) == [
        ["vgripd.config", "vgripd.registry", "vgripd.config"],
        ["vgripd.service.daemon", "vgripd.service.web", "vgripd.service.web.app",
         "vgripd.service.daemon"],
        ["vgripd.vision.diagnosis", "vgripd.vision.pipeline", "vgripd.vision.diagnosis"],
    ]
    # Taking the shared part down breaks the circle.
    sources["vgripd.registry"] = ("import vgripd.errors\n", False)
    assert ["vgripd.config", "vgripd.registry", "vgripd.config"] not in \
        find_cycles(import_graph(sources))


def test_every_import_of_our_own_names_resolves() -> None:
    """Every ``from vgripd/drivers/tests/bench... import name`` names something that exists,
    function-level imports included (mypy does not read tests/ and bench/, and a module moved
    between rooms leaves such an import pointing at its old home)."""
    import importlib

    ours = ("vgripd", "drivers", "tests", "bench")
    bad = []
    for root in ours:
        for path in sorted((REPO / root).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not (isinstance(node, ast.ImportFrom) and node.module and node.level == 0
                        and node.module.split(".")[0] in ours):
                    continue
                where = f"{path.relative_to(REPO)}:{node.lineno}"
                try:
                    module = importlib.import_module(node.module)
                except ImportError as err:
                    if (err.name or "").split(".")[0] not in ours:
                        continue  # an optional SDK missing here (PyGObject, pypylon)
                    bad.append(f"{where}: {node.module}: {err}")
                    continue
                for alias in node.names:
                    if hasattr(module, alias.name):
                        continue
                    try:
                        importlib.import_module(f"{node.module}.{alias.name}")
                    except ImportError:
                        bad.append(f"{where}: {node.module} has no {alias.name}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(("tests_root", "code_root"), [("tests/unit", "vgripd"),
                                                       ("tests/drivers", "drivers")])
def test_tests_sit_where_their_code_sits(tests_root: str, code_root: str) -> None:
    """Every folder of unit and driver tests is a package of the code it tests (tests/unit/
    service/jobs/ for vgripd/service/jobs/), so a module's tests are found by its path."""
    strays = [str(d.relative_to(REPO)) for d in sorted((REPO / tests_root).rglob("*"))
              if d.is_dir() and d.name != "__pycache__" and any(d.glob("test_*.py"))
              and not (REPO / code_root / d.relative_to(REPO / tests_root) / "__init__.py"
                       ).is_file()]
    assert strays == [], f"test folders with no package of that path under {code_root}/"
