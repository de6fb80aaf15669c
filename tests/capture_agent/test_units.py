"""The systemd units in capture_agent/systemd/: systemd accepts them, and they say what a Jetson
node needs (the Argus socket, the camera daemons, PTP first, no restart loop on a config error).

``systemd-analyze verify`` checks every unit as installed, with ExecStart pointing at this
checkout's ``egosurg`` (the units name /opt/egosurg/.venv, which a test machine lacks).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, run_egosurg

UNITS = REPO / "capture_agent" / "systemd"
ANALYZE = shutil.which("systemd-analyze")
INSTALLED_EGOSURG = "/opt/egosurg/.venv/bin/egosurg"


def settings(unit: Path) -> dict[str, list[str]]:
    """``Section.Key`` -> every value given (a key may repeat), comments left out."""
    found: dict[str, list[str]] = {}
    section = ""
    for raw in unit.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        found.setdefault(f"{section}.{key.strip()}", []).append(value.strip())
    return found


def words(unit: dict[str, list[str]], key: str) -> list[str]:
    return " ".join(unit.get(key, [])).split()


@pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze (systemd) is not installed")
@pytest.mark.parametrize(
    "names",
    [
        ("egosurg-agent.service", "egosurg-recorder.service"),
        ("egosurg-ptp4l@eth1.service", "egosurg-phc2sys@eth1.service"),
    ],
)
def test_systemd_accepts_the_units(tmp_path, names):
    if "ptp4l" in names[0] and not Path("/usr/sbin/ptp4l").exists():
        pytest.skip("linuxptp is not installed (make system-deps): the units run /usr/sbin/ptp4l")
    egosurg = Path(sys.executable).with_name("egosurg")
    if not egosurg.exists():
        pytest.skip(f"{egosurg} is missing: install this checkout (pip install -e .)")
    for unit in UNITS.glob("*.service"):
        text = unit.read_text().replace(INSTALLED_EGOSURG, str(egosurg))
        (tmp_path / unit.name).write_text(text)
    argv = [str(ANALYZE), "verify", "--man=no", *(str(tmp_path / n) for n in names)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr


def test_the_agent_unit_fits_a_jetson():
    unit = settings(UNITS / "egosurg-agent.service")
    # /tmp/argus_socket (GMSL cameras through nvargus-daemon) must be the host's.
    assert unit.get("Service.PrivateTmp", ["no"]) == ["no"]
    assert "/tmp" in words(unit, "Service.ReadWritePaths")
    # ProtectClock implies DeviceAllow=char-rtc, and any DeviceAllow closes /dev/video* & co.
    assert "Service.ProtectClock" not in unit and "Service.DeviceAllow" not in unit
    assert "Service.PrivateDevices" not in unit
    for daemon in ("nvargus-daemon.service", "zed_x_daemon.service"):
        assert daemon in words(unit, "Unit.Wants") and daemon in words(unit, "Unit.After")
    # PTP first: the ptp4l/phc2sys units order themselves before time-sync.target.
    assert "time-sync.target" in words(unit, "Unit.After")
    assert unit["Service.RuntimeDirectory"] == ["egosurg"]  # pmc's reply socket


@pytest.mark.parametrize("name", ["egosurg-agent.service", "egosurg-recorder.service"])
def test_restarts_never_give_up_except_on_a_configuration_error(tmp_path, name):
    unit = settings(UNITS / name)
    assert unit["Unit.StartLimitIntervalSec"] == ["0"]
    assert int(unit["Service.LimitNOFILE"][0]) >= 4096
    command = "agent" if "agent" in name else "recorder"
    bad = run_egosurg(command, "--config", str(tmp_path / "missing.toml"), timeout=60)
    assert bad.returncode != 0 and "Traceback" not in bad.stderr, bad.stderr
    assert unit["Service.RestartPreventExitStatus"] == [str(bad.returncode)]


def test_the_ptp_units_open_the_socket_to_the_agent_and_follow_each_other():
    ptp4l = settings(UNITS / "egosurg-ptp4l@.service")
    assert ptp4l["Service.Group"] == ["egosurg"] and "Service.User" not in ptp4l
    assert "time-sync.target" in words(ptp4l, "Unit.Before")
    phc2sys = settings(UNITS / "egosurg-phc2sys@.service")
    assert words(phc2sys, "Unit.Requires") == ["egosurg-ptp4l@%i.service"]
    assert "egosurg-ptp4l@%i.service" in words(phc2sys, "Unit.After")
    assert "time-sync.target" in words(phc2sys, "Unit.Before")
    assert "systemd-timesyncd.service" in words(phc2sys, "Unit.Conflicts")
    rule = (UNITS / "60-egosurg-ptp.rules").read_text()
    assert 'SUBSYSTEM=="ptp", GROUP="egosurg", MODE="0640"' in rule
