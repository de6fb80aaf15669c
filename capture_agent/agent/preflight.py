"""``egosurg agent --check``: the install-day preflight of one node, one table, one verdict.

Example (as the agent's service user, so that what it can read is what the agent can read)::

    sudo -u egosurg egosurg agent --check --config /etc/egosurg/node.toml

Each row is a check, ``ok`` or ``problem``; a problem's row says how to fix it. The exit code is
0 only when every row is ok: the node can record. The checks, in the order they are shown:

- ``user``: the checks run as the agent's service user (``egosurg``, the unit's ``User=``);
  as root every file and socket reads, so a key or socket the agent cannot use looks fine;
- ``python``, ``packages``: the interpreter and the versions the edge imports (numpy, pyzmq,
  OpenCV);
- ``zed sdk``: pyzed loads and the ZED SDK is 5.0 or newer, with the serials the SDK lists
  (only when a ``[[cameras]]`` table says ``source = "zed"``);
- ``camera SN<serial>``: each configured camera opens, in the configured mode (the ZED source
  reads back what the SDK chose and refuses another), then is closed;
- ``argus socket``: ``/tmp/argus_socket`` exists (GMSL cameras reach nvargus-daemon through it;
  a unit with ``PrivateTmp=yes`` would hide it);
- ``ptp``: ptp4l's state read through pmc as this user (capture_agent/agent/ptp.py);
- ``system clock``: CLOCK_REALTIME, which stamps the frames, against the PTP clock;
- ``disk``: free space where the SDK keeps its calibration files and the journal writes;
- ``keys``: the CURVE keys of ``[security]`` load (present, readable, 0600);
- ``ports``: the frames and control addresses can be bound (no other agent holds them).
"""

from __future__ import annotations

import errno
import getpass
import importlib
import os
import platform
import shutil
import socket
import stat
import sys
from collections.abc import Callable
from dataclasses import dataclass

from capture_agent.agent.ptp import read_ptp_status
from protocol.formats.node_config import NodeConfig

SERVICE_USER = "egosurg"  # capture_agent/systemd/egosurg-agent.service's User=
ARGUS_SOCKET = "/tmp/argus_socket"
MIN_FREE_DISK_BYTES = 1 << 30  # SDK calibration downloads, logs and the journal
EDGE_MODULES = (("numpy", "numpy"), ("zmq", "pyzmq"), ("cv2", "opencv"))  # what the agent imports


@dataclass(frozen=True, kw_only=True)
class Check:
    """One row of the table: what was checked, what was found, and the fix when it is wrong."""

    name: str
    ok: bool
    found: str
    fix: str = ""


def current_user() -> str:
    return getpass.getuser()


def check_user() -> Check:
    user = current_user()
    if user == "root":
        return Check(
            name="user",
            ok=False,
            found="running as root, which reads every key and socket",
            fix=f"run the check as the agent's user: sudo -u {SERVICE_USER} egosurg agent --check "
            "--config ...",
        )
    note = "" if user == SERVICE_USER else f" (the agent's unit runs as {SERVICE_USER!r})"
    return Check(name="user", ok=True, found=f"{user}{note}")


def check_python() -> Check:
    version = platform.python_version()
    ok = sys.version_info >= (3, 10)
    return Check(
        name="python",
        ok=ok,
        found=f"{version} ({sys.executable})",
        fix="" if ok else "use Python 3.10 or newer (JetPack 6's system python3)",
    )


def check_packages() -> Check:
    found, missing = [], []
    for module, label in EDGE_MODULES:
        try:
            mod = importlib.import_module(module)
        except ImportError:
            missing.append(label)
            continue
        version = mod.pyzmq_version() if module == "zmq" else getattr(mod, "__version__", "?")
        found.append(f"{label} {version}")
    if missing:
        return Check(
            name="packages",
            ok=False,
            found=", ".join(found) or "none",
            fix=f"install the edge into this Python ({', '.join(missing)} missing): "
            "docs/jetson.md, step 3",
        )
    return Check(name="packages", ok=True, found=", ".join(found))


