"""What is left of a damaged session's attributes, for ``protocol.session.recover``.

Why a child. A session's string attributes live in HDF5's global heap, which has no checksum;
damage there can make HDF5 loop forever inside one attribute read (``protocol.session.probe``
says how). ``salvage_attributes`` therefore reads the attributes of the root group and of every
``/cameras/<serial>`` group in a new interpreter, one attribute at a time, and the child writes
each value as a JSON line the moment it has it. If the child stops making progress for
``SALVAGE_STALL_S``, it is killed, the attribute it was reading is skipped, and so is every other
variable-length string attribute (they share the heap that looped); the child is then run again
for the rest. So a damaged heap costs one stall and one rerun, and every numeric attribute
(serials, sizes, times, the format version) still comes back.

Only attributes are read here: the frame tables and images hold no strings and are read by
``recover`` itself, each camera on its own.
"""

from __future__ import annotations

import json
import logging
import os
import select
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from protocol.camera import Resolution
from protocol.errors import ConfigError
from protocol.session.format import CameraInfo, SessionFormatError, SessionInfo
from protocol.session.open import open_unprobed
from protocol.session.read import READ_ERRORS
from protocol.toml_config import parse_toml

logger = logging.getLogger(__name__)

SALVAGE_STALL_S = 10.0  # one attribute takes milliseconds; more is a loop in HDF5
_REPO = Path(__file__).resolve().parents[2]
_CHILD = "import sys; from protocol.session.salvage import child_main; child_main(*sys.argv[1:])"


@dataclass
class Salvaged:
    """The attributes that could be read: ``attrs["/"]``, ``attrs["/cameras/101"]``, ...;
    ``groups`` every camera group the file links (readable or not); ``problems`` what was not
    read, and why, one line each."""

    attrs: dict[str, dict[str, Any]] = field(default_factory=dict)
    groups: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


def salvage_attributes(path: Path) -> Salvaged:
    """Read every attribute of ``path``'s root and camera groups that can be read, bounded in
    time (see the module docstring)."""
    out = Salvaged()
    skip: list[list[str]] = []  # [object, name] of attributes that stalled
    for _ in range(3):  # a rerun skips every string: a third stall would be a numeric one
        stalled = _run_child(path, skip, out)
        if stalled is None:
            return out
        out.problems.append(
            f"{stalled[0]} attribute {stalled[1]!r}: HDF5 did not finish reading it in "
            f"{SALVAGE_STALL_S:g} s (its string heap is damaged); skipped with every other "
            "string attribute"
        )
        skip.append(stalled)
    return out


def _run_child(path: Path, skip: list[list[str]], out: Salvaged) -> list[str] | None:
    """One child's run, its values merged into ``out``; the [object, name] it stalled on."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(_REPO), *sys.path]))
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, os.fspath(path), json.dumps(skip)],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    assert proc.stdout is not None
    reading: list[str] | None = None
    buffered = b""
    try:
        fd = proc.stdout.fileno()
        while True:
            if not select.select([fd], [], [], SALVAGE_STALL_S)[0]:
                return reading or ["/", "(opening the file)"]
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                return None
            *lines, buffered = (buffered + chunk).split(b"\n")
            for line in lines:
                reading = _merge(json.loads(line), out, reading)
    finally:
        proc.kill()
        proc.stdout.close()
        proc.wait()


def _merge(item: dict[str, Any], out: Salvaged, reading: list[str] | None) -> list[str] | None:
    """Take one line of the child's into ``out``; the attribute being read now, if any."""
    obj = item.get("object", "/")
    if "group" in item:
        if item["group"] not in out.groups:
            out.groups.append(item["group"])
        return None
    if "start" in item:
        return [obj, item["start"]]
    if "value" in item:
        out.attrs.setdefault(obj, {})[item["name"]] = item["value"]
    elif "error" in item:
        what = f"{obj} attribute {item['name']!r}" if "name" in item else obj
        out.problems.append(f"{what} cannot be read ({item['error']})")
    return None


# -- the child's side


