"""PTP status from linuxptp's pmc, with a fake ``pmc`` program (we have no PTP card here).

The fake is a real executable that checks it was called as the agent calls pmc (``-u -b 0 -s
SOCKET -i CLIENT`` and the three questions) and prints what linuxptp's pmc prints in each case.
The real linuxptp is exercised in test_ptp_linuxptp.py.
"""

from __future__ import annotations

import os
import stat
import sys
import textwrap
import time
from pathlib import Path

import pytest

from capture_agent.agent import phc
from capture_agent.agent.pmc import PMC_QUERIES, parse_responses, parse_time_status, utc_lead_ns
from capture_agent.agent.ptp import PtpMonitor, PtpStatus, read_ptp_status
from protocol.errors import ConfigError
from protocol.formats.node_config import PtpConfig
from protocol.toml_config import read_table

HEADER = "".join(f"sending: {q}\n" for q in PMC_QUERIES)


def time_status(
    offset: int,
    gm_present: bool,
    spelling: str = "MANAGEMENT",
    stamping: str = "SOFTWARE",
    port_state: str = "SLAVE",
) -> str:
    """pmc's answer; software timestamping by default: ptp4l's clock is the system clock."""
    return HEADER + textwrap.dedent(
        f"""\
        \t90e2ba.fffe.20c7f8-0 seq 0 RESPONSE {spelling} TIME_STATUS_NP
        \t\tmaster_offset              {offset}
        \t\tingress_time               1361545089345029441
        \t\tcumulativeScaledRateOffset   +1.000000000
        \t\tscaledLastGmPhaseChange    0
        \t\tgmTimeBaseIndicator        0
        \t\tlastGmPhaseChange          0x0000'0000000000000000.0000
        \t\tgmPresent                  {"true" if gm_present else "false"}
        \t\tgmIdentity                 00a069.fffe.0b552d
        \t90e2ba.fffe.20c7f8-1 seq 1 RESPONSE {spelling} PORT_PROPERTIES_NP
        \t\tportIdentity            90e2ba.fffe.20c7f8-1
        \t\tportState               {port_state}
        \t\ttimestamping            {stamping}
        \t\tinterface               eth1
        \t90e2ba.fffe.20c7f8-0 seq 2 RESPONSE {spelling} TIME_PROPERTIES_DATA_SET
        \t\tcurrentUtcOffset      37
        \t\tcurrentUtcOffsetValid 1
        \t\tptpTimescale          1
        """
    )