def check_zed_sdk(config: NodeConfig) -> Check | None:
    if not any(c.source == "zed" for c in config.cameras):
        return None
    from capture_agent.errors import SdkMissingError
    from capture_agent.sources.zed_source import import_pyzed, require_sdk_version

    try:
        sl = import_pyzed()
        version = require_sdk_version(sl)
    except SdkMissingError as exc:
        found, _, fix = str(exc).partition(": ")
        return Check(name="zed sdk", ok=False, found=found, fix=fix)
    serials = sorted(int(d.serial_number) for d in sl.Camera.get_device_list())
    listed = ", ".join(f"SN{s}" for s in serials) or "no camera"
    return Check(name="zed sdk", ok=True, found=f"ZED SDK {version}; the SDK lists {listed}")


def check_cameras(config: NodeConfig) -> list[Check]:
    """Open each configured camera in its mode, then close it."""
    from capture_agent.sources import make_source

    rows = []
    for i, entry in enumerate(config.cameras, start=1):
        name = f"camera #{i} ({entry.source})"
        try:
            source = make_source(entry)
            name = f"camera SN{source.serial}" if source.serial else name
            source.open()
            try:
                res = source.resolution
                found = f"opens at {res.value} ({res.width}x{res.height}) {source.fps:g} fps"
                name = f"camera SN{source.serial}"  # a ZED opened by any serial knows it now
            finally:
                source.close()
        except Exception as exc:  # every failure is a row, never a traceback
            rows.append(Check(name=name, ok=False, found=str(exc), fix=camera_fix(entry.source)))
            continue
        rows.append(Check(name=name, ok=True, found=found))
    return rows


def camera_fix(source: str) -> str:
    if source == "zed":
        return (
            "check the serial in node.toml against ZED_Explorer --all, the GMSL cable and power, "
            "and that nvargus-daemon and zed_x_daemon run"
        )
    return f"check the [[cameras]] table of this {source} camera"


def check_argus(config: NodeConfig) -> Check | None:
    if not any(c.source == "zed" for c in config.cameras):
        return None
    path = ARGUS_SOCKET
    try:
        is_socket = stat.S_ISSOCK(os.stat(path).st_mode)
    except OSError as exc:
        return Check(
            name="argus socket",
            ok=False,
            found=f"{path}: {exc.strerror}",
            fix="sudo systemctl start nvargus-daemon; the agent's unit must not set PrivateTmp",
        )
    return Check(
        name="argus socket",
        ok=is_socket,
        found=f"{path} is {'a socket' if is_socket else 'not a socket'}",
        fix="" if is_socket else "sudo systemctl restart nvargus-daemon",
    )


def check_ptp(config: NodeConfig) -> list[Check]:
    status = read_ptp_status(config.ptp)
    ptp = Check(
        name="ptp",
        ok=status.state in ("locked", "disabled"),
        found=f"{status.state} as {current_user()}"
        + (f": {status.detail}" if status.detail else ""),
        fix="" if status.state in ("locked", "disabled") else ptp_fix(status.state),
    )
    if status.state == "disabled":
        clock = Check(name="system clock", ok=True, found="not on PTP ([ptp] source = 'none')")
    elif status.state == "locked":
        offset = status.system_offset_ns
        where = "ptp4l steers it" if offset is None else f"{offset} ns from the PTP clock"
        clock = Check(name="system clock", ok=True, found=f"on PTP time ({where})")
    else:
        clock = Check(
            name="system clock",
            ok=False,
            found="not known to follow PTP",
            fix="fix the ptp row first; then phc2sys must steer CLOCK_REALTIME from the NIC",
        )
    return [ptp, clock]


def ptp_fix(state: str) -> str:
    return {
        "no_pmc": "sudo apt install linuxptp",
        "no_ptp4l": "sudo systemctl start egosurg-ptp4l@IFACE; the agent's user must be in "
        "ptp4l's group",
        "unlocked": "wait for lock, or check the grandmaster, the VLAN and phc2sys "
        "(systemctl status egosurg-phc2sys@IFACE)",
    }.get(state, "see docs/jetson.md, step 6")


