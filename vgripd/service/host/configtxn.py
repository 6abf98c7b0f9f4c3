"""The one way to write the config the daemon runs on: one judged transaction per write
(docs/web.md, "Writing the config: one transaction").

Every writer (the page's tuning save, camera settings, teaching, hand-eye accept, a saved
hand-eye plan, and whatever writes config next, such as a guided setup) and every reload
(SIGHUP, the page's Reload) runs through one ``ConfigWriter`` (the daemon's ``reloader``), one at
a time under one lock, so nothing interleaves: write -> judge -> apply or discard.

1. **Snapshot**: the bytes of the main file and its includes, read once
   (``vgripd.configsnapshot.Snapshot``).
2. **Edit**: the caller's function (``Edit``) gets that snapshot and returns the new bytes of
   some included files (never the main file, never a file outside the config). It refuses by
   raising a ``ConfigError`` (``EditRefused``) naming what and where: nothing is written.
3. **Candidate**: each new file goes to ``.NAME.candidate`` beside the include, created
   exclusively and without following a link (``O_EXCL | O_NOFOLLOW``), with the include's mode
   and owner, and fsynced. The live include is not touched.
4. **Judge**: ``vgripd check --running --snapshot FILE`` in a child process reads the snapshot,
   with the candidates' bytes in place, from one file, judges it as ``vgripd check`` does, and
   prints the snapshot's digest.
5. **Apply**: the daemon parses exactly those bytes (the child's digest compared with its own),
   makes sure no file of the snapshot changed on disk meanwhile, and applies the config between
   jobs (``ConfigWriter.apply``: the reloader's; the base class applies nothing).
6. **Commit**: each include's old bytes go to a numbered backup (``cell.toml.3``: a byte copy
   with the include's mode), a journal names the candidates, each candidate is renamed over its
   include, and the folder is fsynced; then the journal goes.

Refused or failed before the commit: the candidates are removed and every include holds the
bytes it held, byte for byte. Killed at any moment: each include holds its judged old or its
judged new bytes; a journal left by a kill inside the commit is finished by ``recover`` when
``vgripd run`` starts (the new bytes, judged and running before the kill), and a leftover
candidate is removed then (or by the next write).

Use::

    def edit(snapshot: Snapshot) -> dict[Path, bytes]:
        target = ...                                   # an include of snapshot.main
        data = tomllib.loads(snapshot.text(target))
        data["vision"]["min_contrast"] = 20.0
        return {target: snapshot.encoded(target, toml_from_dict(data))}

    outcome = await daemon.reloader.write(edit, "web 10.0.0.5", "tuning save")
    outcome = await daemon.reloader.reload("SIGHUP")             # no edit: judge and apply
    await daemon.reloader.write_file(plan_path, data)            # a file the config does not name

Each ``write``/``reload`` is one audit entry (``audit``, the log) and answers an ``Outcome``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import stat
import tempfile
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from vgripd.config import Config, load_config
from vgripd.configsnapshot import Snapshot
from vgripd.errors import ConfigError, VgripError
from vgripd.service.host.commands import run_vgripd

log = logging.getLogger("vgripd.reload")

#: ``vgripd check`` in the child process gets this long (it builds and runs every pipeline).
CHECK_TIMEOUT_S = 300.0
#: Audit entries kept for the page (the log keeps them all).
AUDIT_KEEP = 200
#: Numbered backups kept per include file (the oldest beyond are removed).
MAX_BACKUPS = 50

#: An edit: the snapshot in, the new bytes of included files out.
Edit = Callable[[Snapshot], Mapping[Path, bytes]]


class EditRefused(ConfigError):
    """An edit that cannot be made (no include holds the key, a key set elsewhere ...)."""


@dataclasses.dataclass(frozen=True)
class Outcome:
    """One write or reload: ``applied`` or refused (``message`` says why), the effective-config
    ``diff`` (``key: old -> new``), the changed keys that need a restart, and the files
    ``written`` (``cell.toml (backup cell.toml.3)``)."""

    applied: bool
    message: str
    diff: tuple[str, ...] = ()
    restart: tuple[str, ...] = ()
    source: str = ""
    t_wall: float = 0.0
    written: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        return {"applied": self.applied, "message": self.message, "diff": list(self.diff),
                "restart": list(self.restart), "source": self.source,
                "written": list(self.written),
                "time": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(self.t_wall))}


# --- files ----------------------------------------------------------------------------------

def candidate_path(target: Path) -> Path:
    return target.with_name(f".{target.name}.candidate")


def journal_path(target: Path) -> Path:
    return target.with_name(f".{target.name}.commit")


def create_file(path: Path, data: bytes, like: os.stat_result | None = None,
                mode: int = 0o666) -> None:
    """``path`` created exclusively, never through a link (``FileExistsError`` when anything is
    there), holding ``data``, fsynced; with the mode and owner of ``like`` (``mode`` less the
    umask without one)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                 0o600 if like is not None else mode)
    try:
        if like is not None:
            now = os.fstat(fd)
            if (now.st_uid, now.st_gid) != (like.st_uid, like.st_gid):
                os.fchown(fd, like.st_uid, like.st_gid)
            os.fchmod(fd, stat.S_IMODE(like.st_mode))
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        path.unlink(missing_ok=True)
        raise
    os.close(fd)