def child_main(path: str, skip_json: str) -> None:
    """The new-interpreter child: one JSON line per group found and attribute read."""
    logging.disable(logging.CRITICAL)
    skip = {tuple(x) for x in json.loads(skip_json)}
    skip_strings = bool(skip)  # a stall was in the heap every string shares

    def emit(item: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(item) + "\n")
        sys.stdout.flush()

    try:
        f = open_unprobed(Path(path))
    except Exception as exc:
        emit({"error": _one_line(exc)})
        return
    with f:
        objects = ["/"]
        try:
            for name in f["cameras"]:
                emit({"group": f"/cameras/{name}"})
                objects.append(f"/cameras/{name}")
        except Exception as exc:
            emit({"object": "/cameras", "error": _one_line(exc)})
        for obj in objects:
            _read_object(f, obj, skip, skip_strings, emit)


def _read_object(f: h5py.File, obj: str, skip: set, skip_strings: bool, emit: Any) -> None:
    try:
        attrs = f[obj].attrs
        names = list(attrs.keys())  # names are in the object header, not the heap
    except Exception as exc:
        emit({"object": obj, "error": _one_line(exc)})
        return
    for name in names:
        try:
            is_string = h5py.check_string_dtype(attrs.get_id(name).dtype) is not None
            if (obj, name) in skip or (skip_strings and is_string):
                continue
            emit({"object": obj, "start": name})
            emit({"object": obj, "name": name, "value": _plain(attrs[name])})
        except Exception as exc:
            emit({"object": obj, "name": name, "error": _one_line(exc)})