def check_disk(config: NodeConfig) -> Check:
    folders = [c.settings_dir for c in config.cameras if c.source == "zed"] or ["/"]
    path = next((f for f in folders if os.path.isdir(f)), "/")
    free = shutil.disk_usage(path).free
    ok = free >= MIN_FREE_DISK_BYTES
    return Check(
        name="disk",
        ok=ok,
        found=f"{free / 2**30:.1f} GiB free at {path}",
        fix="" if ok else f"free at least {MIN_FREE_DISK_BYTES / 2**30:.0f} GiB there",
    )


def check_keys(config: NodeConfig) -> Check:
    from capture_agent.security import LinkSecurity

    if config.security.insecure:
        return Check(name="keys", ok=True, found="none: plaintext links (insecure = true)")
    try:
        LinkSecurity.from_config(config.security)
    except Exception as exc:  # a missing, unreadable or open key: its one line is the row
        return Check(
            name="keys",
            ok=False,
            found=str(exc).splitlines()[0],
            fix=f"sudo egosurg keys generate --owner {SERVICE_USER} (docs/jetson.md, step 5)",
        )
    return Check(name="keys", ok=True, found=f"readable by {current_user()}")


def check_ports(config: NodeConfig) -> Check:
    problems: list[str] = []
    bound: list[str] = []
    for endpoint in (config.frames_bind, config.control_bind):
        why = bind_problem(endpoint)
        (problems if why else bound).append(f"{endpoint}{': ' + why if why else ''}")
    if problems:
        return Check(
            name="ports",
            ok=False,
            found="; ".join(problems),
            fix="stop what holds the port (is the agent running? systemctl stop egosurg-agent) "
            "or set frames_bind / control_bind to this node's address",
        )
    return Check(name="ports", ok=True, found="free: " + ", ".join(bound))


def bind_problem(endpoint: str) -> str:
    """Why ``endpoint`` (``tcp://host:port``) cannot be bound here; "" when it can."""
    host, _, port = endpoint.removeprefix("tcp://").rpartition(":")
    host = "0.0.0.0" if host in ("*", "") else host.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as ZeroMQ binds
        try:
            s.bind((host, int(port)))
        except OSError as exc:
            if exc.errno == errno.EADDRNOTAVAIL:
                return "not an address of this machine"
            return "in use" if exc.errno == errno.EADDRINUSE else str(exc.strerror)
    return ""


def run_checks(config: NodeConfig) -> list[Check]:
    steps: list[Callable[[], Check | list[Check] | None]] = [
        check_user,
        check_python,
        check_packages,
        lambda: check_zed_sdk(config),
        lambda: check_argus(config),
        lambda: check_cameras(config),
        lambda: check_ptp(config),
        lambda: check_disk(config),
        lambda: check_keys(config),
        lambda: check_ports(config),
    ]
    rows: list[Check] = []
    for step in steps:
        got = step()
        rows += got if isinstance(got, list) else [got] if got is not None else []
    if any(r.name == "zed sdk" and not r.ok for r in rows):  # each camera would say it again
        rows = [r for r in rows if not (r.name.startswith("camera") and not r.ok)]
    return rows


def render(rows: list[Check]) -> str:
    width = max(len(r.name) for r in rows)
    lines = [f"{'check':<{width}}  result   found / fix"]
    for r in rows:
        lines.append(f"{r.name:<{width}}  {'ok' if r.ok else 'problem':<7}  {r.found}")
        if r.fix:
            lines.append(f"{'':<{width}}  {'':<7}  fix: {r.fix}")
    verdict = (
        "this node can record"
        if all(r.ok for r in rows)
        else (f"this node cannot record: {sum(not r.ok for r in rows)} problem(s)")
    )
    return "\n".join([*lines, "", verdict])


def check_node(config: NodeConfig) -> tuple[int, str]:
    """Run every check: the exit code (0 when the node can record, 1 otherwise) and the table."""
    rows = run_checks(config)
    return (0 if all(r.ok for r in rows) else 1), render(rows)
