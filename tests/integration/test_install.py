"""The install routes, outside the checkout: a wheel built from the source carries what the
commands need (robot program templates, example configs, the web view's files, the pages the
unit names), and ``systemd/install.sh`` installs it into a temporary prefix, ending with
``systemd-analyze verify`` clean on the installed unit.

No download: the wheel is built with this environment's setuptools (``--no-build-isolation``)
and installed with ``--no-deps --no-index`` into fresh venvs that borrow this environment's
third-party packages through a ``.pth`` line (the checkout itself is not on their path: the
tests check where ``vgripd`` is imported from)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.conftest import REPO, need_camera_sdk, need_tool
from vgripd.peer.socket_frames import BRANDS

pytestmark = pytest.mark.slow(minutes=3)

EXAMPLES = sorted(p.name for p in (REPO / "config" / "examples").glob("*.toml"))
#: What a wheel is built from (vgripd/share/ links into robots/, docs/, systemd/, config/).
SOURCE = ["pyproject.toml", "README.md", "LICENSE", "vgripd", "drivers", "robots", "docs",
          "systemd", "config"]
TIMEOUT_S = 300


def _run(argv: list[str | Path], cwd: Path, **kw: object) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run([str(a) for a in argv], cwd=cwd, capture_output=True, text=True,
                          timeout=TIMEOUT_S, check=False, **kw)  # type: ignore[call-overload]
    assert proc.returncode == 0, f"{argv}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in SOURCE:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy(REPO / name, src / name)
    out = tmp_path_factory.mktemp("wheel")
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
          "-w", out, src], cwd=out)
    (found,) = out.glob("vgripd-*.whl")
    return found


def fresh_venv(path: Path) -> Path:
    """A new venv whose third-party packages are this environment's; returns its python."""
    base = getattr(sys, "_base_executable", sys.executable)
    path.parent.mkdir(parents=True, exist_ok=True)
    _run([base, "-m", "venv", "--without-pip", path], cwd=path.parent)
    python = path / "bin" / "python"
    purelib = _run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                   cwd=path.parent).stdout.strip()
    Path(purelib, "_vgripd_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python


@pytest.fixture(scope="module")
def installed(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel installed into a fresh venv: its bin folder."""
    root = tmp_path_factory.mktemp("venv")
    python = fresh_venv(root / "venv")
    _run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps",
          "--no-index", wheel], cwd=root)
    return python.parent


def _share(bin_dir: Path) -> Path:
    return Path(_run([bin_dir / "python", "-c",
                      "from vgripd.resources import shared; print(shared())"],
                     cwd=bin_dir).stdout.strip())


def test_the_installed_package_is_not_the_checkout(installed: Path, tmp_path: Path) -> None:
    where = _run([installed / "python", "-c", "import vgripd, drivers; "
                  "print(vgripd.__file__); print(drivers.__file__)"], cwd=tmp_path).stdout
    for line in where.split():
        assert Path(line).is_relative_to(installed.parent), line
        assert not Path(line).is_relative_to(REPO), line
    share = _share(installed)
    assert (share / "systemd" / "vgripd.service").is_file()
    assert (share / "docs" / "daemon.md").is_file()
    assert (share.parent / "service" / "web" / "static" / "index.html").is_file()
    assert sorted(p.name for p in (share / "examples").glob("*.toml")) == EXAMPLES


@pytest.mark.parametrize("brand", sorted(BRANDS))
def test_robot_program_from_the_wheel(brand: str, installed: Path, tmp_path: Path) -> None:
    example = _share(installed) / "examples" / f"robot-socket-{brand}.toml"
    proc = _run([installed / "vgripd", "robot-program", "--brand", brand, "-c", example,
                 "-o", tmp_path / brand, "--host", "192.168.1.20"], cwd=tmp_path)
    assert sorted(p.name for p in (tmp_path / brand).iterdir()) == sorted(BRANDS[brand].files)
    # the set-up page it names is installed too
    installed_page = proc.stdout.rsplit("(installed with vgripd: ", 1)[1].split(")")[0]
    assert Path(installed_page).is_file()
    assert Path(installed_page).is_relative_to(installed.parent)


@pytest.mark.parametrize("name", EXAMPLES)
def test_check_every_example_from_the_wheel(name: str, installed: Path, tmp_path: Path) -> None:
    example = _share(installed) / "examples" / name
    need_camera_sdk(example)
    proc = _run([installed / "vgripd", "check", "--no-camera", "-c", example], cwd=tmp_path)
    assert proc.stdout.startswith(f"OK {example}"), proc.stdout


def test_demo_from_the_wheel(installed: Path, tmp_path: Path) -> None:
    proc = _run([installed / "vgripd", "demo", "--cycles", "2", "--port", "0",
                 "--web-port", "0"], cwd=tmp_path)
    assert "counts:" in proc.stdout
    assert "OK" in proc.stdout


def test_install_script_into_a_temporary_prefix(wheel: Path, tmp_path: Path) -> None:
    analyze = need_tool("systemd-analyze", "systemd")
    prefix, etc, state, units = (tmp_path / d for d in ("opt", "etc", "state", "units"))
    fresh_venv(prefix / "venv")
    env = {**os.environ, "PYTHON": getattr(sys, "_base_executable", sys.executable)}
    _run(["bash", REPO / "systemd" / "install.sh", "--prefix", prefix, "--etc", etc,
          "--state", state, "--unit-dir", units, "--package", wheel, "--pip-option",
          "--no-deps", "--pip-option", "--no-index", "--no-systemctl"], cwd=tmp_path, env=env)
    unit = units / "vgripd.service"
    text = unit.read_text()
    assert f"ExecStart={prefix}/venv/bin/vgripd run -c {etc}/vgripd.toml" in text
    assert f"Documentation=file://{prefix}/docs/daemon.md" in text
    assert f"WorkingDirectory={etc}" in text
    assert (prefix / "docs" / "daemon.md").is_file()  # the page the unit names is there
    assert (state / "cell.toml").is_file()  # vgripd init: the includes the page writes
    proc = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip() == "", proc.stderr
