"""``egosurg sim roles`` on a recorded session: the times it covers come from its sets."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from protocol.formats.trajectory import read_trajectories
from protocol.session import CameraInfo, SessionWriter
from sim.timing import SIM_EPOCH_UNIX_NS
from tests.helpers import run_egosurg


def _session(path: Path, first_set_offset_ns: int) -> Path:
    """A sim session (seed 3, intraoperative) whose first set lies ``first_set_offset_ns``
    from its start, then one set every 66.7 ms."""
    jpeg = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    cam = CameraInfo(camera_serial=7, node_id="n", resolution="HD1200", width=8, height=8,
                     fps_nominal=15.0, encoding="jpeg", factory_conf_text="")  # fmt: skip
    meta = {"seed": "3", "phase": "intraoperative"}
    start = SIM_EPOCH_UNIX_NS + 5_000_000_000
    with SessionWriter(path, session_name="live", case_metadata=meta, cameras=[cam],
                       tolerance_ns=33_000_000, software_version="test",
                       started_unix_ns=start) as writer:  # fmt: skip
        for k in range(4):
            t = start + first_set_offset_ns + k * 66_666_667
            row = writer.append_frame(7, left=jpeg, right=jpeg, capture_unix_ns=t,
                                      host_receive_unix_ns=t, recorder_receive_unix_ns=t,
                                      frame_index=k, seq=k, ptp_offset_ns=0,
                                      ptp_locked=True)  # fmt: skip
            writer.append_set(t, [row], 0)
        writer.close(t + 1)
    return path


def test_a_first_set_stamped_just_before_the_start_still_gives_roles_from_0(tmp_path):
    """A live rig's first set can be stamped a fraction of a millisecond before the session's
    start; the roles then start at 0 s rather than the command refusing the session."""
    session = _session(tmp_path / "s.h5", first_set_offset_ns=-400_000)
    out = tmp_path / "roles.toml"
    done = run_egosurg("sim", "roles", str(session), "--every", "0.1", "--out", str(out))
    assert done.returncode == 0, done.stderr
    roles = read_trajectories(out)
    assert roles and all(r.keyframes[0].time_s == 0.0 for r in roles)
    assert all(abs(r.keyframes[-1].time_s - 0.1) < 1e-9 for r in roles)  # sets end at 0.2 s
