"""The NIC's PTP hardware clock (PHC) read against the system clock, as the service user.

With hardware timestamping ptp4l steers the PHC, not the system clock; the frames are stamped
with CLOCK_REALTIME, which is on PTP time only while ``phc2sys`` copies the PHC onto it. phc2sys
has no socket to ask, so the agent measures what phc2sys should achieve:

1. find the interface's PHC the way ``ethtool -T`` does (SIOCETHTOOL, ETHTOOL_GET_TS_INFO gives
   ``phc_index`` N, the device ``/dev/ptpN``), unless the config names the device;
2. open it read-only (reading a dynamic POSIX clock needs only read access: the udev rule in
   capture_agent/systemd/ gives the ``egosurg`` group that) and read it between two reads of
   CLOCK_REALTIME, a few times, keeping the tightest pair (its half-width bounds the error);
3. offset = PHC - midpoint - expected, where ``expected`` is the PTP timescale's lead over UTC
   (``currentUtcOffset`` seconds when ptp4l says ``ptpTimescale 1``, as phc2sys -w applies it).

A small offset says phc2sys runs and is locked; a large one (or none) says the stamps are not
on the rig's timeline, whatever ptp4l's own offset is.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import socket
import struct
import time

SIOCETHTOOL = 0x8946
ETHTOOL_GET_TS_INFO = 0x41
_TS_INFO_BYTES = 44  # struct ethtool_ts_info: cmd, so_timestamping, phc_index, tx_types, ...
_IFREQ_BYTES = 40
_READS = 5  # sandwiches per measurement; the tightest one is kept


def phc_index(interface: str) -> int:
    """The PHC number of ``interface`` (``/dev/ptp<N>``), or -1 when it has none (veth, lo).

    Raises OSError when the interface does not exist or cannot be asked.
    """
    name = interface.encode()
    if not name or len(name) >= 16:
        raise OSError(f"{interface!r} is not a network interface name")
    info = ctypes.create_string_buffer(struct.pack("I", ETHTOOL_GET_TS_INFO), _TS_INFO_BYTES)
    request = struct.pack("16sP", name, ctypes.addressof(info))
    request += bytes(_IFREQ_BYTES - len(request))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        fcntl.ioctl(sock.fileno(), SIOCETHTOOL, request)
    index: int = struct.unpack_from("i", info.raw, 8)[0]
    return index


def phc_device(interface: str) -> str | None:
    """``/dev/ptp<N>`` of ``interface``, or None when it has no hardware clock."""
    index = phc_index(interface)
    return f"/dev/ptp{index}" if index >= 0 else None


def _dynamic_clock_id(fd: int) -> int:
    return ((~fd) << 3) | 3  # the kernel's FD_TO_CLOCKID for a POSIX clock device


def system_offset_ns(device: str, expected_ns: int = 0) -> tuple[int, int]:
    """(PHC - CLOCK_REALTIME - expected_ns, uncertainty) in ns, read from ``device``.

    Raises OSError when the device cannot be opened (absent, or this user may not read it).
    """
    fd = os.open(device, os.O_RDONLY)
    try:
        clock = _dynamic_clock_id(fd)
        best: tuple[int, int] | None = None
        for _ in range(_READS):
            before = time.clock_gettime_ns(time.CLOCK_REALTIME)
            phc = time.clock_gettime_ns(clock)
            after = time.clock_gettime_ns(time.CLOCK_REALTIME)
            width = after - before
            if best is None or width < best[1]:
                best = (phc - (before + after) // 2 - expected_ns, width)
        assert best is not None
        return best[0], best[1] // 2 + 1
    finally:
        os.close(fd)