def regular_file(path: Path) -> os.stat_result:
    """``lstat`` of ``path``; ``EditRefused`` unless it is a regular file (a link is not
    written through)."""
    st = os.lstat(path)
    if not stat.S_ISREG(st.st_mode):
        raise EditRefused(f"{path}: not a regular file (a link or other): the daemon writes "
                          "only a regular include; include the file itself")
    return st


def write_candidate(target: Path, data: bytes) -> Path:
    """``data`` as the candidate of ``target`` (its mode and owner); a leftover candidate of an
    interrupted write is removed first (unlinked: a planted link is never followed)."""
    st = regular_file(target)
    cand = candidate_path(target)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(cand)
        log.warning("config write: removed a leftover %s", cand)
    create_file(cand, data, st)
    return cand


def backup_copy(target: Path, data: bytes, like: os.stat_result) -> Path:
    """``data`` (the include's bytes before) as the next numbered backup, same mode."""
    numbers = [int(p.suffix[1:]) for p in target.parent.glob(target.name + ".*")
               if p.suffix[1:].isdigit()]
    n = max(numbers, default=0) + 1
    while True:
        path = target.with_name(f"{target.name}.{n}")
        try:
            create_file(path, data, like)
            return path
        except FileExistsError:
            n += 1


def prune_backups(target: Path, keep: int = MAX_BACKUPS) -> None:
    backups = sorted((p for p in target.parent.glob(target.name + ".*")
                      if p.suffix[1:].isdigit()), key=lambda p: int(p.suffix[1:]))
    for old in backups[:-keep]:
        old.unlink(missing_ok=True)


def fsync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace_file(path: Path, data: bytes) -> None:
    """``path`` holds ``data`` afterwards, atomically (candidate, rename, fsync), with its mode
    and owner when it exists; for files the config does not name (hand-eye plans)."""
    like = regular_file(path) if os.path.lexists(path) else None
    cand = candidate_path(path)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(cand)
    create_file(cand, data, like, 0o666)
    os.replace(cand, path)
    fsync_folder(path.parent)


def commit(candidates: Mapping[Path, Path], before: Snapshot) -> list[str]:
    """Backups, journal, renames, fsyncs (see the module's docstring); the names written."""
    written = []
    for target in candidates:
        backup = backup_copy(target, before.data(target), regular_file(target))
        written.append(f"{target.name} (backup {backup.name})")
    first = next(iter(candidates))
    journal = journal_path(first)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(journal)  # a stale one (a start without ``recover``) names no candidate here
    create_file(journal, json.dumps([[str(c), str(t), _sha256(Path(c).read_bytes())]
                                     for t, c in candidates.items()]).encode(), mode=0o600)
    fsync_folder(first.parent)
    for target, cand in candidates.items():
        os.replace(cand, target)
        fsync_folder(target.parent)
    journal.unlink()
    for target in candidates:
        prune_backups(target)
    return written


