"""Helpers the tests share: the real ``egosurg`` command in a subprocess, simulated sessions
recorded and cut down to chosen sets, a calibration with one camera moved, a recorder's and an
agent's config on free loopback ports, a frame message as an agent sends it, and which heavy
modules a fresh interpreter loads."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from protocol.camera import Pose
from protocol.formats.rig_calibration import RigCalibration

if TYPE_CHECKING:
    from protocol.sealing import Recipient
    from sim.deploy import SimRigSpec

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Ran:
    """What an ``egosurg`` command run in this process answered."""

    returncode: int
    stdout: str
    stderr: str

    def __iter__(self):
        """``code, out, err = egosurg_in_process(...)``."""
        return iter((self.returncode, self.stdout, self.stderr))


def egosurg_in_process(capsys, *args: str) -> Ran:
    """The real dispatcher (protocol/cli.py), in this process: torch loads once per test file."""
    from protocol.cli import main

    capsys.readouterr()
    code = main(list(args))
    out = capsys.readouterr()
    return Ran(code, out.out, out.err)


def one_camera_session(
    path: Path, *, name: str, started_unix_ns: int, set_unix_ns: Sequence[int], metadata: dict
) -> Path:
    """A session of one 8 x 8 px camera (serial 7) with one set at each of ``set_unix_ns``:
    what a review tool reads of a session's identity and times, without its pictures."""
    import cv2

    from protocol.session import CameraInfo, SessionWriter

    jpeg = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    cam = CameraInfo(camera_serial=7, node_id="demo-node", resolution="HD1200", width=8, height=8,
                     fps_nominal=15.0, encoding="jpeg", factory_conf_text="")  # fmt: skip
    with SessionWriter(path, session_name=name, case_metadata=metadata, cameras=[cam],
                       tolerance_ns=33_000_000, software_version="test",
                       started_unix_ns=started_unix_ns) as writer:  # fmt: skip
        for k, t in enumerate(set_unix_ns):
            row = writer.append_frame(7, left=jpeg, right=jpeg, capture_unix_ns=t,
                                      host_receive_unix_ns=t, recorder_receive_unix_ns=t,
                                      frame_index=k, seq=k, ptp_offset_ns=0,
                                      ptp_locked=True)  # fmt: skip
            writer.append_set(t, [row], 0)
        writer.close(set_unix_ns[-1] + 1)
    return path


def run_egosurg(
    *args: str, timeout: float = 300.0, cwd: Path | None = None, env: dict[str, str] | None = None
):
    """Run the real ``egosurg`` command in a subprocess, as a user would (in ``env``, else this
    process's environment: a sim rig's ``files.reader_env()`` names its identity)."""
    env = dict(os.environ) if env is None else env
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
    source: Path,
    target: Path,
    set_rows: np.ndarray,
    *,
    drop_serial: int | None = None,
    identity: Path | None = None,
    recipients: Sequence[Recipient] = (),
) -> None:
    """A session holding only the sets ``set_rows`` of ``source`` (their frames, byte for
    byte; a sealed ``source`` is opened with the ``identity`` file), plaintext, or sealed for
    ``recipients`` when given; ``drop_serial``'s frames are left out, so its members read -1
    (a missing camera)."""
    # conftest imports this module for every test, the capture tests' too: the session
    # and sim modules load only when a helper that needs them runs
    from protocol.sealing import load_identity
    from protocol.session import SessionReader, SessionWriter

    key = load_identity(identity) if identity is not None else None
    with SessionReader(source, identity=key) as reader:
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
            recipients=recipients,
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
    """Record ``seconds`` through real agent and recorder processes of a sim rig; the file,
    sealed for the rig's site key unless ``spec.plaintext`` (``sim_identity`` opens it)."""
    from sim.deploy import SimRig, write_sim_rig

    files = write_sim_rig(directory, spec)
    with SimRig(files) as rig:
        rig.wait_streaming(timeout_s=900)
        rig.control("start", case=case)
        time.sleep(seconds)
        summary = rig.control("stop")
    return Path(summary["file"])


def sim_identity(session: Path) -> Path:
    """The site identity that opens a session ``record_sim_session`` recorded (the sim rig's
    ``reader-keys/``, beside its ``sessions/``)."""
    from sim.deploy import READER_KEYS, SITE_KEY

    return session.parent.parent / READER_KEYS / f"{SITE_KEY}.identity"


