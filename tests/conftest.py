"""Shared test fixtures.

Autouse fixtures undo a test's in-process logging set-up, and fail any test that leaves a
thread behind (a leaked supervisor or executor would keep a real daemon from shutting down) or
an asyncio task still pending on its event loop after its teardown (a daemon, link or peer that
does not end what it started); each waits a few seconds first, so a busy machine is no
failure.

Tests that need something from outside the repository (the public datasets, a system tool such
as ``mbpoll`` or ``socat``) go through :func:`need` / :func:`need_tool` / the ``datasets``
fixture: on a developer's machine they skip with one line saying what to install or where to put
the data; with ``VGRIPD_REQUIRE_ALL=1`` (set by ``.ci/run``) the same line is a failure, so CI
always runs them.

Property tests (hypothesis) run under one of two profiles, chosen by ``VGRIPD_HYPOTHESIS``:

- ``repeatable`` (the default: ``make test``, CI): every run draws the same examples (a seed
  from each test's own source), so the README's test command passes or fails the same way on
  every machine and every run; no deadline and no "too slow" health check, which would turn a
  busy machine into a failure. A case found once is kept as an ``@example(...)`` on its test.
- ``explore`` (``make explore``: the property tests' files, ``ROUNDS`` times, 10 by default):
  fresh random examples on every run, failures stored in ``.hypothesis/`` and replayed first the
  next time: for finding new cases, each to be pinned as an ``@example`` when found.
"""

from __future__ import annotations

import asyncio
import fcntl
import inspect
import logging
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

REPO = Path(__file__).resolve().parents[1]
REQUIRE_ALL = os.environ.get("VGRIPD_REQUIRE_ALL", "") not in ("", "0")

settings.register_profile("repeatable", derandomize=True, database=None, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow], print_blob=True)
settings.register_profile("explore", derandomize=False, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow], print_blob=True)
settings.load_profile(os.environ.get("VGRIPD_HYPOTHESIS", "repeatable"))


def datasets_dir() -> Path | None:
    """The public datasets: ``$VGRIPD_DATASETS``, else ``../shared/datasets`` beside the clone."""
    env = os.environ.get("VGRIPD_DATASETS")
    folder = Path(env) if env else REPO.parent / "shared" / "datasets"
    return folder if folder.is_dir() else None


def need(ok: bool, what: str) -> None:
    """Skip (fail under VGRIPD_REQUIRE_ALL=1) with the one line ``what`` unless ``ok``."""
    if ok:
        return
    if REQUIRE_ALL:
        pytest.fail(f"{what} (VGRIPD_REQUIRE_ALL=1 makes this a failure)", pytrace=False)
    pytest.skip(what)


def need_camera_sdk(config: Path) -> None:
    """Skip (fail under VGRIPD_REQUIRE_ALL=1) when ``config``'s camera driver needs an SDK that
    is not installed: judging its options imports the driver (aravis: PyGObject)."""
    import importlib.util
    import tomllib

    kind = tomllib.loads(config.read_text()).get("camera", {}).get("type")
    if kind == "aravis":
        need(importlib.util.find_spec("gi") is not None,
             "needs PyGObject for the aravis driver: apt-get install gir1.2-aravis-0.8 "
             "libgirepository1.0-dev libcairo2-dev pkg-config gcc; pip install -e '.[aravis]'")


def need_tool(name: str, package: str | None = None) -> str:
    """The path of system tool ``name``; skips with the apt-get line that installs it."""
    path = shutil.which(name)
    need(path is not None, f"needs {name}: apt-get install {package or name}")
    assert path is not None
    return path


_SLOT_FOLDER = Path(tempfile.gettempdir()) / "vgripd-test-slots"
_slot: tuple[int, int] | None = None  # (second octet, the lock file's descriptor held open)


