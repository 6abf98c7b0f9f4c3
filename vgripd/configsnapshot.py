"""The bytes of a config: the main file and its ``include = [...]`` files, read once.

A config write is judged and applied from one ``Snapshot`` (``vgripd.service.host.configtxn``): the
check child (``vgripd check --snapshot FILE``) and the daemon both parse exactly these bytes
(``load_config(path, files=snapshot.files)``), never the files again, so what runs is what was
judged. ``digest`` names the bytes: the child prints it and the daemon compares it with its own.

Paths are the strings ``vgripd.config`` uses for them: the main file as given, an include
resolved against the main file's folder (``include_path``), so messages and ``owner`` maps
name the same files as a load from disk.
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import json
import tomllib
from collections.abc import Mapping
from pathlib import Path

from vgripd.errors import ConfigError

#: A snapshot file larger than this is no snapshot (the check child refuses it).
MAX_SNAPSHOT_BYTES = 64 << 20


def include_path(main: Path, name: str) -> Path:
    """Where ``include = [name]`` of ``main`` points: an absolute path as it is, a relative one
    against ``main``'s folder."""
    return Path(name) if Path(name).is_absolute() else main.parent / name


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """``files``: path -> bytes, the main file first, then its includes in their order."""

    main: Path
    files: Mapping[str, bytes]

    @classmethod
    def read(cls, main: str | Path) -> Snapshot:
        """The main file and the includes it names, as bytes (``ConfigError`` for one that
        cannot be read). A main file that is no TOML, or whose ``include`` is no list of
        names, is kept alone: loading the snapshot gives the error."""
        path = Path(main)
        files = {str(path): _read(path, "config")}
        try:
            includes = tomllib.loads(files[str(path)].decode("utf-8")).get("include", [])
        except (UnicodeDecodeError, tomllib.TOMLDecodeError):
            includes = []
        if isinstance(includes, list) and all(isinstance(i, str) for i in includes):
            for name in includes:
                inc = include_path(path, name)
                files.setdefault(str(inc), _read(inc, f"included file (from {path}: include)"))
        return cls(path, files)

    def data(self, path: str | Path) -> bytes:
        """The bytes of ``path`` (``ConfigError`` for a file not in the snapshot)."""
        try:
            return self.files[str(path)]
        except KeyError:
            raise ConfigError(f"{path}: not a file of the config {self.main}") from None

    def text(self, path: str | Path) -> str:
        """The text of ``path`` (UTF-8; ``ConfigError`` otherwise)."""
        try:
            return self.data(path).decode("utf-8")
        except UnicodeDecodeError as err:
            raise ConfigError(f"{path}: not UTF-8 text: {err}") from None

    def encoded(self, path: str | Path, text: str) -> bytes:
        """``text`` as the new bytes of ``path``, with the line ends it has now (CRLF kept)."""
        if b"\r\n" in self.data(path):
            text = text.replace("\r\n", "\n").replace("\n", "\r\n")
        return text.encode("utf-8")

    def replaced(self, changes: Mapping[Path, bytes]) -> Snapshot:
        """This snapshot with the files of ``changes`` holding their new bytes."""
        unknown = [str(p) for p in changes if str(p) not in self.files]
        if unknown:
            raise ConfigError(f"{', '.join(unknown)}: not a file of the config {self.main}")
        files = dict(self.files)
        files.update({str(p): bytes(b) for p, b in changes.items()})
        return Snapshot(self.main, files)

    def digest(self) -> str:
        """SHA-256 of the paths and bytes, in order (hex)."""
        h = hashlib.sha256()
        for path, data in self.files.items():
            name = path.encode("utf-8", "surrogateescape")
            h.update(len(name).to_bytes(8, "big") + name + len(data).to_bytes(8, "big"))
            h.update(data)
        return h.hexdigest()

    def dumps(self) -> bytes:
        """The snapshot as a file's bytes (JSON, the file contents base64)."""
        return json.dumps({"main": str(self.main), "files": [
            [p, base64.b64encode(d).decode("ascii")] for p, d in self.files.items()]}).encode()

    @classmethod
    def loads(cls, raw: bytes, where: str = "snapshot") -> Snapshot:
        """``dumps`` read back (``ConfigError`` naming ``where`` for anything else)."""
        try:
            data = json.loads(raw)
            files = {str(p): base64.b64decode(d, validate=True) for p, d in data["files"]}
            return cls(Path(data["main"]), files)
        except (ValueError, KeyError, TypeError) as err:
            raise ConfigError(f"{where}: not a config snapshot: {err}") from None

    @classmethod
    def load(cls, path: str | Path) -> Snapshot:
        """A snapshot file written with ``dumps``."""
        p = Path(path)
        try:
            with p.open("rb") as f:
                raw = f.read(MAX_SNAPSHOT_BYTES + 1)
        except OSError as err:
            raise ConfigError(f"{p}: cannot read the snapshot: {err.strerror}") from None
        if len(raw) > MAX_SNAPSHOT_BYTES:
            raise ConfigError(f"{p}: over {MAX_SNAPSHOT_BYTES} bytes: no config snapshot")
        return cls.loads(raw, str(p))


def _read(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read {what}: {err.strerror}") from None