def sim_reader_env(session: Path) -> dict[str, str]:
    """The environment of an ``egosurg`` reader of that session: its identity in
    ``EGOSURG_IDENTITY``."""
    return {**os.environ, "EGOSURG_IDENTITY": str(sim_identity(session))}


def loopback_rig_config(
    output_dir: Path | str,
    *,
    frames: str | None = None,
    cameras: tuple[int, ...] = (11,),
    fps: float = 30.0,
    rig_name: str = "test",
):
    """A recorder's config on free loopback ports: one agent ``n0`` with ``cameras``, plaintext
    links (CURVE is tests/capture_agent/test_security.py's) and plaintext sessions (sealed ones
    are tests/capture_agent/test_rig_sealing.py's), no PTP or disk-reserve checks."""
    from protocol.formats.rig_config import AgentEndpoint, RigConfig
    from protocol.formats.sealing_config import RigSealingConfig
    from protocol.formats.security_config import RigSecurityConfig
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
        security=RigSecurityConfig(insecure=True),
        sealing=RigSealingConfig(plaintext=True),
    )


def frame_message(
    node: str,
    serial: int,
    index: int,
    seq: int,
    capture_unix_ns: int,
    image: bytes,
    *,
    encoding: str = "jpeg",
    size_px: tuple[int, int] = (8, 4),
):
    """A frame message as a PTP-locked agent publishes it: received the instant it was captured,
    ``image`` as both sensors' picture, ``size_px`` its (width, height)."""
    from protocol.wire import FrameMessage

    width, height = size_px
    return FrameMessage(
        node_id=node,
        camera_serial=serial,
        frame_index=index,
        seq=seq,
        capture_unix_ns=capture_unix_ns,
        host_receive_unix_ns=capture_unix_ns,
        ptp_offset_ns=0,
        ptp_locked=True,
        encoding=encoding,
        width=width,
        height=height,
        left=image,
        right=image,
    )


def heavy_modules_after(imports: str, heavy: tuple[str, ...]) -> list[str]:
    """Which of the modules ``heavy`` a fresh interpreter has loaded once it has run the import
    lines ``imports``: in this process they may be loaded already by other tests."""
    snippet = f"import sys\n{imports}\nprint(','.join(m for m in {heavy!r} if m in sys.modules))\n"
    out = subprocess.run(
        [sys.executable, "-c", snippet], capture_output=True, text=True, check=True, cwd=REPO
    )
    return [m for m in out.stdout.strip().split(",") if m]


def loopback_sim_node(
    node_id: str,
    *,
    fps: float,
    seed: int,
    cameras: Sequence[dict] = ({},),
    where: str = "test node.toml",
    **options: object,
):
    """An agent's config on free loopback ports, read from its table as node.toml's is: one
    simulated camera per entry of ``cameras`` (each entry adds options to that camera's table),
    streaming pre-rendered JPEG content with no random drops, the cameras' clocks starting at the
    last whole second; no PTP, plaintext links (CURVE is tests/capture_agent/test_security.py's).
    ``options`` add node options (``status_interval_s``, ``watchdog_timeout_s``, ...)."""
    from protocol.formats.node_config import NodeConfig
    from sim.deploy import free_ports

    frames_port, control_port = free_ports(2)
    epoch_unix_ns = (time.time_ns() // 10**9 - 1) * 10**9
    camera_tables = [
        {
            "source": "sim",
            "seed": seed,
            "camera_index": i,
            "fps": fps,
            "epoch_unix_ns": epoch_unix_ns,
            "content_fps": 0.5,  # one picture per camera, rendered before streaming, repeated
            "prerender_s": 2.0,
            "pre_encode": "jpeg",
            "drop_probability": 0.0,
            **extra,
        }
        for i, extra in enumerate(cameras)
    ]
    table = {
        "node_id": node_id,
        "frames_bind": f"tcp://127.0.0.1:{frames_port}",
        "control_bind": f"tcp://127.0.0.1:{control_port}",
        "ptp": {"source": "none", "require_lock": False},
        "cameras": camera_tables,
        "security": {"insecure": True},
        **options,
    }
    return NodeConfig.from_table(table, where)
