"""linuxptp's ``pmc``: the command line the agent runs and the answers it reads.

Its answer to the three questions looks like this (linuxptp 3.1; older versions spell
``MANAGMENT``)::

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
               90e2ba.fffe.20c7f8-1 seq 1 RESPONSE MANAGEMENT PORT_PROPERTIES_NP
                       portIdentity            90e2ba.fffe.20c7f8-1
                       portState               SLAVE
                       timestamping            HARDWARE
                       interface               eth1
               90e2ba.fffe.20c7f8-0 seq 2 RESPONSE MANAGEMENT TIME_PROPERTIES_DATA_SET
                       currentUtcOffset      37
                       ...
                       ptpTimescale          1

An answer is a ``RESPONSE`` line naming the management ID, then its indented ``name value``
fields; an error is ``RESPONSE MANAGEMENT_ERROR_STATUS <ID>``. When ptp4l cannot be reached pmc
prints only the ``sending:`` lines.
"""

from __future__ import annotations

import re

PMC_QUERIES = ("GET TIME_STATUS_NP", "GET PORT_PROPERTIES_NP", "GET TIME_PROPERTIES_DATA_SET")
_RESPONSE = re.compile(r"\sseq\s+\d+\s+RESPONSE\s+(MANAGE?MENT\S*)\s+(\S+)")


def pmc_argv(exe: str, ptp4l_socket: str, client_socket: str) -> list[str]:
    """pmc's command line: over UDS (``-u``) to this node's ptp4l only (``-b 0``), at ptp4l's
    ``uds_address`` (``-s``), answered at ``client_socket`` (``-i``), the three questions."""
    return [exe, "-u", "-b", "0", "-s", ptp4l_socket, "-i", client_socket, *PMC_QUERIES]


def parse_responses(text: str) -> dict[str, dict[str, str]]:
    """The fields of each management answer in pmc's output, by its ID (the first of each).

    An error response (``MANAGEMENT_ERROR_STATUS``) gives ``{"error": <its text>}``.
    """
    lines = text.splitlines()
    found: dict[str, dict[str, str]] = {}
    for i, line in enumerate(lines):
        m = _RESPONSE.search(line)
        if m is None or m.group(2) in found:
            continue
        fields: dict[str, str] = {}
        for body in lines[i + 1 :]:
            if _RESPONSE.search(body) or not body[:1].isspace():
                break
            parts = body.split(None, 1)
            if parts:
                fields[parts[0]] = parts[1].strip() if len(parts) > 1 else ""
        if "ERROR" in m.group(1):
            fields = {"error": " ".join(f"{k} {v}".strip() for k, v in fields.items()) or line}
        found[m.group(2)] = fields
    return found


def parse_time_status(text: str) -> dict[str, str] | None:
    """The fields of the first TIME_STATUS_NP response in pmc's output, or None if there is none."""
    return parse_responses(text).get("TIME_STATUS_NP")


def utc_lead_ns(time_properties: dict[str, str]) -> int:
    """How far the PHC's timescale runs ahead of CLOCK_REALTIME (UTC), as phc2sys -w sets it."""
    if time_properties.get("ptpTimescale") != "1":
        return 0
    try:
        return int(time_properties.get("currentUtcOffset", "0")) * 1_000_000_000
    except ValueError:
        return 0
