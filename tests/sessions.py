"""Test helper: copies of recorded sessions cut down to chosen sets, as recorded."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from protocol.session import SessionReader, SessionWriter
from sim.deploy import SimRig, SimRigSpec, write_sim_rig


def copy_sets(
    source: Path, target: Path, set_rows: np.ndarray, *, drop_serial: int | None = None
) -> None:
    """A session holding only the sets ``set_rows`` of ``source`` (their frames, byte for byte);
    ``drop_serial``'s frames are left out, so its members read -1 (a missing camera)."""
    with SessionReader(source) as reader:
        sets = reader.sets()
        serials = reader.info.camera_serials
        tables = {s: reader.frame_table(s) for s in serials}
        with SessionWriter(
            target,
            session_name="copy",
            case_metadata={},
            cameras=list(reader.info.cameras),
            tolerance_ns=reader.info.tolerance_ns,
            software_version="test",
            started_unix_ns=reader.info.started_unix_ns,
        ) as writer:
            for k in set_rows:
                members = []
                for column, serial in enumerate(serials):
                    row = int(sets.members[k, column])
                    if row < 0 or serial == drop_serial:
                        members.append(-1)
                        continue
                    left, right = reader.frame_bytes(serial, row)
                    members.append(
                        writer.append_frame(
                            serial,
                            left=left,
                            right=right,
                            capture_unix_ns=int(tables[serial]["capture_unix_ns"][row]),
                            host_receive_unix_ns=0,
                            recorder_receive_unix_ns=0,
                            frame_index=int(tables[serial]["frame_index"][row]),
                            seq=0,
                            ptp_offset_ns=0,
                            ptp_locked=True,
                        )
                    )
                writer.append_set(int(sets.set_unix_ns[k]), members, int(sets.spread_ns[k]))
            writer.close(time.time_ns())


def record_sim_session(directory: Path, spec: SimRigSpec, case: str, seconds: float) -> Path:
    """Record ``seconds`` through real agent and recorder processes of a sim rig; the file."""
    files = write_sim_rig(directory, spec)
    with SimRig(files) as rig:
        rig.wait_streaming(timeout_s=900)
        rig.control("start", case=case)
        time.sleep(seconds)
        summary = rig.control("stop")
    return Path(summary["file"])
