"""The systemd unit: `systemd-analyze verify` accepts it without a warning, and the settings the
daemon relies on are there (notify + watchdog, no restart on a config error, hardening)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO, need_tool

UNIT = REPO / "systemd" / "vgripd.service"


def _settings(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            out.setdefault(key, []).append(value)
    return out


def test_systemd_analyze_verify_has_no_complaint(tmp_path: Path) -> None:
    analyze = need_tool("systemd-analyze", "systemd")
    # verify insists that ExecStart exists: point it at this interpreter, keep everything else.
    text = UNIT.read_text().replace(
        "/opt/vgripd/venv/bin/vgripd run", f"{sys.executable} -m vgripd run")
    unit = tmp_path / "vgripd.service"
    unit.write_text(text)
    proc = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip() == "", proc.stderr  # unknown keys are only warnings


def test_unit_key_settings() -> None:
    s = _settings(UNIT.read_text())
    expected = {
        "Type": "notify", "NotifyAccess": "main", "WatchdogSec": "10",
        "Restart": "on-failure", "RestartPreventExitStatus": "78",
        "DynamicUser": "yes", "StateDirectory": "vgripd", "ConfigurationDirectory": "vgripd",
        "ProtectSystem": "strict", "ProtectHome": "yes", "NoNewPrivileges": "yes",
        "PrivateTmp": "yes", "CapabilityBoundingSet": "CAP_NET_BIND_SERVICE",
        "AmbientCapabilities": "CAP_NET_BIND_SERVICE", "SupplementaryGroups": "dialout",
        "RestrictAddressFamilies": "AF_UNIX AF_INET AF_INET6", "DevicePolicy": "closed",
        "LimitNOFILE": "8192", "MemoryMax": "2G", "TasksMax": "256", "PrivateMounts": "yes",
        # Stop signals the whole unit; the children end with the daemon well within the timeout.
        "KillMode": "control-group", "TimeoutStopSec": "15",
    }
    for key, value in expected.items():
        assert s.get(key) == [value], f"{key}: {s.get(key)}"
    assert s["ExecStart"][0].endswith("vgripd run -c /etc/vgripd/vgripd.toml")
    assert s["ExecReload"] == ["/bin/kill -HUP $MAINPID"]  # SIGHUP: reload without a restart
    assert "char-ttyS rw" in s["DeviceAllow"]
    # The exit code systemd must not restart on is the one the CLI uses for config errors.
    from vgripd.__main__ import EXIT_CONFIG
    assert s["RestartPreventExitStatus"] == [str(EXIT_CONFIG)]


def test_systemd_analyze_security_exposure_at_most_1_8(tmp_path: Path) -> None:
    """`systemd-analyze security` rates the unit's exposure (0 = locked down, 10 = none): the
    hardening must not slip above 1.8 (docs/security.md)."""
    analyze = need_tool("systemd-analyze", "systemd")
    unit = tmp_path / "vgripd.service"
    unit.write_text(UNIT.read_text().replace(
        "/opt/vgripd/venv/bin/vgripd run", f"{sys.executable} -m vgripd run"))
    proc = subprocess.run([analyze, "security", "--offline=true", str(unit)],
                          capture_output=True, text=True, timeout=60, check=False)
    match = re.search(r"Overall exposure level for vgripd.service: (\d+\.\d+)", proc.stdout)
    assert match, proc.stdout + proc.stderr
    assert float(match[1]) <= 1.8, proc.stdout
