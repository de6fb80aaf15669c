"""The session file: one HDF5 file per recording, written while it records (SWMR).

``SessionWriter`` is used by the recorder; ``SessionReader`` by the session tools, calibration and
the reconstructor. The full layout, written so anyone can read a session with plain h5py or
``h5dump``, is in ``docs/session.md``; in short::

    /                 attrs: format="egosurg-session", format_version=2, session_name, ...,
                      previous_session_file, take_part (a take resumed after a kill)
    /cameras/<serial> attrs: the CameraInfo fields; 1-D tables, one row per frame:
                      capture_unix_ns, host_receive_unix_ns, recorder_receive_unix_ns,
                      frame_index, seq, ptp_offset_ns, ptp_locked,
                      left_offset, left_length, right_offset, right_length,
                      left_xxh3_64, right_xxh3_64 (checksums of the images, version 2 on)
                      and the encoded images as received, end to end in left_bytes / right_bytes
    /sets             set_unix_ns (N,), members (N, C) row per camera or -1, spread_ns (N,)
    /gaps             camera_serial, kind, first_missing_frame_index, missing_count,
                      start_unix_ns, end_unix_ns
    /events           time_unix_ns, kind, node_id, camera_serial, count, detail: what happened
                      to the links and streams (absent in files written before it existed)
    /summary          per-camera totals and summary_json, written by a clean close
    /sealing          a sealed session only (format_version 3): key_block, recipients_json,
                      recipients_sealed; its frame tables add sealed_row

Sealed sessions. ``SessionWriter(..., recipients=[...])`` seals every image, case metadata
value and the rig text for the recipients' public keys (``protocol.session.sealed``,
``protocol.sealing``); ``SessionReader(path, identity=...)`` opens them. Without an identity a
sealed session's structure, tables, sets, gaps and events still read and ``verify`` checks each
image's checksum (over the ciphertext); its images and case values raise
``IdentityRequiredError``, naming the recipients. Plaintext sessions are written as before
(format_version 2).

Crash safety. Every dataset is created before the file switches to SWMR mode, so that a writer
killed at any moment (SIGKILL included) leaves a file that opens without ``h5clear``.
``flush()`` writes and flushes the image bytes before the tables that point into them, and the
frame tables before the sets and gaps that point at frames, so a reader never sees an index past
its data. Rows appended since the last ``flush()`` are held in memory and are lost on a kill.
Tables of a killed writer may differ in length by one flush; the reader uses the consistent
prefix and ``verify()`` notes it.

Speed. Image bytes are assembled into whole chunks and written past HDF5's chunk cache; the
byte datasets grow geometrically (their extent is a capacity; the logical end is the last
offset + length) and are trimmed at a clean close. The small tables are written once per flush.

Damaged files give a ``SessionFormatError``, never a hang (``protocol.session.open``);
``protocol.session.recover`` copies what is intact into a new file; files are owner-only and
hold no keys (``protocol.session.privacy``).

The public names live in three modules, all re-exported here: ``protocol.session.format``
(names, types, errors), ``protocol.session.write`` (``SessionWriter``) and
``protocol.session.read`` (``SessionReader``).
"""

from __future__ import annotations

from protocol.session.format import (
    BLOB_CHUNK_BYTES,
    CHECKSUM_COLUMNS,
    ENCODINGS,
    FORMAT,
    FORMAT_VERSION,
    FRAME_COLUMNS,
    GAP_COLUMNS,
    SEALED_FORMAT_VERSION,
    SEALED_FRAME_COLUMNS,
    SUMMARY_COLUMNS,
    CameraInfo,
    EventKind,
    GapKind,
    GapRecord,
    ImageChecksumError,
    ImageSealError,
    SessionEvent,
    SessionFormatError,
    SessionInfo,
    SessionNotFoundError,
    SessionWriteError,
    SetTable,
)
from protocol.session.read import SessionReader
from protocol.session.write import SessionWriter

__all__ = [
    "BLOB_CHUNK_BYTES",
    "CHECKSUM_COLUMNS",
    "ENCODINGS",
    "FORMAT",
    "FORMAT_VERSION",
    "FRAME_COLUMNS",
    "GAP_COLUMNS",
    "SEALED_FORMAT_VERSION",
    "SEALED_FRAME_COLUMNS",
    "SUMMARY_COLUMNS",
    "CameraInfo",
    "EventKind",
    "GapKind",
    "GapRecord",
    "ImageChecksumError",
    "ImageSealError",
    "SessionEvent",
    "SessionFormatError",
    "SessionInfo",
    "SessionNotFoundError",
    "SessionReader",
    "SessionWriteError",
    "SessionWriter",
    "SetTable",
]
