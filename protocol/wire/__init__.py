"""Wire messages between capture agents, the recorder and the control tools.

Every message has one encoder and one decoder. Nothing from the network is ever unpickled or
``eval``-ed: frames are a fixed binary header plus raw buffers, everything else is UTF-8 JSON.
This docstring is the whole spec; the code is one module per message kind in this folder
(``frame``, ``status``, ``control``, ``agent_info`` for the agent's status reply, and ``checks``
for what they share), and every name is imported from here: ``from protocol.wire import
FrameMessage``.

Sockets (the whole agent-recorder contract: ``docs/capture.md``, "Writing an agent")
-------------------------------------------------------------------------------------
- Agent ``PUB`` (the agent binds ``frames_bind``) -> recorder ``SUB`` (connects to every agent's
  ``frames`` in rig.toml, subscribes to everything): frame messages (3 parts) and agent status
  messages (1 part), interleaved on one socket. The receiver calls ``decode_published(parts)``,
  which dispatches on the 4-byte magic that starts the first part.
- Control, ``REQ``/``REP`` (or ``DEALER``/``ROUTER``): one ``ControlRequest`` part, answered by one
  ``ControlReply`` part. Every agent binds a ``REP`` socket (``control_bind``) that the recorder
  connects to; the recorder binds its own ``REP`` for the control tools.
- Every link is CURVE-encrypted, the binding side the CURVE server with an allow-list of client
  keys; plaintext only where the configs say ``insecure = true``.
- ``node_id`` in frames and status messages must equal the agent's ``node_id`` in rig.toml.

Frame message (magic ``b"EGSF"``), a ZeroMQ multipart message of exactly 3 parts
----------------------------------------------------------------------------------
Part 0 is a 112-byte little-endian header (``struct`` format ``"<4sHHQQQqqqQQHHBBBB32s"``, no
implicit padding; every 8-byte field sits on an 8-byte boundary)::

    offset size type   field                  meaning
    0      4    bytes  magic                  b"EGSF"
    4      2    u16    wire_version           1 (FRAME_WIRE_VERSION)
    6      2    u16    header_bytes           112, the size of this header
    8      8    u64    seq                    per publisher, +1 per frame message; a gap is a drop
    16     8    u64    camera_serial          ZED serial number
    24     8    u64    frame_index            per camera, from 0
    32     8    i64    capture_unix_ns        frame time, Unix ns, PTP-disciplined system clock
    40     8    i64    host_receive_unix_ns   agent host clock when the frame came off the camera
    48     8    i64    ptp_offset_ns          PTP master offset when the frame was taken
    56     8    u64    left_bytes             length of part 1
    64     8    u64    right_bytes            length of part 2
    72     2    u16    width                  pixels, 1..8192, both images
    74     2    u16    height                 pixels, 1..8192, both images
    76     1    u8     encoding               1 = jpeg, 2 = raw_bgr8
    77     1    u8     ptp_locked             0 or 1
    78     1    u8     node_id_bytes          1..32, length of the UTF-8 node id
    79     1    u8     reserved               0
    80     32   bytes  node_id                UTF-8, padded with NUL bytes to 32

``frame_index`` only increases while a camera stays open; after a reopen it may restart at 0 (the
recorder records a reconnect, not a loss). ``seq`` going backwards means the agent restarted.
``ptp_offset_ns`` has linuxptp's sign: this node's clock minus the grandmaster's (0 if unknown).
``width``, ``height`` and ``encoding`` equal the camera's ``cameras_info`` entry (below).

Part 1 is the left image, part 2 the right image, each sent and received without a copy
(``send_multipart(msg.to_parts(), copy=False)`` / ``recv_multipart(copy=False)``). ``jpeg`` is a
complete JPEG file (starts with ``FF D8``) that decodes to BGR; ``raw_bgr8`` is exactly
``height * width * 3`` bytes, 8-bit BGR, row-major (OpenCV's ``(height, width, 3)`` array).
Unsigned fields carry values below 2**63, so every field fits an int64 (HDF5, numpy).

Agent status message (magic ``b"EGSH"``), 1 part, about once a second per agent
---------------------------------------------------------------------------------
``b"EGSH"`` + u16 little-endian wire version (1, ``STATUS_WIRE_VERSION``) + a UTF-8 JSON object::

    {"node_id": "node-a", "sent_unix_ns": 1700000000000000000, "status_seq": 42,
     "software_version": "0.1.0",
     "ptp": {"state": "locked", "master_offset_ns": -12, "gm_present": true},
     "cameras": [{"camera_serial": 40123456, "state": "streaming", "fps_measured": 29.97,
                  "frames_captured": 1200, "frames_dropped": 0, "frames_published": 1200,
                  "queue_depth": 1, "reopen_count": 0,
                  "last_capture_unix_ns": 1699999999990000000, "error": null}]}

``status_seq`` is the status messages' own counter, independent of the frames' ``seq``. Every
field is required; ``master_offset_ns``, ``gm_present``, ``last_capture_unix_ns`` and ``error``
are nullable. ``ptp.state`` is one of ``PTP_STATES``, a camera's ``state`` one of
``CAMERA_STATES`` (meanings in docs/capture.md). The recorder counts an agent gone after
``agent_timeout_s`` (rig.toml, default 3 s) without a status message.

Control messages, 1 part, a UTF-8 JSON object
---------------------------------------------
Request: ``{"egosurg": "control", "version": 1, "verb": "start", "args": {...},
"request_id": "..."}``; verbs are ``CONTROL_VERBS``. Reply: ``{"egosurg": "reply", "version": 1,
"ok": false, "result": {}, "error": "PTP is unlocked on node-b; ...", "request_id": "..."}``,
echoing the request's ``request_id`` (1..``MAX_REQUEST_ID_CHARS`` characters, no control
characters); ``error`` is null exactly when ``ok`` is true. A ``REP`` socket answers every
request, also one it cannot decode (``ok: false`` with ``request_id`` ""). An agent answers
``status`` and ``heartbeat`` with ``ok: true`` and ``start``/``stop`` with ``ok: false``; its
``status`` result is ``{"cameras_info": [{"camera_serial", "resolution", "width", "height",
"fps", "encoding", "factory_conf"}, ...], "status": {...optional, a status message's body}}``,
checked by ``protocol/wire/agent_info.py`` (every entry field required, ``factory_conf`` text or
null).

Versioning
----------
The magic and the version (bytes 0..5 of a binary message, ``egosurg``/``version`` of a JSON one)
keep their place in every version. Any change to a binary layout, a field's meaning or unit, or a
required JSON field bumps the version; there are no optional binary fields. A receiver reads the
version before anything else and rejects one it does not know with ``UnknownVersionError``. JSON
messages may gain fields without a version bump: a receiver ignores fields it does not know.

What is rejected (``MalformedMessageError``, a ``ValueError``)
--------------------------------------------------------------
Wrong magic; unknown version (``UnknownVersionError``); wrong part count; a header of the wrong
size; lengths in the header that differ from the buffers; width or height outside 1..8192;
``raw_bgr8`` not ``width * height * 3`` bytes; ``jpeg`` not starting with ``FF D8``; an image above
``MAX_FRAME_BYTES``; a node id that is empty, over 32 bytes or not UTF-8; negative or out-of-range
integers; non-zero reserved or padding bytes; non-UTF-8 or non-JSON bodies, non-object JSON,
missing or mistyped fields, unknown states or verbs; JSON bodies above ``MAX_JSON_BYTES``. The same
checks run when a message is constructed, so a sender cannot build what a receiver would refuse.
Receivers count and log these errors and keep running; decoders raise nothing else on bad input.
"""

