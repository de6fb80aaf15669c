"""Helpers the tests share: the real ``egosurg`` command in a subprocess, simulated sessions
recorded and cut down to chosen sets, and a calibration with one camera moved."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from protocol.camera import Pose
from protocol.formats.rig_calibration import RigCalibration

if TYPE_CHECKING:
    from sim.deploy import SimRigSpec

REPO = Path(__file__).resolve().parents[1]


def run_egosurg(*args: str, timeout: float = 300.0, cwd: Path | None = None):
    """Run the real ``egosurg`` command in a subprocess, as a user would."""
    env = dict(os.environ)
    return subprocess.run(
        [sys.executable, "-m", "protocol.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd or REPO,
        env=env,
    )


def moved_camera(cal: RigCalibration, serial: int, shift_m: np.ndarray) -> RigCalibration:
    """``cal`` with camera ``serial`` (both sensors) moved by ``shift_m`` in the world."""
    sensors = []
    for s in cal.sensors:
        if s.camera_serial == serial:
            s = replace(s, pose=Pose(R=s.pose.R, t_m=s.pose.t_m - s.pose.R @ shift_m))
        sensors.append(s)
    return replace(cal, sensors=tuple(sensors))


def copy_sets(
    source: Path, target: Path, set_rows: np.ndarray, *, drop_serial: int | None = None
) -> None:
    """A session holding only the sets ``set_rows`` of ``source`` (their frames, byte for byte);
    ``drop_serial``'s frames are left out, so its members read -1 (a missing camera)."""
    # conftest imports this module for every test, the capture tests' too: the session
    # and sim modules load only when a helper that needs them runs
    from protocol.session import SessionReader, SessionWriter

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
    from sim.deploy import SimRig, write_sim_rig

    files = write_sim_rig(directory, spec)
    with SimRig(files) as rig:
        rig.wait_streaming(timeout_s=900)
        rig.control("start", case=case)
        time.sleep(seconds)
        summary = rig.control("stop")
    return Path(summary["file"])


def loopback_rig_config(
    output_dir: Path | str,
    *,
    frames: str | None = None,
    cameras: tuple[int, ...] = (11,),
    fps: float = 30.0,
    rig_name: str = "test",
):
    """A recorder's config on free loopback ports: one agent ``n0`` with ``cameras``, plaintext
    links (CURVE is tests/capture_agent/test_security.py's), no PTP or disk-reserve checks."""
    from capture_agent.config import AgentEndpoint, RigConfig, SecurityConfig
    from sim.deploy import free_ports

    control, frames_port, agent_control = free_ports(3)
    return RigConfig(
        rig_name=rig_name,
        fps=fps,
        control_bind=f"tcp://127.0.0.1:{control}",
        output_dir=str(output_dir),
        agents=(
            AgentEndpoint(
                node_id="n0",
                frames=frames or f"tcp://127.0.0.1:{frames_port}",
                control=f"tcp://127.0.0.1:{agent_control}",
                cameras=cameras,
            ),
        ),
        require_ptp_lock=False,
        disk_reserve_gb=0.0,
        security=SecurityConfig(insecure=True),
    )
