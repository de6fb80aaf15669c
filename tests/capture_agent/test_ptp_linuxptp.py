"""The agent's PTP reading against the real linuxptp, as an unprivileged user.

Two ptp4l daemons on a veth pair, each in its own network namespace: a master, and a slave with
software timestamping and ``free_running 1`` (it measures its offset but never steers this
machine's clock). The slave runs with group ``nogroup``, as egosurg-ptp4l@.service runs ptp4l
with ``Group=egosurg``, so its 0660 socket is the group's. A child process running as ``nobody``
(in that group) watches the slave through capture_agent/agent/ptp.py's own PtpMonitor and prints
every state it sees: locked once the master is heard, unlocked when the master is killed (ptp4l
3.1 then still says ``gmPresent true`` with a stale offset: only its port state tells). The
master's socket (group root) stays closed to it: no_ptp4l, with the fix in the message.

Needs root (namespaces), linuxptp (``apt-get install linuxptp``: make system-deps), ``ip`` and
``setpriv``; skipped otherwise.
"""

from __future__ import annotations

import json
import os
import pwd
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO

SBIN = os.pathsep.join(["/usr/sbin", "/sbin", os.environ.get("PATH", "")])
TOOLS = {name: shutil.which(name, path=SBIN) for name in ("ptp4l", "pmc", "ip", "setpriv")}


def _why_skip() -> str | None:
    if os.geteuid() != 0:
        return "needs root to make network namespaces"
    missing = [name for name, path in TOOLS.items() if path is None]
    if missing:
        return f"needs {', '.join(missing)} (apt-get install linuxptp iproute2 util-linux)"
    try:
        pwd.getpwnam("nobody")
    except KeyError:
        return "needs the unprivileged user 'nobody'"
    return None


pytestmark = pytest.mark.skipif(_why_skip() is not None, reason=_why_skip() or "")

COMMON = """[global]
network_transport L2
time_stamping software
logAnnounceInterval -2
announceReceiptTimeout 3
logSyncInterval -3
"""

# Runs as nobody: the agent's own code, with the [ptp] settings node.toml would give. The
# subclass stands for PtpConfig's socket settings until PtpConfig declares them.
MONITOR = """
import json, sys, time
from dataclasses import dataclass
from capture_agent.agent.ptp import PtpMonitor, read_ptp_status
from protocol.formats.node_config import PtpConfig

@dataclass(frozen=True, kw_only=True)
class Config(PtpConfig):
    ptp4l_socket: str = ""
    pmc_client_dir: str = ""

mode, socket_path, client_dir, pmc = sys.argv[1:5]
config = Config(pmc_path=pmc, ptp4l_socket=socket_path, pmc_client_dir=client_dir,
                lock_threshold_ns=5_000_000, poll_interval_s=0.2, timeout_s=2.0)
if mode == "once":
    s = read_ptp_status(config)
    print(json.dumps({"state": s.state, "detail": s.detail}), flush=True)
    sys.exit(0)
seen = None
with PtpMonitor(config) as monitor:
    while True:
        s = monitor.latest
        if s is not None and (s.state, s.gm_present) != seen:
            seen = (s.state, s.gm_present)
            print(json.dumps({"state": s.state, "gm_present": s.gm_present,
                              "offset_ns": s.master_offset_ns, "detail": s.detail}), flush=True)
        time.sleep(0.05)
"""