def recover(config_path: str | Path) -> list[str]:
    """Finish a commit that a kill interrupted (its journal beside an include): the rest of
    its candidates renamed over their includes, then the journal removed. Run before the
    config is loaded at start; the files finished are named (and logged)."""
    try:
        snapshot = Snapshot.read(config_path)
    except ConfigError:
        return []
    done = []
    for name in list(snapshot.files)[1:]:
        journal = journal_path(Path(name))
        try:
            pairs = json.loads(journal.read_bytes())
        except FileNotFoundError:
            continue
        except (OSError, ValueError) as err:
            log.error("config: cannot read %s (%s): left as it is", journal, err)
            continue
        if not (isinstance(pairs, list) and all(isinstance(p, list) and len(p) == 3
                                                for p in pairs)):
            log.error("config: %s is no journal of a write: left as it is", journal)
            continue
        for cand, target, digest in pairs:
            try:
                same = _sha256(Path(cand).read_bytes()) == digest and stat.S_ISREG(
                    os.lstat(cand).st_mode)
            except OSError:
                same = False  # renamed before the kill, or gone
            if same:
                os.replace(cand, target)
                fsync_folder(Path(target).parent)
                done.append(target)
                log.warning("config: finished the interrupted write of %s", target)
        journal.unlink(missing_ok=True)
    for name in list(snapshot.files)[1:]:  # candidates of writes killed before their commit
        cand = candidate_path(Path(name))
        with contextlib.suppress(FileNotFoundError):
            os.unlink(cand)
            log.warning("config: removed %s, left by an interrupted write (never judged "
                        "and applied)", cand)
    return done


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def changed_on_disk(snapshot: Snapshot) -> list[str]:
    """The files of ``snapshot`` whose bytes on disk are others now."""
    moved = []
    for path, data in snapshot.files.items():
        try:
            now = Path(path).read_bytes()
        except OSError:
            now = None
        if now != data:
            moved.append(path)
    return moved


# --- the judge ------------------------------------------------------------------------------

async def judge(snapshot: Snapshot, untaught_ok: bool = False,
                timeout_s: float = CHECK_TIMEOUT_S, uncalibrated_ok: bool = False) -> str:
    """``vgripd check --running`` of ``snapshot`` in a child process (``--untaught-ok`` with
    ``untaught_ok``, ``--uncalibrated-ok`` with ``uncalibrated_ok``): "" when it passes on
    exactly these bytes, else why not."""
    with tempfile.TemporaryDirectory(prefix="vgripd-judge-") as tmp:
        file = Path(tmp) / "snapshot.json"
        await asyncio.to_thread(create_file, file, snapshot.dumps(), None, 0o600)
        rc, out, err = await run_vgripd(
            ["check", "--running", "-c", str(snapshot.main), "--snapshot", str(file),
             *(["--untaught-ok"] if untaught_ok else []),
             *(["--uncalibrated-ok"] if uncalibrated_ok else [])], timeout_s)
    if rc != 0:
        lines = [line for line in (out + "\n" + err).splitlines()
                 if line.strip() and not line.lower().startswith(("warning:", "note:"))]
        return "\n".join(lines[-20:]) or f"vgripd check exited with {rc}"
    digests = [line.split()[-1] for line in out.splitlines() if line.startswith("snapshot ")]
    if digests != [snapshot.digest()]:
        return (f"vgripd check judged other bytes than the daemon holds (digest "
                f"{digests[-1] if digests else 'none'}, expected {snapshot.digest()})")
    return ""


# --- the transaction ------------------------------------------------------------------------