from protocol.wire.checks import (
    FRAME_MAGIC,
    MAX_JSON_BYTES,
    MAX_NODE_ID_BYTES,
    STATUS_MAGIC,
    ImageBuffer,
    MalformedMessageError,
    UnknownVersionError,
    WirePart,
)
from protocol.wire.control import (
    CONTROL_VERBS,
    CONTROL_WIRE_VERSION,
    MAX_REQUEST_ID_CHARS,
    ControlReply,
    ControlRequest,
)
from protocol.wire.frame import (
    FRAME_HEADER_BYTES,
    FRAME_WIRE_VERSION,
    MAX_FRAME_BYTES,
    MAX_IMAGE_SIDE_PX,
    Encoding,
    FrameMessage,
)
from protocol.wire.status import (
    CAMERA_STATES,
    PTP_STATES,
    STATUS_WIRE_VERSION,
    AgentStatus,
    CameraStatus,
    PtpState,
    decode_published,
)

__all__ = [
    "CAMERA_STATES",
    "CONTROL_VERBS",
    "CONTROL_WIRE_VERSION",
    "FRAME_HEADER_BYTES",
    "FRAME_MAGIC",
    "FRAME_WIRE_VERSION",
    "MAX_FRAME_BYTES",
    "MAX_IMAGE_SIDE_PX",
    "MAX_JSON_BYTES",
    "MAX_NODE_ID_BYTES",
    "MAX_REQUEST_ID_CHARS",
    "PTP_STATES",
    "STATUS_MAGIC",
    "STATUS_WIRE_VERSION",
    "AgentStatus",
    "CameraStatus",
    "ControlReply",
    "ControlRequest",
    "Encoding",
    "FrameMessage",
    "ImageBuffer",
    "MalformedMessageError",
    "PtpState",
    "UnknownVersionError",
    "WirePart",
    "decode_published",
]