class Testbed:
    __test__ = False  # a fixture's helper, not a test class

    def __init__(self, base: Path) -> None:
        self.base = base
        tag = f"eg{os.getpid() % 100000}"
        self.netns = {"master": f"{tag}m", "slave": f"{tag}s"}
        self.links = {"master": f"{tag}a", "slave": f"{tag}b"}
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.nobody = pwd.getpwnam("nobody")

    def as_nobody(self) -> list[str]:
        uid, gid = self.nobody.pw_uid, self.nobody.pw_gid
        return [str(TOOLS["setpriv"]), f"--reuid={uid}", f"--regid={gid}", "--clear-groups"]

    def up(self) -> None:
        ip = str(TOOLS["ip"])
        for ns in self.netns.values():
            subprocess.run([ip, "netns", "add", ns], check=True)
        a, b = self.links["master"], self.links["slave"]
        subprocess.run([ip, "link", "add", a, "type", "veth", "peer", "name", b], check=True)
        for role, link in self.links.items():
            ns = self.netns[role]
            subprocess.run([ip, "link", "set", link, "netns", ns], check=True)
            subprocess.run([ip, "-n", ns, "link", "set", link, "up"], check=True)
        self.start("master", "priority1 127\n", group=0)
        # The slave's group is nobody's, as Group=egosurg gives the agent's user its socket.
        self.start("slave", "priority1 200\nslaveOnly 1\nfree_running 1\n", self.nobody.pw_gid)

    def socket(self, role: str) -> str:
        return str(self.base / f"{role}.sock")

    def start(self, role: str, extra: str, group: int) -> None:
        conf = self.base / f"{role}.cfg"
        conf.write_text(COMMON + extra + f"uds_address {self.socket(role)}\n")
        log = open(self.base / f"{role}.log", "wb")
        argv = [str(TOOLS["ip"]), "netns", "exec", self.netns[role], str(TOOLS["setpriv"])]
        argv += [f"--regid={group}", "--clear-groups", str(TOOLS["ptp4l"]), "-f", str(conf)]
        argv += ["-i", self.links[role], "-m"]
        self.procs[role] = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
        log.close()

    def stop(self, role: str) -> None:
        proc = self.procs.pop(role, None)
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)

    def down(self) -> None:
        for role in list(self.procs):
            self.stop(role)
        for ns in self.netns.values():  # deleting a namespace deletes its end of the veth
            subprocess.run([str(TOOLS["ip"]), "netns", "delete", ns], check=False)

    def logs(self) -> str:
        return "\n".join(
            f"--- {p.name}\n{p.read_text(errors='replace')[-1500:]}"
            for p in sorted(self.base.glob("*.log"))
        )


@pytest.fixture
def testbed() -> Iterator[Testbed]:
    base = Path(tempfile.mkdtemp(prefix="egosurg-ptp-"))  # short: socket paths hold 107 bytes
    base.chmod(0o755)
    client = base / "run"  # the unit's RuntimeDirectory: the service user's own folder
    client.mkdir(mode=0o700)
    os.chown(client, pwd.getpwnam("nobody").pw_uid, -1)
    bed = Testbed(base)
    try:
        bed.up()
        yield bed
    finally:
        bed.down()
        shutil.rmtree(base, ignore_errors=True)


def _monitor_argv(bed: Testbed, mode: str, role: str) -> list[str]:
    script = bed.base / "monitor.py"
    script.write_text(MONITOR)
    script.chmod(0o644)
    args = [mode, bed.socket(role), str(bed.base / "run"), str(TOOLS["pmc"])]
    return [*bed.as_nobody(), sys.executable, str(script), *args]


def _lines(proc: subprocess.Popen[str]) -> queue.Queue[str]:
    """The monitor's lines, read by a thread so that a wait can time out."""
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stdout is not None
    out = proc.stdout
    threading.Thread(target=lambda: [lines.put(line) for line in out], daemon=True).start()
    return lines


def _next_state(lines: queue.Queue[str], want: str, timeout_s: float) -> dict:
    """Read the monitor's lines until one says ``want``; fail with what it said instead."""
    seen: list[dict] = []
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        try:
            seen.append(json.loads(lines.get(timeout=left)))
        except queue.Empty:
            break
        if seen[-1]["state"] == want:
            return seen[-1]
    raise AssertionError(f"no {want!r} within {timeout_s} s; the monitor saw {seen}")


def test_lock_and_loss_of_lock_read_as_an_unprivileged_user(testbed: Testbed) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "HOME": "/"}
    once = subprocess.run(
        _monitor_argv(testbed, "once", "master"),
        capture_output=True, text=True, timeout=30, cwd=REPO, env=env,
    )  # fmt: skip
    denied = json.loads(once.stdout.strip().splitlines()[-1])
    assert denied["state"] == "no_ptp4l" and testbed.socket("master") in denied["detail"]
    assert "group" in denied["detail"]

    watch = subprocess.Popen(
        _monitor_argv(testbed, "watch", "slave"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env,
    )  # fmt: skip
    lines = _lines(watch)
    try:
        try:
            locked = _next_state(lines, "locked", timeout_s=30)
            assert locked["gm_present"] is True and abs(locked["offset_ns"]) < 5_000_000
            assert "software" in locked["detail"]
            testbed.stop("master")  # the grandmaster goes away
            lost = _next_state(lines, "unlocked", timeout_s=20)
        except AssertionError as exc:
            watch.kill()
            _, err = watch.communicate(timeout=10)
            raise AssertionError(f"{exc}\nthe monitor's stderr: {err}\n{testbed.logs()}") from None
        # linuxptp 3.1 keeps gmPresent true and the last offset; its port state tells
        assert "not following a master" in lost["detail"] or lost["gm_present"] is False
    finally:
        watch.kill()
        watch.wait(timeout=10)
    assert not list((testbed.base / "run").iterdir())  # every pmc reply socket cleaned up