def loopback_slot() -> int:
    """This test process's own second octet of 127.0.0.0/8 (1 .. 254), held by an ``flock``
    on a file in the temporary folder while the process lives: two test runs on one machine (a
    suite beside a suite, each with its xdist workers) never share an address. Needed where a
    peer has a fixed port: the RTDE controller's 30004, which ur_rtde always dials."""
    global _slot
    if _slot is None:
        _SLOT_FOLDER.mkdir(exist_ok=True)
        for n in range(1, 255):
            fd = os.open(_SLOT_FOLDER / f"{n}.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            _slot = (n, fd)
            break
        else:
            raise RuntimeError(f"all 254 loopback slots in {_SLOT_FOLDER} are held")
    return _slot[0]


def lo(address: str) -> str:
    """``127.0.A.B`` moved into this process's own slot: ``127.<slot>.A.B`` (loopback_slot)."""
    parts = address.split(".")
    if len(parts) != 4 or parts[:2] != ["127", "0"]:
        raise ValueError(f"lo({address!r}): expected 127.0.A.B")
    return f"127.{loopback_slot()}.{parts[2]}.{parts[3]}"


#: asyncua's client watchdog in the tests: a probe of the server every this many seconds, given
#: as long to answer. Its default (1 s, answered within 1 s) takes a busy machine for a dead
#: server and drops the connection under a request in flight.
UA_WATCHDOG_S = 30.0


def ua_client(url: str, timeout: float = 30.0, **options: object) -> Any:
    """asyncua's ``Client`` as the tests use it (``UA_WATCHDOG_S``, ``timeout`` per request)."""
    from asyncua import Client

    return Client(url, timeout=timeout, watchdog_intervall=UA_WATCHDOG_S, **options)


async def stop_task(task: asyncio.Task[object], wait_s: float = 10.0) -> None:
    """Cancel ``task`` and wait until it has ended, cancelling again if a cancel was lost (the
    links' ``end_task``: Python 3.11's ``asyncio.wait_for``, inside snap7's asyncio client among
    others, drops a cancel that arrives as the awaited read completes); at most ``wait_s``."""
    from vgripd.service.links.supervisor import end_task

    async with asyncio.timeout(wait_s):
        await end_task(task)


@pytest.fixture(autouse=True)
def root_logging_restored() -> Iterator[None]:
    """Undoes ``configure_logging`` (``logging.basicConfig(force=True)``) of a test that runs
    ``vgripd run`` or the like in-process: its handler writes to that test's captured stderr,
    which pytest closes, and every later log line of the process would print a "Logging error"
    traceback (slow enough to hold up an event loop for a second)."""
    root, pymodbus = logging.getLogger(), logging.getLogger("pymodbus")
    handlers, levels = list(root.handlers), (root.level, pymodbus.level)
    yield
    for handler in root.handlers[:]:  # pytest's own are subclasses, added and removed by it
        if type(handler) is logging.StreamHandler and handler not in handlers:
            root.removeHandler(handler)
    root.setLevel(levels[0])
    pymodbus.setLevel(levels[1])


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while True:
        leaked = [
            t for t in threading.enumerate()
            if t not in before and t.is_alive() and not t.daemon
        ]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not leaked, f"test leaked threads: {[t.name for t in leaked]}"


_RUNNERS = tuple(f"_{scope}_scoped_runner" for scope in ("function", "class", "module",
                                                          "package", "session"))


def _task_where(task: asyncio.Task[object]) -> str:
    """``task``'s name and its coroutine, with the file and line that defines it."""
    coro = task.get_coro()
    what = getattr(coro, "__qualname__", repr(coro))
    code = getattr(coro, "cr_code", None)
    where = f" {code.co_filename}:{code.co_firstlineno}" if code is not None else ""
    return f"{task.get_name()} ({what}{where})"


def _async_fixture_runner(request: pytest.FixtureRequest) -> str | None:
    """The loop runner a plain (sync) test's async fixtures run on, or None if it has none.
    pytest-asyncio requests that runner only while it sets such a fixture up, so it is not
    among the test's fixture names: it is found from the fixtures' own definitions."""
    default = request.config.getini("asyncio_default_fixture_loop_scope")
    defs = getattr(getattr(request.node, "_fixtureinfo", None), "name2fixturedefs", {})
    for name in request.fixturenames:
        for fixturedef in defs.get(name, ())[-1:]:  # the definition the test gets
            func = fixturedef.func
            if inspect.iscoroutinefunction(func) or inspect.isasyncgenfunction(func):
                scope = getattr(func, "_loop_scope", None) or default or fixturedef.scope
                return f"_{scope}_scoped_runner"
    return None


@pytest.fixture(autouse=True)
def no_leaked_tasks(request: pytest.FixtureRequest, no_leaked_threads: None) -> Iterator[None]:
    """Fails a test that leaves tasks pending on its event loop once its own fixtures are torn
    down (pytest-asyncio would cancel them silently when it closes the loop). Requesting the
    test's loop runner here sets it up before, and tears it down after, every other fixture of
    the test; the loop is run for up to 2 s first, for tasks that are still ending. It needs
    ``no_leaked_threads`` so that the thread check comes after the loop has closed (and with it
    the loop's default executor, whose threads are no leak)."""
    runner_name = next((name for name in _RUNNERS if name in request.fixturenames),
                       None) or _async_fixture_runner(request)
    if runner_name is None:  # a test without an event loop
        yield
        return
    loop: asyncio.AbstractEventLoop = request.getfixturevalue(runner_name).get_loop()
    before = asyncio.all_tasks(loop)
    yield

    async def pending(wait_s: float) -> list[asyncio.Task[object]]:
        deadline = time.monotonic() + wait_s
        while True:
            left = [t for t in asyncio.all_tasks()
                    if t is not asyncio.current_task() and t not in before]
            if not left or time.monotonic() > deadline:
                return left
            await asyncio.sleep(0.02)

    leaked = loop.run_until_complete(pending(2.0))
    if not leaked:
        return
    names = [_task_where(t) for t in leaked]
    for task in leaked:
        task.cancel()
    loop.run_until_complete(asyncio.wait(leaked, timeout=5.0))
    pytest.fail(f"test leaked asyncio tasks: {names}", pytrace=False)


@pytest.fixture(scope="session")
def datasets() -> Path:
    """The public calibration datasets (see each folder's PROVENANCE.md)."""
    folder = datasets_dir()
    need(folder is not None,
         "needs the public datasets: set VGRIPD_DATASETS=/path/to/datasets "
         "or put them at ../shared/datasets beside the clone")
    assert folder is not None
    return folder


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files with a ``slow`` test first, the longest first (``slow(minutes=N)``: a file's whole
    time on a busy machine, 1 when not given), their tests in their order. ``make test`` hands whole
    files to its processes in this order (``--dist loadfile``): the long ones start at once and
    the short ones fill the gaps at the end, instead of one long file started last holding up
    the end of the run."""
    minutes: dict[Path, float] = {}
    for item in items:
        mark = item.get_closest_marker("slow")
        if mark is not None:
            minutes[item.path] = max(minutes.get(item.path, 0.0), mark.kwargs.get("minutes", 1))
    items.sort(key=lambda item: -minutes.get(item.path, 0.0))