class ConfigWriter:
    """Writes and reloads ``path`` (the main config file), one transaction at a time, and keeps
    the audit. ``apply`` is what a judged config does to the running daemon (the reloader's
    subclass); here it applies nothing."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.audit: deque[Outcome] = deque(maxlen=AUDIT_KEEP)
        self.last: Outcome | None = None
        self._lock = asyncio.Lock()
        self._tasks: set[asyncio.Task[Outcome]] = set()

    @property
    def running(self) -> bool:
        return self._lock.locked()

    async def apply(self, config: Config, source: str) -> Outcome:
        """Apply the judged ``config``; ``Outcome.applied`` False keeps the files as they are."""
        return Outcome(True, "saved", source=source, t_wall=time.time())

    def request(self, source: str = "SIGHUP") -> None:
        """Reload in the background (a signal handler calls this)."""
        task = asyncio.ensure_future(self.reload(source))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def close(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    async def reload(self, source: str = "SIGHUP", note: str = "",
                     untaught_ok: bool = False) -> Outcome:
        """Judge the files as they are and apply them; the running config stays when they are
        refused. ``untaught_ok``: a recipe left untaught is no refusal."""
        return await self.write(None, source, note, untaught_ok)

    async def write_file(self, path: Path, data: bytes) -> None:
        """``path`` (a file the config does not name, e.g. a hand-eye plan) replaced by
        ``data`` atomically, in turn with every config write (``EditRefused`` for a file of
        the config)."""
        async with self._lock:
            await asyncio.to_thread(_replace_other, self.path, path, data)

    async def write(self, edit: Edit | None, source: str, note: str = "",
                    untaught_ok: bool = False, uncalibrated_ok: bool = False) -> Outcome:
        """One transaction (the module's docstring): ``edit`` None reloads.
        ``uncalibrated_ok``: a cell not calibrated yet is no refusal (the setup's camera and
        link choices before its calibration step)."""
        async with self._lock:
            log.info("config reload (%s)%s: judging %s", source, f" ({note})" if note else "",
                     self.path)
            try:
                before = await asyncio.to_thread(Snapshot.read, self.path)
                changes = {} if edit is None else await asyncio.to_thread(_changes, edit,
                                                                          before)
            except (VgripError, OSError, ValueError, KeyError, TypeError) as err:
                return self._audit(Outcome(False, f"refused, nothing written: {err}",
                                           source=source, t_wall=time.time()), note)
            if edit is not None and not changes:
                return self._audit(Outcome(True, "no change: the file holds it already",
                                           source=source, t_wall=time.time()), note)
            candidates: dict[Path, Path] = {}
            committing = False
            try:
                try:
                    for target, data in changes.items():
                        candidates[target] = await asyncio.to_thread(write_candidate, target,
                                                                     data)
                except (ConfigError, OSError) as err:
                    return self._audit(Outcome(False, f"refused, nothing written: {err}",
                                               source=source, t_wall=time.time()), note)
                judged = before.replaced(changes)
                try:
                    problem = await judge(judged, untaught_ok,
                                          uncalibrated_ok=uncalibrated_ok)
                    if problem:
                        raise ConfigError(problem)
                    new = await asyncio.to_thread(load_config, judged.main, judged.files)
                    moved = await asyncio.to_thread(changed_on_disk, before)
                    if moved:
                        raise ConfigError(f"{', '.join(moved)} changed on disk while judged: "
                                          "nothing written; try again")
                except (VgripError, TimeoutError) as err:
                    return self._audit(Outcome(False, f"refused, the running config stays: "
                                               f"{err}", source=source, t_wall=time.time()),
                                       note)
                outcome = await self.apply(new, source)
                if not outcome.applied or not candidates:
                    return self._audit(outcome, note)
                committing = True  # from here the commit runs to its end, cancelled or not
                try:
                    written = await asyncio.shield(asyncio.to_thread(commit, candidates,
                                                                     before))
                except OSError as err:
                    log.exception("config write: the commit failed")
                    return self._audit(dataclasses.replace(
                        outcome, applied=False, message=f"{outcome.message}, but saving "
                        f"failed ({err}): the next start finishes it when its journal was "
                        "written, else runs the files as they were"), note)
                message = f"{outcome.message}; saved to {', '.join(written)}"
                return self._audit(dataclasses.replace(outcome, message=message,
                                                       written=tuple(written)), note)
            finally:
                if not committing:
                    for cand in candidates.values():
                        cand.unlink(missing_ok=True)

    def _audit(self, outcome: Outcome, note: str = "") -> Outcome:
        self.audit.appendleft(outcome)
        self.last = outcome
        what = f" ({note})" if note else ""
        changes = "; ".join(outcome.diff) or "no change"
        if outcome.applied:
            log.info("config reload (%s)%s: %s: %s", outcome.source, what, outcome.message,
                     changes)
        else:
            log.error("config reload (%s)%s: %s", outcome.source, what, outcome.message)
        return outcome


def _replace_other(config_path: Path, path: Path, data: bytes) -> None:
    snapshot = Snapshot.read(config_path)
    if any(Path(p).resolve() == path.resolve() for p in snapshot.files):
        raise EditRefused(f"{path}: a file of the config {config_path}: not written")
    replace_file(path, data)


def _changes(edit: Edit, before: Snapshot) -> dict[Path, bytes]:
    """The edit's new bytes that differ from the snapshot's; ``EditRefused`` for the main file
    or a file the config does not name."""
    changes = {Path(p): bytes(b) for p, b in edit(before).items()}
    for path in changes:
        if str(path) == str(before.main) or str(path) not in before.files:
            raise EditRefused(f"{path}: the daemon writes only an included file of "
                              f"{before.main}, never the main file or another")
    return {p: b for p, b in changes.items() if b != before.data(p)}
