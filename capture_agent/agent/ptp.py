"""PTP state of this node, read from linuxptp's ``pmc`` as the agent's own (unprivileged) user.

Each node runs ``ptp4l`` (PTP on the NIC's hardware clock) and ``phc2sys`` (the system clock
follows the NIC clock), so the ZED SDK's image stamps, taken on the system clock, are on the rig's
common timeline. A camera must not be opened before the clock is locked: the SDK slews, it does
not step, after a jump.

How the state is read, step by step:

1. run ``pmc -u -b 0 -s SOCKET -i CLIENT 'GET TIME_STATUS_NP' 'GET PORT_PROPERTIES_NP'
   'GET TIME_PROPERTIES_DATA_SET'`` with a timeout. ``-s`` is ptp4l's ``uds_address``
   (``[ptp] ptp4l_socket``); ``-i`` is pmc's own reply socket, made in a fresh private folder
   under the unit's RuntimeDirectory (``/run/egosurg``), because pmc's default,
   ``/var/run/pmc.<pid>``, only root may create. The service user may write to ptp4l's socket
   (mode 0660) because ptp4l runs with ``Group=egosurg`` (capture_agent/systemd/
   egosurg-ptp4l@.service; linuxptp 4 also offers a read-only ``uds_ro_address``);
2. the answers are parsed by capture_agent/agent/pmc.py (its docstring shows one);
3. the state is
   - ``no_pmc``: the ``pmc`` binary is missing (install linuxptp);
   - ``no_ptp4l``: pmc ran but no RESPONSE came (ptp4l not running, its socket not reachable by
     this user, or the timeout passed);
   - ``unlocked``: ``gmPresent false`` (no grandmaster), ``|master_offset| > lock_threshold_ns``
     (the NIC's clock is off), the port not in SLAVE or UNCALIBRATED (no master heard now:
     ptp4l 3.1 keeps ``gmPresent true`` and a stale offset then), or the system clock is off
     the NIC's clock (step 4);
   - ``locked``: otherwise;
   - ``disabled``: ``source = "none"`` in the config (simulation, or a single-node bench).
4. the system clock: with ``timestamping SOFTWARE`` ptp4l steers CLOCK_REALTIME itself, so
   ``master_offset`` is the system clock's offset. Otherwise ptp4l steers the NIC's PHC and the
   PHC is read against CLOCK_REALTIME (capture_agent/agent/phc.py): more than
   ``system_clock_threshold_ns`` apart means phc2sys is not running or not locked.

``master_offset`` is the last measured offset of ptp4l's clock from the grandmaster in ns;
``system_offset_ns`` that of CLOCK_REALTIME from the PHC (None where it is ptp4l's own clock).

Example ``node.toml`` table (``protocol.formats.node_config.PtpConfig``)::

    [ptp]
    source = "pmc"
    lock_threshold_ns = 1000
    require_lock = true
    # ptp4l_socket = "/var/run/ptp4l"     # ptp4l's uds_address
    # system_clock_threshold_ns = 20000   # CLOCK_REALTIME vs the PHC
    # phc_device = ""                     # "": the PHC of ptp4l's interface (ethtool -T)
    # pmc_client_dir = ""                 # "": $RUNTIME_DIRECTORY, else the temp folder
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass, replace
from tempfile import TemporaryDirectory, gettempdir
from types import TracebackType
from typing import Any

from capture_agent.agent import phc, pmc
from protocol.formats.node_config import PtpConfig

log = logging.getLogger(__name__)

PTP_STATES = ("locked", "unlocked", "no_ptp4l", "no_pmc", "disabled")
# [ptp] settings that PtpConfig may not have yet: name -> default (see the module docstring)
_DEFAULTS: dict[str, object] = {
    "ptp4l_socket": "/var/run/ptp4l",
    "pmc_client_dir": "",
    "system_clock_threshold_ns": 20_000,
    "phc_device": "",
}


def _setting(config: PtpConfig, name: str) -> Any:
    return getattr(config, name, _DEFAULTS[name])


@dataclass(frozen=True, kw_only=True)
class PtpStatus:
    state: str
    master_offset_ns: int | None = None
    gm_present: bool | None = None
    system_offset_ns: int | None = None
    checked_unix_ns: int
    detail: str = ""

    def __post_init__(self) -> None:
        if self.state not in PTP_STATES:
            raise ValueError(f"PtpStatus.state={self.state!r}; one of {', '.join(PTP_STATES)}")

    @property
    def locked(self) -> bool:
        return self.state == "locked"


def status_from_fields(
    fields: dict[str, str], config: PtpConfig, checked_unix_ns: int
) -> PtpStatus:
    """Decide the state of ptp4l's own clock from a parsed TIME_STATUS_NP answer."""
    if "error" in fields:
        return PtpStatus(
            state="unlocked",
            checked_unix_ns=checked_unix_ns,
            detail=f"ptp4l answered with an error: {fields['error']}",
        )
    gm_text = fields.get("gmPresent", "").lower()
    gm_present = {"true": True, "false": False}.get(gm_text)
    try:
        offset: int | None = int(fields["master_offset"])
    except (KeyError, ValueError):
        offset = None
    if gm_present is None or offset is None:
        return PtpStatus(
            state="unlocked",
            master_offset_ns=offset,
            gm_present=gm_present,
            checked_unix_ns=checked_unix_ns,
            detail=f"pmc's TIME_STATUS_NP answer lacks gmPresent or master_offset: {fields}",
        )
    if not gm_present:
        state, detail = "unlocked", "ptp4l sees no grandmaster (gmPresent false)"
    elif abs(offset) > config.lock_threshold_ns:
        state = "unlocked"
        detail = f"|master_offset| {abs(offset)} ns > lock_threshold_ns {config.lock_threshold_ns}"
    else:
        state = "locked"
        detail = f"locked to grandmaster {fields.get('gmIdentity', '?')}"
    return PtpStatus(
        state=state,
        master_offset_ns=offset,
        gm_present=gm_present,
        checked_unix_ns=checked_unix_ns,
        detail=detail,
    )


