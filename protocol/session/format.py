"""The session file's schema, shared by its writer and its reader: names, types, errors.

The layout is documented for readers without EgoSurg in ``docs/session.md``; ``protocol.session``
re-exports everything public here, in ``protocol.session.write`` and in ``protocol.session.read``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from protocol.errors import UserError

FORMAT = "egosurg-session"
# Version 2 added the per-frame checksums (required in a version-2 file: one that lacks them has
# been damaged or edited, which only the version can tell) and the take links of a resumed take.
FORMAT_VERSION = 2
# Version 3 is a sealed session (``protocol.session.sealed``): its images and case values are
# ciphertext that an older reader would misread. Plaintext sessions are still written as
# version 2, so every reader that read them still does.
SEALED_FORMAT_VERSION = 3
NEWEST_FORMAT_VERSION = SEALED_FORMAT_VERSION  # the newest version this code reads
OLDEST_FORMAT_VERSION = 1  # every version a reader of this code still reads
ENCODINGS = ("jpeg", "raw_bgr8")

# Column name -> dtype of the per-camera frame table of version 1, in file order.
FRAME_COLUMNS_V1: dict[str, type[np.generic]] = {
    "capture_unix_ns": np.int64,
    "host_receive_unix_ns": np.int64,
    "recorder_receive_unix_ns": np.int64,
    "frame_index": np.int64,
    "seq": np.int64,
    "ptp_offset_ns": np.int64,
    "ptp_locked": np.uint8,
    "left_offset": np.uint64,
    "left_length": np.uint32,
    "right_offset": np.uint64,
    "right_length": np.uint32,
}
# xxHash's XXH3 (64-bit, seed 0) of each image exactly as stored, from format_version 2 on.
CHECKSUM_COLUMNS: dict[str, type[np.generic]] = {
    "left_xxh3_64": np.uint64,
    "right_xxh3_64": np.uint64,
}
# The frame table this version writes.
FRAME_COLUMNS: dict[str, type[np.generic]] = {**FRAME_COLUMNS_V1, **CHECKSUM_COLUMNS}
# A sealed session's frame table: each image's associated data names ``sealed_row``, the row it
# was recorded at (equal to the row, except in a recovered file that left frames out).
SEALED_FRAME_COLUMNS: dict[str, type[np.generic]] = {**FRAME_COLUMNS, "sealed_row": np.uint64}
GAP_COLUMNS: dict[str, type[np.generic]] = {
    "camera_serial": np.int64,
    "kind": np.uint8,
    "first_missing_frame_index": np.int64,
    "missing_count": np.int64,
    "start_unix_ns": np.int64,
    "end_unix_ns": np.int64,
}
SUMMARY_COLUMNS = ("frames", "missing_frames", "gap_records", "image_bytes")
# The session events (``/events``): what happened to the links and streams during the take.
# A file written before the table existed has no ``/events`` group; it reads as no events.
EVENT_NODE_ID_BYTES = 32  # a node id's bound on the wire (UTF-8)
EVENT_DETAIL_BYTES = 240  # a detail line, cut at a character boundary (UTF-8)
EVENT_COLUMNS: dict[str, np.dtype] = {
    "time_unix_ns": np.dtype(np.int64),
    "kind": np.dtype(np.uint8),
    "node_id": np.dtype(f"S{EVENT_NODE_ID_BYTES}"),
    "camera_serial": np.dtype(np.int64),  # -1: the event is the node's, not one camera's
    "count": np.dtype(np.int64),  # occurrences the row stands for (a flood is aggregated)
    "detail": np.dtype(f"S{EVENT_DETAIL_BYTES}"),
}

# The chunk size of the image byte datasets this version writes. Readers never depend on it:
# images are located by offset and length, whatever the chunking of the file.
BLOB_CHUNK_BYTES = 1 << 20
TABLE_CHUNK_ROWS = 4096  # 32 KiB of int64


def frame_columns(format_version: int) -> dict[str, type[np.generic]]:
    """The frame table's columns in a file of ``format_version``."""
    if format_version >= SEALED_FORMAT_VERSION:
        return SEALED_FRAME_COLUMNS
    return FRAME_COLUMNS if format_version >= 2 else FRAME_COLUMNS_V1


class SessionFormatError(UserError, ValueError):
    """Not an EgoSurg session, an unsupported format_version, or an inconsistent file."""


class SessionNotFoundError(SessionFormatError, FileNotFoundError):
    """The session file does not exist."""


class ImageChecksumError(SessionFormatError):
    """An image's bytes no longer match the checksum stored when it was recorded."""

    def __init__(self, path: Path, camera_serial: int, row: int, side: str) -> None:
        self.camera_serial, self.row, self.side = camera_serial, row, side
        super().__init__(
            f"{path}: camera {camera_serial} row {row} {side} image does not match its "
            "recorded checksum (xxh3_64): its bytes changed after it was recorded; "
            "'egosurg session verify' lists every damaged image"
        )


class ImageSealError(ImageChecksumError):
    """A sealed image that does not open where it is read (its AES-GCM tag fails): changed
    bytes whose checksum was forged too, or an image moved from another row or session. An
    ``ImageChecksumError``, so every command treats it as it treats a damaged image."""

    def __init__(self, path: Path, camera_serial: int, row: int, side: str) -> None:
        self.camera_serial, self.row, self.side = camera_serial, row, side
        SessionFormatError.__init__(
            self,
            f"{path}: camera {camera_serial} row {row} {side} image does not open with the "
            "session's key (AES-GCM tag): its bytes were changed, or it was moved here from "
            "another row, camera or session; 'egosurg session verify' lists every such image",
        )


