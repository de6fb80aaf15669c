"""PTP state of this node, read from linuxptp's ``pmc``.

Each node runs ``ptp4l`` (PTP on the NIC's hardware clock) and ``phc2sys`` (the system clock
follows the NIC clock), so the ZED SDK's image stamps, taken on the system clock, are on the rig's
common timeline. A camera must not be opened before the clock is locked: the SDK slews, it does
not step, after a jump.

How the state is read, step by step:

1. run ``pmc -u -b 0 'GET TIME_STATUS_NP'`` (UDS to the local ptp4l, boundary hops 0: this node
   only) with a timeout;
2. its answer looks like this (linuxptp; older versions spell ``MANAGMENT``)::

       sending: GET TIME_STATUS_NP
               90e2ba.fffe.20c7f8-0 seq 0 RESPONSE MANAGEMENT TIME_STATUS_NP
                       master_offset              310
                       ingress_time               1361545089345029441
                       cumulativeScaledRateOffset   +1.000000000
                       scaledLastGmPhaseChange    0
                       gmTimeBaseIndicator        0
                       lastGmPhaseChange          0x0000'0000000000000000.0000
                       gmPresent                  true
                       gmIdentity                 00a069.fffe.0b552d

3. the state is
   - ``no_pmc``: the ``pmc`` binary is missing (install linuxptp);
   - ``no_ptp4l``: pmc ran but no RESPONSE came (ptp4l not running, or the timeout passed);
   - ``unlocked``: ``gmPresent false`` (no grandmaster) or ``|master_offset| > lock_threshold_ns``;
   - ``locked``: otherwise;
   - ``disabled``: ``source = "none"`` in the config (simulation, or a single-node bench).

``master_offset`` is the last measured offset of the NIC clock from the grandmaster in ns; the
system clock's own offset (phc2sys) is not in this answer.

Example ``node.toml`` table (``capture_agent.config.PtpConfig``)::

    [ptp]
    source = "pmc"
    lock_threshold_ns = 1000
    require_lock = true
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass
from types import TracebackType

from capture_agent.config import PtpConfig

log = logging.getLogger(__name__)

PTP_STATES = ("locked", "unlocked", "no_ptp4l", "no_pmc", "disabled")
PMC_QUERY = "GET TIME_STATUS_NP"
_RESPONSE = re.compile(r"\sseq\s+\d+\s+RESPONSE\s+(MANAGE?MENT\S*)\s+(\S+)")


@dataclass(frozen=True, kw_only=True)
class PtpStatus:
    state: str
    master_offset_ns: int | None = None
    gm_present: bool | None = None
    checked_unix_ns: int
    detail: str = ""

    def __post_init__(self) -> None:
        if self.state not in PTP_STATES:
            raise ValueError(f"PtpStatus.state={self.state!r}; one of {', '.join(PTP_STATES)}")

    @property
    def locked(self) -> bool:
        return self.state == "locked"


def parse_time_status(text: str) -> dict[str, str] | None:
    """The fields of the first TIME_STATUS_NP response in pmc's output, or None if there is none.

    An error response (``MANAGEMENT_ERROR_STATUS``) gives ``{"error": <its text>}``.
    """
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = _RESPONSE.search(line)
        if m is None or m.group(2) != "TIME_STATUS_NP":
            continue
        fields: dict[str, str] = {}
        for body in lines[i + 1 :]:
            if _RESPONSE.search(body) or not body[:1].isspace():
                break
            parts = body.split(None, 1)
            if parts:
                fields[parts[0]] = parts[1].strip() if len(parts) > 1 else ""
        if "ERROR" in m.group(1):
            return {"error": " ".join(f"{k} {v}".strip() for k, v in fields.items()) or line}
        return fields
    return None


def status_from_fields(
    fields: dict[str, str], config: PtpConfig, checked_unix_ns: int
) -> PtpStatus:
    """Decide the state from a parsed TIME_STATUS_NP answer."""
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
    argv = [exe, "-u", "-b", "0", PMC_QUERY]
    try:
        proc = subprocess.run(
            argv, capture_output=True, text=True, timeout=config.timeout_s, check=False
        )
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
    fields = parse_time_status(proc.stdout)
    if fields is None:
        err = proc.stderr.strip().splitlines()
        why = f": {err[-1]}" if err else ""
        return PtpStatus(
            state="no_ptp4l",
            checked_unix_ns=checked,
            detail=f"pmc (exit {proc.returncode}) got no TIME_STATUS_NP answer{why}; is ptp4l "
            "running (systemctl status ptp4l), and may this user reach its socket?",
        )
    return status_from_fields(fields, config, checked)


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
