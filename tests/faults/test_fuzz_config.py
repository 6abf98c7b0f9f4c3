"""A seeded fuzzer over config files: random mutations of config/example.toml (wrong types,
unknown keys, typos, deleted keys, out-of-range numbers, bad choices), each checked with
``vgripd check``. Every mutation must exit 0 (still a valid config) or 78 with
``vgripd: config error: ...``: one line per problem (``vgripd.config.format_validation_error``),
each ``<file>: <field path>: <message>``, one of them naming a field on the mutated path; never a
traceback, never another exit code.

``VGRIPD_FUZZ_SEED`` replays another sequence; the failing mutation is in the assertion message.
Known gap (vgripd/config.py, not these tests): a non-finite number (inf, nan) in a pose of the
calibration or reference passes validation and fails later building the pipeline, exit 1 with a
message that names no field; ``test_non_finite_pose_numbers_are_config_errors`` pins it.
"""

from __future__ import annotations

import copy
import json
import math
import os
import random
import tomllib
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import REPO
from vgripd.__main__ import EXIT_CONFIG, main

pytestmark = pytest.mark.timeout(300)
SEED = int(os.environ.get("VGRIPD_FUZZ_SEED", "1618"))
CASES = 120
EXAMPLE = REPO / "config" / "example.toml"

Path_ = tuple[str | int, ...]


# --- a small TOML writer (tables, arrays of inline tables, scalars) ------------------------

def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"no TOML for {v!r}")


def _key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def to_toml(data: dict[str, Any], prefix: str = "") -> str:
    scalars = [f"{_key(k)} = {_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    out = "\n".join(scalars) + ("\n" if scalars else "")
    for k, v in data.items():
        if isinstance(v, dict):
            name = f"{prefix}.{_key(k)}" if prefix else _key(k)
            out += f"\n[{name}]\n" + to_toml(v, name)
    return out


# --- mutations ---------------------------------------------------------------------------

def leaves(data: Any, path: Path_ = ()) -> list[Path_]:
    """Every path to a key or list item (tables included)."""
    found: list[Path_] = []
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(
        data, list) else ()
    for k, v in items:
        found.append((*path, k))
        found += leaves(v, (*path, k))
    return found


def tables(data: Any, path: Path_ = ()) -> list[Path_]:
    found = [path] if isinstance(data, dict) else []
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(
        data, list) else ()
    for k, v in items:
        found += tables(v, (*path, k))
    return found


def at(data: Any, path: Path_) -> Any:
    for part in path:
        data = data[part]
    return data


WRONG = ["text", 7, -3, 0, 1e300, -1e300, float("nan"), float("inf"), True, [1, "a"], [],
         {"x": 1}, 2**40, 0.0001]


def mutate(data: dict[str, Any], rng: random.Random) -> tuple[str, Path_]:
    """Change ``data`` in place; what was done and where."""
    op = rng.choice(["wrong", "wrong", "range", "unknown", "typo", "delete", "choice"])
    if op == "unknown":
        path = rng.choice(tables(data))
        name = rng.choice(["bogus", "prot", "timeout", "Port", "extra_key"])
        at(data, path)[name] = rng.choice(WRONG)
        return op, (*path, name)
    path = rng.choice(leaves(data))
    parent, key = at(data, path[:-1]), path[-1]
    if op == "delete":
        del parent[key]
    elif op == "typo" and isinstance(key, str):
        value = parent.pop(key)
        new = key[:-1] if len(key) > 2 and rng.random() < 0.5 else key + "s"
        parent[new] = value
        return op, (*path[:-1], new)
    elif op == "range" and isinstance(parent[key], (int, float)) and not isinstance(
            parent[key], bool):
        parent[key] = rng.choice([-1, 0, -1e9, 1e9, 2**31, float("nan"), float("-inf")])
    elif op == "choice" and isinstance(parent[key], str):
        parent[key] = rng.choice(["nonsense", "", "KUKA", "ttyS0", "../../etc/passwd"])
    else:
        parent[key] = rng.choice(WRONG)
    return op, path


def test_mutated_configs_exit_0_or_78_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # example.toml's camera folder is relative to the working directory
    base = tomllib.loads(EXAMPLE.read_text())
    rng = random.Random(SEED)
    outcomes = {0: 0, EXIT_CONFIG: 0}
    for i in range(CASES):
        data = copy.deepcopy(base)
        changes = [mutate(data, rng) for _ in range(rng.choice([1, 1, 1, 2]))]
        cfg = tmp_path / f"case{i}.toml"
        cfg.write_text(to_toml(data))
        where = f"seed {SEED} case {i}: {changes}"
        try:
            rc = main(["check", "-c", str(cfg)])
        except SystemExit as exit_:  # argparse; never expected here
            rc = exit_.code  # type: ignore[assignment]
        except BaseException as err:
            pytest.fail(f"{where}: {type(err).__name__}: {err}")
        out, err = capsys.readouterr()
        assert rc in (0, EXIT_CONFIG), f"{where}: exit {rc}: {err}"
        outcomes[rc] += 1
        assert "Traceback" not in err + out, where
        if rc == 0:
            assert out.startswith(f"OK {cfg}"), where
            continue
        check_config_error(err, cfg, changes, where)
    assert outcomes[EXIT_CONFIG] > CASES // 2, outcomes


def check_config_error(err: str, cfg: Path, changes: list[tuple[str, Path_]],
                       where: str) -> None:
    """``vgripd: config error:`` then one line per problem: ``<file>: <field>: <message>``
    (driver options, judged when the daemon builds the driver: ``<section>: <option>: ...``)."""
    prefix = "vgripd: config error: "
    assert err.startswith(prefix), f"{where}: {err}"
    lines = err[len(prefix):].strip().splitlines()
    assert all(line.startswith(f"{cfg}: ") or line.split(": ")[0] in ("camera", "links")
               or line.split(": ")[0].startswith("links.") for line in lines), f"{where}: {err}"
    assert all(line.count(": ") >= 2 for line in lines), f"{where}: {err}"
    names = {str(part) for _, path in changes for part in path}
    assert any(name in line for line in lines for name in names), f"{where}: {err}"


@pytest.mark.parametrize("path", [
    ("calibration", "stereo", "T_right_left", "rotvec_rad", 0),
    ("calibration", "hand_eye", "T_base_camera", "translation_mm", 2),
    ("reference", "T_base_obj", "translation_mm", 1),
])
def test_non_finite_pose_numbers_are_config_errors(
        path: Path_, tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    data = tomllib.loads(EXAMPLE.read_text())
    at(data, path[:-1])[path[-1]] = float("inf")
    cfg = tmp_path / "inf.toml"
    cfg.write_text(to_toml(data))
    rc = main(["check", "-c", str(cfg)])
    _, err = capsys.readouterr()
    assert rc == EXIT_CONFIG, err
    check_config_error(err, cfg, [("range", path)], str(path))