class SessionWriteError(UserError, OSError):
    """The session file cannot be created or written (it exists, no directory, disk full...)."""


class GapKind(enum.IntEnum):
    """Why frames are missing; the value is the ``kind`` code stored in ``/gaps/kind``."""

    FRAME_INDEX_GAP = 1  # the camera's frame_index skipped: the camera or its SDK dropped frames
    SEQ_GAP = 2  # the publisher's seq skipped: messages lost in transport
    TIME_GAP = 3  # capture_unix_ns jumped by more than 1.5x the median frame interval
    RECONNECT = 4  # the camera reconnected or its agent restarted


class EventKind(enum.IntEnum):
    """What a session event records; the value is the ``kind`` code stored in ``/events/kind``."""

    LINK_DROPPED = 1  # the recorder's link to a node's publisher went down
    HANDSHAKE_FAILED = 2  # a (re)connection's CURVE handshake was refused, by either side
    LINK_RECONNECTED = 3  # the link came back (detail: after how long, the cause)
    PUBLISHER_CHANGED = 4  # a node's publisher restarted or was replaced mid-take
    RATE_CAPPED = 5  # a camera's frames came faster than 1.5x its fps: the excess refused
    BYTES_CAPPED = 6  # a camera's bytes exceeded its budget (fps x largest frame): refused
    STAMP_BACKWARDS = 7  # a camera's capture stamp went back or repeated: frame refused
    IMPLAUSIBLE_JUMP = 8  # frame_index or seq jumped by over an hour of frames: a reconnect
    MESSAGE_REFUSED = 9  # a message over the size limits, refused where it was decoded


def event_text(text: str, limit_bytes: int) -> bytes:
    """``text`` as UTF-8 of at most ``limit_bytes``, cut at a character boundary."""
    raw = text.encode("utf-8", "replace")
    if len(raw) <= limit_bytes:
        return raw
    return raw[:limit_bytes].decode("utf-8", "ignore").encode("utf-8")


@dataclass(frozen=True, kw_only=True)
class SessionEvent:
    """One row of ``/events``: ``camera_serial`` is -1 for an event of the node as a whole;
    ``count`` is how many occurrences the row stands for (more than 1 when a flood of one
    kind from one node was aggregated)."""

    time_unix_ns: int
    kind: EventKind
    node_id: str
    camera_serial: int
    count: int
    detail: str


@dataclass(frozen=True, kw_only=True)
class CameraInfo:
    """One stereo camera of a recording, as stored in ``/cameras/<serial>`` attributes."""

    camera_serial: int
    node_id: str
    resolution: str
    width: int
    height: int
    fps_nominal: float
    encoding: str
    factory_conf_text: str = ""

    def __post_init__(self) -> None:
        if self.camera_serial < 0:
            raise ValueError(f"camera_serial must be >= 0, got {self.camera_serial}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.camera_serial}: bad size {self.width}x{self.height}")
        if not self.fps_nominal > 0:
            raise ValueError(f"camera {self.camera_serial}: fps_nominal must be > 0")
        if self.encoding not in ENCODINGS:
            raise ValueError(
                f"camera {self.camera_serial}: encoding {self.encoding!r} is not one of {ENCODINGS}"
            )


@dataclass(frozen=True, kw_only=True)
class GapRecord:
    """One row of ``/gaps``. -1 in an integer field means unknown."""

    camera_serial: int
    kind: GapKind
    first_missing_frame_index: int
    missing_count: int
    start_unix_ns: int
    end_unix_ns: int


@dataclass(frozen=True, kw_only=True)
class SessionInfo:
    """The root attributes and camera descriptions of a session file."""

    path: Path
    format_version: int
    session_name: str
    case_metadata: dict[str, str]
    software_version: str
    rig_config_toml: str
    tolerance_ns: int
    started_unix_ns: int
    stopped_unix_ns: int  # 0 unless closed cleanly
    closed_cleanly: bool
    camera_serials: tuple[int, ...]  # the column order of the sets' members
    cameras: tuple[CameraInfo, ...] = field(default=())
    # A take resumed after the recorder was killed continues in a new file: the earlier part's
    # file name (same folder) and this file's part number, 1 for a take's first file.
    previous_session_file: str = ""
    take_part: int = 1
    # A sealed session (format_version 3): without an identity, ``case_metadata``'s values and
    # ``rig_config_toml`` read as ``"<sealed>"`` (the keys stay readable).
    sealed: bool = False

    @property
    def has_checksums(self) -> bool:
        """Whether each image has its XXH3-64 stored (format_version 2 on)."""
        return self.format_version >= 2

    def camera(self, serial: int) -> CameraInfo:
        for cam in self.cameras:
            if cam.camera_serial == serial:
                return cam
        raise KeyError(f"{self.path}: no camera {serial}; cameras are {list(self.camera_serials)}")


class SetTable(NamedTuple):
    """Synchronised sets: ``members[i, c]`` is the frame row of camera c in set i, or -1."""

    set_unix_ns: np.ndarray  # (N,) int64
    members: np.ndarray  # (N, C) int64
    spread_ns: np.ndarray  # (N,) int64