def system_clock_status(
    nic: PtpStatus, answers: dict[str, dict[str, str]], config: PtpConfig
) -> PtpStatus:
    """``nic`` (ptp4l's clock locked) checked against the clock the frames are stamped with."""
    port = answers.get("PORT_PROPERTIES_NP", {})
    stamping = port.get("timestamping", "").upper()
    if stamping == "SOFTWARE":  # ptp4l steers CLOCK_REALTIME itself: master_offset is its offset
        return replace(nic, detail=f"{nic.detail}; system clock steered by ptp4l (software)")
    device = str(_setting(config, "phc_device"))
    interface = port.get("interface", "")
    try:
        if not device:
            if not interface:
                raise OSError(f"ptp4l named no interface (PORT_PROPERTIES_NP: {port})")
            device = phc.phc_device(interface) or ""
            if not device:
                raise OSError(f"{interface} has no PTP hardware clock (ethtool -T {interface})")
        lead = pmc.utc_lead_ns(answers.get("TIME_PROPERTIES_DATA_SET", {}))
        offset_ns, _ = phc.system_offset_ns(device, lead)
    except OSError as exc:
        why = exc.strerror or str(exc)
        denied = exc.errno in (errno.EACCES, errno.EPERM)
        fix = " (install capture_agent/systemd/60-egosurg-ptp.rules, docs/capture.md)"
        fix = fix if denied else ""
        return replace(
            nic,
            state="unlocked",
            detail=f"ptp4l is locked but the system clock cannot be compared with the PTP "
            f"hardware clock {device or '?'}: {why}{fix}",
        )
    threshold = int(_setting(config, "system_clock_threshold_ns"))
    if abs(offset_ns) > threshold:
        return replace(
            nic,
            state="unlocked",
            system_offset_ns=offset_ns,
            detail=f"the system clock is {offset_ns} ns off the PTP clock {device} (more than "
            f"system_clock_threshold_ns {threshold}): is phc2sys running and locked "
            f"(systemctl status egosurg-phc2sys@{interface or 'IFACE'})?",
        )
    return replace(
        nic,
        system_offset_ns=offset_ns,
        detail=f"{nic.detail}; system clock {offset_ns} ns from {device} (phc2sys)",
    )


def _client_folder(config: PtpConfig) -> str:
    # Under systemd, RuntimeDirectory=egosurg gives /run/egosurg, writable by the service user and
    # reachable by ptp4l (the host's /run); pmc's default /var/run/pmc.<pid> needs root.
    configured = str(_setting(config, "pmc_client_dir"))
    return configured or os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0] or gettempdir()


def _run_pmc(argv: list[str], config: PtpConfig) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        argv, capture_output=True, text=True, timeout=config.timeout_s, check=False
    )


