"""Apply a judged config without a restart (``systemctl reload vgripd``: SIGHUP; the web view's
reload and every save). The transaction around it (one lock, candidate files, the judge, the
commit) and the audit are ``vgripd.service.host.configtxn``'s (docs/web.md, "Reload, tuning and
audit"; "Writing the config: one transaction").

A reload:

1. judges a byte snapshot of the config files in full, as ``vgripd check --running`` does
   (fields, drivers, every recipe calibrated and taught, the scene, the replay samples), in a
   child process so that the daemon's event loop keeps answering the PLC while the pipelines
   are built and run;
2. refused: the running config stays, the reason goes to the log and to the page
   (``Outcome.message``), and the audit lists it;
3. accepted: the change is applied *between jobs* (it waits until no job runs and no several-view
   job waits for a view): the daemon's config, its recipes on every link, the RECALIBRATE
   threshold and the pipelines (rebuilt in the worker process, which keeps its camera; in the
   daemon when ``daemon.worker = false``) and each recipe's ``[conveyor]`` (a changed or added
   belt starts with an empty part queue, an unchanged one keeps its queue, a removed one is
   gone). PLC and robot connections are not touched.

What only a restart can change: the camera (``camera``), the links (``links``: ports,
addresses, drivers), the web view (``status``), the recorder (``record``) and the service
(``daemon``). A reload keeps those sections as they run and names each changed key as needing a
restart (``Outcome.restart``); the rest is applied. The setup page's "Restart the daemon now"
(``restart_between_jobs``) stops the daemon between jobs to be started again on the saved files.

Every reload and save, applied or refused, is one audit entry: wall time, who asked (``SIGHUP``
or the web client's address), the outcome and a diff of the effective config (secrets
redacted), logged as one line each and listed on the page (``GET /api/audit``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from vgripd.config import Config, config_from_dict
from vgripd.errors import ConfigError
from vgripd.redaction import redact
from vgripd.service.host.configtxn import ConfigWriter, Outcome
from vgripd.service.jobs.beltlines import belt_lines
from vgripd.service.links.protocol import tell_links
from vgripd.service.worker.process import WorkerError

log = logging.getLogger("vgripd.reload")

#: Sections a reload cannot apply: their objects (camera driver, link servers and clients, the
#: web server, the recorder, the job machinery) are built once at start.
RESTART_SECTIONS = ("camera", "links", "status", "record", "daemon")
#: A reload waits this long for the running job (or several-view job) to end.
IDLE_TIMEOUT_S = 3600.0
#: ``vgripd run``'s exit status after a restart asked for (the setup page's "Restart the daemon
#: now"): EX_TEMPFAIL, so systemd's ``Restart=on-failure`` starts the service again.
EXIT_RESTART = 75


def _flat(data: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(data, Mapping):
        for key, value in data.items():
            yield from _flat(value, f"{prefix}{key}.")
    elif isinstance(data, list | tuple) and data and all(isinstance(v, Mapping) for v in data):
        for i, value in enumerate(data):
            yield from _flat(value, f"{prefix}{i}.")
    else:
        yield prefix.rstrip("."), data


def _dump(config: Config) -> dict[str, Any]:
    data: dict[str, Any] = config.model_dump(mode="json", exclude_none=True)
    return data


def config_diff(old: Config, new: Config) -> list[str]:
    """The effective configs' differences, one ``key: old -> new`` line per leaf (secrets
    redacted; ``(unset)`` for a key one side does not have)."""
    a, b = dict(_flat(redact(_dump(old)))), dict(_flat(redact(_dump(new))))
    lines = []
    for key in sorted(a.keys() | b.keys()):
        if a.get(key, ...) != b.get(key, ...):
            before = "(unset)" if key not in a else repr(a[key])
            after = "(unset)" if key not in b else repr(b[key])
            lines.append(f"{key}: {before} -> {after}")
    return lines


def restart_keys(old: Config, new: Config) -> list[str]:
    """The changed keys a reload cannot apply (``RESTART_SECTIONS``)."""
    a, b = _dump(old), _dump(new)
    keys: list[str] = []
    for section in RESTART_SECTIONS:
        if a.get(section) != b.get(section):
            fa = dict(_flat(a.get(section, {}), f"{section}."))
            fb = dict(_flat(b.get(section, {}), f"{section}."))
            keys += sorted(k for k in fa.keys() | fb.keys() if fa.get(k, ...) != fb.get(k, ...))
    return keys


def _with_keys(config: Config, keys: Mapping[str, Any]) -> Config:
    """``config`` with the flat ``keys`` (``camera.exposure_us``) set."""
    if not keys:
        return config
    data = _dump(config)
    for key, value in keys.items():
        *tables, leaf = key.split(".")
        table = data
        for name in tables:
            table = table.setdefault(name, {})
        table[leaf] = value
    return config_from_dict(data, "<running config with the values taken live>")


def applicable(old: Config, new: Config) -> Config:
    """``new`` with the sections only a restart can change kept as they run (``old``)."""
    a, b = _dump(old), _dump(new)
    kept = {s: a[s] for s in RESTART_SECTIONS if a.get(s) != b.get(s) and s in a}
    if not kept and all(s in b or s not in a for s in RESTART_SECTIONS):
        return new
    merged = {**b, **kept}
    for s in RESTART_SECTIONS:
        if s not in a:
            merged.pop(s, None)
    return config_from_dict(merged, "<reloaded config, restart sections as running>")


class Reloader(ConfigWriter):
    """Writes and reloads ``path`` into ``daemon`` (a ``vgripd.service.daemon.Daemon``, typed
    loosely so that this module does not import the daemon): the transaction and the audit are
    ``ConfigWriter``'s, applying a judged config is this class's."""

    def __init__(self, daemon: Any, path: str | Path) -> None:
        super().__init__(path)
        self.daemon = daemon
        #: Keys of restart-only sections the running daemon already took live (the page's
        #: exposure and gain: ``camera.exposure_us``): a file with the same value does not name
        #: them as needing a restart, and the running config takes them.
        self.live: dict[str, Any] = {}
        #: Who asked for a restart ("" none): the daemon stopped to be started again.
        self.restart_requested = ""

    async def restart_between_jobs(self, source: str, timeout_s: float) -> None:
        """What only a start applies (the camera, the links) made to run: the daemon stopped
        between jobs (none running, no several-view job waiting; TimeoutError) for its caller
        to start it again on the files as saved: ``vgripd run`` exits with ``EXIT_RESTART``,
        ``vgripd demo --setup`` starts it again itself."""
        d = self.daemon
        runner = d.rooms.jobs
        await d.wait_for(lambda: runner.job is None and runner.views is None, timeout_s)
        log.warning("restart asked by %s: stopping to be started again", source)
        self.restart_requested = source
        d.request_stop()

    async def apply(self, config: Config, source: str) -> Outcome:
        """The judged ``config`` applied between jobs: what a reload can apply, the keys only a
        restart can change named (``Outcome.restart``)."""
        old = self.daemon.config
        flat_new = dict(_flat(_dump(config)))
        taken = {k: v for k, v in self.live.items() if flat_new.get(k, ...) == v}
        restart = [k for k in restart_keys(old, config) if k not in taken]
        try:
            target = _with_keys(applicable(old, config), taken)
        except ConfigError as err:
            return Outcome(False, f"refused, the running config stays: {err}", source=source,
                           t_wall=time.time())
        diff = config_diff(old, target)
        if not diff and not restart:
            return Outcome(True, "no change", source=source, t_wall=time.time())
        try:
            await self._apply(target)
        except Exception as err:  # the worker could not build them: it is replaced
            log.exception("config reload: applying failed")
            return Outcome(False, f"applying failed: {err}", tuple(diff), tuple(restart),
                           source, time.time())
        message = "applied" if diff else "nothing applied"
        if restart:
            message += f"; needs a restart (systemctl restart vgripd): {', '.join(restart)}"
        return Outcome(True, message, tuple(diff), tuple(restart), source, time.time())

    async def _apply(self, config: Config) -> None:
        """Swap ``config`` in between jobs: no job running, no several-view job waiting."""
        d = self.daemon
        runner = d.rooms.jobs  # the job room: its pipelines, its job thread, its jobs
        pipelines = await _in_process_pipelines(runner, config)
        await d.wait_for(lambda: runner.job is None and runner.views is None, IDLE_TIMEOUT_S)
        # From here to the worker's request nothing awaits: no job starts in between, and a
        # job started later sends its requests after the reconfigure, which the worker answers
        # first (one request at a time, in order).
        runner.core.lines = belt_lines(config, runner.core.lines, d.config)  # conveyor queues
        d.use_config(config, pipelines)
        tell_links(d.rooms.links.links.values(), config)
        d.rooms.jobs.epipolar.threshold_px = config.vision.epipolar_warn_px
        worker = d.rooms.worker
        if worker is not None:
            try:
                for n in await worker.reconfigure(config):
                    d.recipe_problems[n] = "not calibrated after the reload"
            except WorkerError as err:  # it died: the next worker is built from ``config``
                log.warning("config reload: the worker process did not rebuild its pipelines "
                            "(%s); the worker started next is built from the new config", err)
        if d.status_server is not None:  # the web view draws later jobs with it
            d.status_server.images.reconfigure(config)
        d.show_state()


async def _in_process_pipelines(runner: Any, config: Config) -> dict[int, Any] | None:
    """The pipelines of ``config`` built on the job thread when the daemon runs them in its
    own process; None when the worker process does (it rebuilds its own)."""
    from vgripd.vision.checked import CheckedPipeline  # heavy (OpenCV)
    from vgripd.vision.pipeline import Pipeline

    if not any(isinstance(p, Pipeline) for p in runner.pipelines.values()):
        return None
    loop = asyncio.get_running_loop()
    return {n: await loop.run_in_executor(runner._executor, CheckedPipeline,
                                          config.for_recipe(n))
            for n in config.recipe_numbers()}