def _plain(value: Any) -> Any:
    """An attribute's value as JSON can carry it."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.reshape(-1).tolist()]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _one_line(value: object) -> str:
    return " ".join(str(value).split())[:300]


# -- the session's description, rebuilt from what was salvaged


def rebuild_info(path: Path, f: h5py.File, s: Salvaged, notes: list[str]) -> SessionInfo:
    """A ``SessionInfo`` from the salvaged attributes, each missing one rebuilt from the rig
    text, the frame tables or a neutral default, and said in ``notes``. Cameras whose group or
    size cannot be read are left out (and said); ``SessionFormatError`` if none is left."""
    root = s.attrs.get("/", {})
    rig = _rig_table(_text(root, "rig_config_toml"))
    serials = _ints(root.get("camera_serials"))
    if not serials:
        serials = tuple(
            int(g.rsplit("/", 1)[-1]) for g in s.groups if g.rsplit("/", 1)[-1].isdigit()
        )
        notes.append(
            f"root attribute camera_serials is lost: the cameras are those the file links "
            f"({', '.join(map(str, serials))}); the sets' columns cannot be matched to them"
        )
    version = root.get("format_version")
    if version not in (1, 2, 3):  # 3: sealed, the only version with a /sealing group
        checksums = any(f"cameras/{c}/left_xxh3_64" in f for c in serials)
        version = 3 if "sealing" in f else 2 if checksums else 1
        notes.append(f"root attribute format_version is lost: {version}, from the frame tables")
    cameras = []
    for serial in serials:
        try:
            cameras.append(_camera(f, serial, s.attrs.get(f"/cameras/{serial}", {}), rig, notes))
        except READ_ERRORS as exc:  # SessionFormatError is a ValueError
            notes.append(f"camera {serial} is left out: its description is lost ({exc})")
    if not cameras:
        raise SessionFormatError(f"{path}: no camera's description and frames can be read")
    started = _int(root, "started_unix_ns", 0, notes, "the first frame's capture time")
    for cam in cameras if not started else ():
        try:
            first_ns = int(f[f"cameras/{cam.camera_serial}/capture_unix_ns"][0])
            started = min(started or first_ns, first_ns)
        except READ_ERRORS:
            continue  # a camera without a readable first frame says nothing of the start
    name = _text(root, "session_name") or path.stem
    if not _text(root, "session_name"):
        notes.append(f"root attribute session_name is lost: {name!r}, from the file name")
    period_ns = 1e9 / cameras[0].fps_nominal
    previous = _text(root, "previous_session_file")
    return SessionInfo(
        path=path,
        format_version=int(version),
        session_name=name,
        case_metadata=_metadata(root, notes),
        software_version=_text(root, "software_version"),
        rig_config_toml=_text(root, "rig_config_toml"),
        tolerance_ns=_int(root, "tolerance_ns", int(period_ns / 2), notes, "half a frame period"),
        started_unix_ns=started,
        stopped_unix_ns=_int(root, "stopped_unix_ns", 0, [], ""),
        closed_cleanly=False,
        camera_serials=tuple(c.camera_serial for c in cameras),
        cameras=tuple(cameras),
        previous_session_file=previous,
        take_part=_int(root, "take_part", 1, [], "") if previous else 1,
    )


def _camera(
    f: h5py.File, serial: int, attrs: dict[str, Any], rig: dict[str, Any], notes: list[str]
) -> CameraInfo:
    """One camera's description from its attributes, or rebuilt from the rig and its frames."""
    group = f[f"cameras/{serial}"]
    wanted = ("width", "height", "fps_nominal", "encoding", "resolution", "node_id")
    lost = [k for k in wanted if k not in attrs]
    width, height = attrs.get("width"), attrs.get("height")
    sized = isinstance(width, int) and isinstance(height, int)
    # the first image tells what is lost of the encoding and size (a camera may have no frame)
    first = _first_image(group) if not sized or "encoding" not in attrs else b""
    encoding = attrs.get("encoding") or ("jpeg" if first[:2] == b"\xff\xd8" else "raw_bgr8")
    if not sized:
        if encoding != "jpeg":
            raise SessionFormatError("its image size is lost and its images are raw")
        import cv2  # local: only a camera whose size is lost needs OpenCV

        image = cv2.imdecode(np.frombuffer(first, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise SessionFormatError("its image size is lost and its first image cannot be decoded")
        height, width = int(image.shape[0]), int(image.shape[1])
    assert isinstance(width, int) and isinstance(height, int)  # read, or decoded above
    node = attrs.get("node_id") or _rig_node(rig, serial) or "unknown"
    fps = attrs.get("fps_nominal") or rig.get("fps") or 30.0
    resolution = attrs.get("resolution") or next(
        (r.value for r in Resolution if r.size == (width, height)), f"{width}x{height}"
    )
    if lost:
        notes.append(
            f"camera {serial}: attributes {', '.join(lost)} lost; rebuilt as {width}x{height} "
            f"{encoding} at {float(fps):g} fps from node {node} (from its images and the rig text)"
        )
    if "factory_conf" not in attrs:
        notes.append(
            f"camera {serial}: its factory calibration text is lost; calibrating from this file "
            f"needs SN{serial}.conf from the camera's node"
        )
    return CameraInfo(
        camera_serial=serial,
        node_id=str(node),
        resolution=str(resolution),
        width=width,
        height=height,
        fps_nominal=float(fps),
        encoding=str(encoding),
        factory_conf_text=str(attrs.get("factory_conf", "")),
    )


def _first_image(group: h5py.Group) -> bytes:
    offset, length = int(group["left_offset"][0]), int(group["left_length"][0])
    return np.asarray(group["left_bytes"][offset : offset + min(length, 1 << 24)]).tobytes()


def _rig_table(text: str) -> dict[str, Any]:
    try:
        return parse_toml(text, "the session's rig text") if text else {}
    except ConfigError:
        return {}


def _rig_node(rig: dict[str, Any], serial: int) -> str:
    for agent in rig.get("agents", []):
        if isinstance(agent, dict) and serial in agent.get("cameras", []):
            return str(agent.get("node_id", ""))
    return ""


def _metadata(root: dict[str, Any], notes: list[str]) -> dict[str, str]:
    try:
        table = json.loads(root["case_metadata_json"])
        if isinstance(table, dict) and all(isinstance(v, str) for v in table.values()):
            return table
    except (KeyError, TypeError, ValueError):
        pass
    notes.append("root attribute case_metadata_json is lost or damaged: the case metadata is empty")
    return {}


def _text(root: dict[str, Any], name: str) -> str:
    value = root.get(name, "")
    return value if isinstance(value, str) else ""


def _int(root: dict[str, Any], name: str, default: int, notes: list[str], how: str) -> int:
    value = root.get(name)
    if isinstance(value, int) and value > 0:
        return value
    if how:
        notes.append(f"root attribute {name} is lost: {how}")
    return default


def _ints(value: Any) -> tuple[int, ...]:
    if not isinstance(value, list) or not all(isinstance(v, int) for v in value):
        return ()
    return tuple(value) if value and len(set(value)) == len(value) else ()