def read_ptp_status(config: PtpConfig) -> PtpStatus:
    """Ask the local ptp4l through pmc, once (blocks up to ``config.timeout_s``)."""
    checked = time.time_ns()
    if config.source == "none":
        return PtpStatus(state="disabled", checked_unix_ns=checked, detail="PTP source is 'none'")
    exe = shutil.which(config.pmc_path)
    if exe is None:
        where = "on PATH" if os.sep not in config.pmc_path else "there"
        return PtpStatus(
            state="no_pmc",
            checked_unix_ns=checked,
            detail=f"pmc program {config.pmc_path!r} not found {where}; install linuxptp "
            "(apt install linuxptp) or set [ptp] pmc_path",
        )
    try:
        folder = TemporaryDirectory(prefix="pmc.", dir=_client_folder(config))
    except OSError as exc:
        return PtpStatus(
            state="no_ptp4l",
            checked_unix_ns=checked,
            detail=f"no folder for pmc's reply socket in {_client_folder(config)}: "
            f"{exc.strerror}; set [ptp] pmc_client_dir or the unit's RuntimeDirectory",
        )
    try:
        with folder:
            socket_path = str(_setting(config, "ptp4l_socket"))
            argv = pmc.pmc_argv(exe, socket_path, os.path.join(folder.name, "c"))
            proc = _run_pmc(argv, config)
    except subprocess.TimeoutExpired:
        return PtpStatus(
            state="no_ptp4l",
            checked_unix_ns=checked,
            detail=f"pmc got no answer within {config.timeout_s} s; is ptp4l running?",
        )
    except OSError as exc:
        return PtpStatus(
            state="no_pmc", checked_unix_ns=checked, detail=f"cannot run {exe}: {exc.strerror}"
        )
    answers = pmc.parse_responses(proc.stdout)
    fields = answers.get("TIME_STATUS_NP")
    if fields is None:
        err = proc.stderr.strip().splitlines()
        why = f": {err[-1]}" if err else ""
        socket_path = _setting(config, "ptp4l_socket")
        return PtpStatus(
            state="no_ptp4l",
            checked_unix_ns=checked,
            detail=f"pmc (exit {proc.returncode}) got no TIME_STATUS_NP answer{why}; is ptp4l "
            f"running (systemctl status egosurg-ptp4l@IFACE), and may this user write to its "
            f"socket {socket_path} (ptp4l's group, docs/capture.md)?",
        )
    nic = port_status(status_from_fields(fields, config, checked), answers)
    return system_clock_status(nic, answers, config) if nic.locked else nic


def port_status(nic: PtpStatus, answers: dict[str, dict[str, str]]) -> PtpStatus:
    """``nic`` unlocked unless ptp4l's port listens to a master now.

    Seen with linuxptp 3.1: when the grandmaster goes away a slave-only ptp4l keeps saying
    ``gmPresent true`` and its last ``master_offset`` while its port drops to LISTENING. A port
    in UNCALIBRATED (servo settling, or ``free_running``) counts: its offset is measured afresh
    and the threshold judges it.
    """
    state = answers.get("PORT_PROPERTIES_NP", {}).get("portState", "").upper()
    if not nic.locked or state in ("SLAVE", "UNCALIBRATED"):
        return nic
    return replace(
        nic,
        state="unlocked",
        detail=f"ptp4l's port is {state or 'unknown'}, not following a master (its last "
        f"offset, {nic.master_offset_ns} ns, is stale)",
    )


class PtpMonitor:
    """Polls ``read_ptp_status`` in a background thread; ``latest`` is the newest status.

    ``start()`` reads once before it returns, so ``latest`` is never empty after it.
    """

    def __init__(self, config: PtpConfig) -> None:
        self.config = config
        self._latest: PtpStatus | None = None
        self._changed = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def latest(self) -> PtpStatus | None:
        with self._changed:
            return self._latest

    def start(self) -> PtpMonitor:
        if self._thread is not None:
            return self
        self._update(read_ptp_status(self.config))
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="ptp-monitor", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.config.timeout_s + self.config.poll_interval_s + 1.0)
            self._thread = None

    def wait_for(self, states: tuple[str, ...], timeout_s: float) -> PtpStatus | None:
        """Block until the latest state is one of ``states`` (returns it) or the timeout passes
        (returns the latest status, whatever it is)."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while self._latest is None or self._latest.state not in states:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._changed.wait(left)
            return self._latest

    def wait_for_lock(self, timeout_s: float) -> PtpStatus | None:
        return self.wait_for(("locked", "disabled"), timeout_s)

    def _run(self) -> None:
        while not self._stop.wait(self.config.poll_interval_s):
            try:
                status = read_ptp_status(self.config)
            except Exception:  # a monitor must outlive one bad poll
                log.exception("reading the PTP status failed")
                continue
            self._update(status)

    def _update(self, status: PtpStatus) -> None:
        with self._changed:
            previous = self._latest
            self._latest = status
            self._changed.notify_all()
        if previous is None or previous.state != status.state:
            level = logging.INFO if status.state in ("locked", "disabled") else logging.WARNING
            log.log(level, "PTP %s: %s", status.state, status.detail)

    def __enter__(self) -> PtpMonitor:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