def fake_pmc(directory: Path, stdout: str, *, sleep_s: float = 0.0, exit_code: int = 0) -> Path:
    """Write an executable ``pmc`` that prints ``stdout`` if called with the real arguments: ptp4l's
    default socket, and a reply socket in a folder that exists (pmc binds it there)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "pmc"
    tmp = directory / "pmc.tmp"  # written aside and renamed: a polling monitor never sees half
    tmp.write_text(
        f"#!{sys.executable}\n"
        "import os, sys, time\n"
        "a = sys.argv[1:]\n"
        "ok = a[:6] == ['-u', '-b', '0', '-s', '/var/run/ptp4l', '-i'] and len(a) == 10\n"
        f"ok = ok and os.path.isdir(os.path.dirname(a[6])) and a[7:] == {list(PMC_QUERIES)!r}\n"
        "if not ok:\n"
        "    sys.stderr.write('unexpected arguments: %r\\n' % a); sys.exit(2)\n"
        f"time.sleep({sleep_s})\n"
        f"sys.stdout.write({stdout!r})\n"
        f"sys.exit({exit_code})\n"
    )
    tmp.chmod(tmp.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    os.replace(tmp, path)
    return path


def test_locked(tmp_path):
    pmc = fake_pmc(tmp_path, time_status(-142, True))
    status = read_ptp_status(PtpConfig(pmc_path=str(pmc)))
    assert status.state == "locked" and status.locked
    assert status.master_offset_ns == -142 and status.gm_present is True
    assert "00a069.fffe.0b552d" in status.detail
    assert abs(status.checked_unix_ns - time.time_ns()) < 10e9


def test_old_linuxptp_spelling_is_understood(tmp_path):
    pmc = fake_pmc(tmp_path, time_status(12, True, spelling="MANAGMENT"))
    assert read_ptp_status(PtpConfig(pmc_path=str(pmc))).state == "locked"


def test_large_offset_is_unlocked(tmp_path):
    pmc = fake_pmc(tmp_path, time_status(250_000, True))
    status = read_ptp_status(PtpConfig(pmc_path=str(pmc), lock_threshold_ns=1000))
    assert status.state == "unlocked" and not status.locked
    assert status.master_offset_ns == 250_000
    assert "250000" in status.detail and "1000" in status.detail
    loose = read_ptp_status(PtpConfig(pmc_path=str(pmc), lock_threshold_ns=500_000))
    assert loose.state == "locked"


def test_no_grandmaster_is_unlocked(tmp_path):
    pmc = fake_pmc(tmp_path, time_status(0, False))
    status = read_ptp_status(PtpConfig(pmc_path=str(pmc)))
    assert status.state == "unlocked" and status.gm_present is False
    assert "gmPresent false" in status.detail


def test_no_answer_means_no_ptp4l(tmp_path):
    """pmc with no ptp4l to ask prints only what it sent."""
    pmc = fake_pmc(tmp_path, HEADER)
    status = read_ptp_status(PtpConfig(pmc_path=str(pmc)))
    assert status.state == "no_ptp4l"
    assert status.master_offset_ns is None and status.gm_present is None
    assert "ptp4l" in status.detail


def test_a_pmc_that_hangs_times_out_as_no_ptp4l(tmp_path):
    pmc = fake_pmc(tmp_path, time_status(1, True), sleep_s=10)
    t0 = time.monotonic()
    status = read_ptp_status(PtpConfig(pmc_path=str(pmc), timeout_s=0.5))
    assert time.monotonic() - t0 < 5
    assert status.state == "no_ptp4l" and "0.5 s" in status.detail


def test_missing_binary_is_no_pmc(tmp_path, monkeypatch):
    status = read_ptp_status(PtpConfig(pmc_path=str(tmp_path / "nowhere" / "pmc")))
    assert status.state == "no_pmc" and "linuxptp" in status.detail
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    status = read_ptp_status(PtpConfig())
    assert status.state == "no_pmc" and "PATH" in status.detail


def test_pmc_is_found_on_path(tmp_path, monkeypatch):
    fake_pmc(tmp_path / "bin", time_status(3, True))
    monkeypatch.setenv("PATH", str(tmp_path / "bin") + os.pathsep + os.environ.get("PATH", ""))
    assert read_ptp_status(PtpConfig()).state == "locked"


def test_disabled():
    status = read_ptp_status(PtpConfig(source="none", pmc_path="/definitely/not/here"))
    assert status.state == "disabled" and not status.locked


def test_parse_error_response_and_garbage():
    text = (
        HEADER + "\t90e2ba.fffe.20c7f8-0 seq 0 RESPONSE MANAGEMENT_ERROR_STATUS TIME_STATUS_NP\n"
        "\t\tERROR: NOT_SUPPORTED\n"
    )
    fields = parse_time_status(text)
    assert fields is not None and "NOT_SUPPORTED" in fields["error"]
    assert parse_time_status("") is None
    assert parse_time_status("uds: sendto failed: No such file or directory\n") is None


def test_error_response_is_unlocked(tmp_path):
    text = (
        HEADER + "\t90e2ba.fffe.20c7f8-0 seq 0 RESPONSE MANAGEMENT_ERROR_STATUS TIME_STATUS_NP\n"
        "\t\tERROR: NOT_SUPPORTED\n"
    )
    status = read_ptp_status(PtpConfig(pmc_path=str(fake_pmc(tmp_path, text))))
    assert status.state == "unlocked" and "NOT_SUPPORTED" in status.detail


def test_monitor_follows_the_clock(tmp_path):
    pmc_dir = tmp_path / "bin"
    fake_pmc(pmc_dir, HEADER)
    config = PtpConfig(pmc_path=str(pmc_dir / "pmc"), poll_interval_s=0.05)
    with PtpMonitor(config) as monitor:
        first = monitor.latest
        assert first is not None and first.state == "no_ptp4l"
        fake_pmc(pmc_dir, time_status(20, True))  # ptp4l comes up and locks
        status = monitor.wait_for_lock(timeout_s=10)
        assert status is not None and status.state == "locked"
        assert status.checked_unix_ns > first.checked_unix_ns
        fake_pmc(pmc_dir, time_status(90_000, True))
        status = monitor.wait_for(("unlocked",), timeout_s=10)
        assert status is not None and status.master_offset_ns == 90_000


def test_wait_for_lock_times_out_with_the_latest_status(tmp_path):
    config = PtpConfig(pmc_path=str(fake_pmc(tmp_path, HEADER)), poll_interval_s=0.05)
    with PtpMonitor(config) as monitor:
        t0 = time.monotonic()
        status = monitor.wait_for_lock(timeout_s=0.3)
        assert 0.25 < time.monotonic() - t0 < 5
        assert status is not None and status.state == "no_ptp4l"


def test_config_from_table():
    cfg = read_table(PtpConfig, {"source": "pmc", "lock_threshold_ns": 500}, "node.toml [ptp]")
    assert cfg.lock_threshold_ns == 500 and cfg.require_lock and cfg.poll_interval_s == 1.0
    assert read_table(PtpConfig, {}, "x") == PtpConfig()
    with pytest.raises(ConfigError, match=r"node.toml \[ptp\]: source = 'gps'.*'pmc', 'none'"):
        read_table(PtpConfig, {"source": "gps"}, "node.toml [ptp]")
    with pytest.raises(ConfigError, match="lock_threshold_ns = -5"):
        read_table(PtpConfig, {"lock_threshold_ns": -5}, "node.toml [ptp]")
    with pytest.raises(ConfigError, match="require_lock = 'yes'"):
        read_table(PtpConfig, {"require_lock": "yes"}, "node.toml [ptp]")
    with pytest.raises(ConfigError, match=r"unknown option.*treshold"):
        read_table(PtpConfig, {"treshold": 5}, "node.toml [ptp]")
    with pytest.raises(ValueError):
        PtpStatus(state="sort of", checked_unix_ns=0)


def test_parse_all_three_answers_and_the_utc_lead():
    answers = parse_responses(time_status(7, True, stamping="HARDWARE"))
    assert set(answers) == {"TIME_STATUS_NP", "PORT_PROPERTIES_NP", "TIME_PROPERTIES_DATA_SET"}
    assert answers["PORT_PROPERTIES_NP"]["interface"] == "eth1"
    assert utc_lead_ns(answers["TIME_PROPERTIES_DATA_SET"]) == 37_000_000_000
    assert utc_lead_ns({"ptpTimescale": "0", "currentUtcOffset": "37"}) == 0


def _hardware_pmc(tmp_path: Path, monkeypatch, offset_ns: int | OSError) -> PtpConfig:
    """A hardware-timestamping ptp4l on eth1 whose PHC reads ``offset_ns`` off the system clock."""

    def system_offset_ns(device: str, expected_ns: int = 0) -> tuple[int, int]:
        assert expected_ns == 37_000_000_000  # the PHC runs on TAI, ptp4l says so
        if isinstance(offset_ns, OSError):
            raise offset_ns
        return offset_ns, 500

    monkeypatch.setattr(phc, "phc_device", lambda iface: "/dev/ptp3" if iface == "eth1" else None)
    monkeypatch.setattr(phc, "system_offset_ns", system_offset_ns)
    pmc = fake_pmc(tmp_path, time_status(40, True, stamping="HARDWARE"))
    return PtpConfig(pmc_path=str(pmc))


def test_hardware_timestamping_is_locked_only_when_the_system_clock_follows(tmp_path, monkeypatch):
    """ptp4l locked on the NIC is not enough: the frames are stamped with CLOCK_REALTIME."""
    status = read_ptp_status(_hardware_pmc(tmp_path, monkeypatch, -800))
    assert status.state == "locked" and status.system_offset_ns == -800
    assert "/dev/ptp3" in status.detail and status.master_offset_ns == 40
    status = read_ptp_status(_hardware_pmc(tmp_path, monkeypatch, 3_000_000))
    assert status.state == "unlocked" and status.system_offset_ns == 3_000_000
    assert "phc2sys" in status.detail and "egosurg-phc2sys@eth1" in status.detail


def test_an_unreadable_phc_is_unlocked_and_names_the_fix(tmp_path, monkeypatch):
    denied = PermissionError(13, "Permission denied", "/dev/ptp3")
    status = read_ptp_status(_hardware_pmc(tmp_path, monkeypatch, denied))
    assert status.state == "unlocked" and "/dev/ptp3" in status.detail
    assert "60-egosurg-ptp.rules" in status.detail


def test_phc_lookup_and_the_sandwich_read(monkeypatch):
    assert phc.phc_index("lo") == -1 and phc.phc_device("lo") is None  # the real ioctl
    with pytest.raises(OSError):
        phc.phc_index("no-such-if0")
    reads = iter([1_000, 38_000_002_000, 1_100])  # realtime, PHC (TAI: +37 s), realtime
    monkeypatch.setattr(phc.os, "open", lambda path, flags: 99)
    monkeypatch.setattr(phc.os, "close", lambda fd: None)
    monkeypatch.setattr(phc, "_READS", 1)
    monkeypatch.setattr(phc.time, "clock_gettime_ns", lambda clock: next(reads))
    offset_ns, uncertainty_ns = phc.system_offset_ns("/dev/ptp0", expected_ns=37_000_000_000)
    assert offset_ns == 38_000_002_000 - 1_050 - 37_000_000_000 and uncertainty_ns == 51


def test_a_port_that_hears_no_master_is_unlocked_whatever_the_stale_offset(tmp_path):
    """linuxptp 3.1 after the grandmaster goes: gmPresent true, the last offset, port LISTENING."""
    pmc = fake_pmc(tmp_path, time_status(256, True, port_state="LISTENING"))
    status = read_ptp_status(PtpConfig(pmc_path=str(pmc)))
    assert status.state == "unlocked" and "LISTENING" in status.detail
    settling = fake_pmc(tmp_path / "b", time_status(256, True, port_state="UNCALIBRATED"))
    assert read_ptp_status(PtpConfig(pmc_path=str(settling))).state == "locked"
