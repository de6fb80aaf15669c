"""``egosurg session``: look inside a recorded session.

Examples::

    egosurg session info sessions/case-0042_20261121-101500.h5
    egosurg session verify sessions/case-0042_20261121-101500.h5
    egosurg session export-frames sessions/case-0042_20261121-101500.h5 --out frames/ --sets 0:30
    egosurg session recover damaged.h5 --out recovered.h5

A sealed session (rig.toml's ``[sealing]``) is opened with the identity of one of its
recipients: ``--identity FILE`` or ``EGOSURG_IDENTITY``. Without it ``info`` shows the
session's structure and its recipients (the metadata values read ``<sealed>``), ``verify`` checks
the structure and every image's checksum (taken over the ciphertext; with the identity each image
is also opened), and ``export-frames`` refuses in one line naming the recipients (exit 2).
``recover`` needs none: it copies the sealed images as they are.

``info`` and ``verify`` also list the take's session events, per kind with their count and
nodes: links that dropped or came back, frames the recorder refused (a node over its rate, a
stamp that went back), counters that jumped (docs/session.md, "Session events").

A file that cannot be read (truncated, damaged metadata, not a session) gives one line and exit
code 2; ``verify`` exits 1 when it finds damage inside a readable file (an image whose checksum
no longer matches, ...). ``recover`` copies every intact frame and synchronised set of a damaged
or killed recording into a new session and says what was kept and lost.

``export-frames`` exports by synchronised set, so the files of one set index show one instant
from every camera: ``<out>/set_000012/SN<serial>_left.png``. With ``--by-camera`` it exports
each camera's frames in order instead: ``<out>/SN<serial>/left_<frame_index>.png``. Every image
is checked against the checksum stored when it was recorded: one that no longer matches is not
written; the others are, and the damaged ones are listed by camera, row and side at the end, with
exit code 1.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import cv2

from protocol.command import CommandArgumentError, add_subcommand, command_parser
from protocol.errors import UserError
from protocol.images import decode_image
from protocol.private_files import make_owner_only, plaintext_notice
from protocol.sealing import IDENTITY_ENV
from protocol.sealing.arguments import add_identity_argument, identity_from_args
from protocol.session import ImageChecksumError, SessionFormatError, SessionReader
from protocol.session.health import summarise  # also egosurg report's
from protocol.session.recover import recover_session
from protocol.session.verify import describe_events

# What reading a damaged file may still raise past the reader's own checks (h5py, numpy, cv2).
READ_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError, IndexError, MemoryError)
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def _safe(text: object) -> str:
    """Text from a file, with terminal controls (ANSI, bidi) shown as escapes, not obeyed."""
    return _CONTROL.sub(lambda m: ascii(m.group(0))[1:-1], str(text))


def _slice(text: str | None, n: int) -> range:
    if not text:
        return range(n)
    a, sep, b = text.partition(":")
    try:
        start = int(a) if a else 0
        stop = int(b) if (sep and b) else (n if sep else start + 1)
    except ValueError:
        raise CommandArgumentError(f"{text!r} must look like 10:20, 10: or 10") from None
    if start < 0 or start >= max(n, 1) or stop <= start:
        raise CommandArgumentError(f"range {text!r} is outside 0:{n}")
    return range(start, min(stop, n))


def format_info(s: dict) -> str:
    state = "closed cleanly" if s["closed_cleanly"] else "NOT CLOSED CLEANLY (recorder killed?)"
    lines = [
        f"{s['file']}",
        f"session {_safe(s['session'])}  {state}  (format version {s['format_version']})",
        f"duration {s['duration_s']:.2f} s; {s['sets']} synchronised sets, "
        f"{s['complete_sets']} complete",
    ]
    if s["sets"]:
        sp = s["spread_ms"]
        lines.append(
            f"set spread: median {sp['median']:.2f} ms, p95 {sp['p95']:.2f} ms, max "
            f"{sp['max']:.2f} ms (each frame within +-{s['tolerance_ms']:.2f} ms of its set time)"
        )
    if s["previous_session_file"]:
        lines.append(
            f"take part {s['take_part']}: continues {_safe(s['previous_session_file'])} (same "
            "folder); the recorder was restarted during the take"
        )
    if s["metadata"]:
        lines.append(
            "metadata: " + ", ".join(f"{_safe(k)}={_safe(v)}" for k, v in s["metadata"].items())
        )
    for kind, per_node in sorted(s["events"].items()):
        nodes = ", ".join(f"{_safe(n)} {k}" for n, k in sorted(per_node.items()))
        lines.append(f"event {kind}: {sum(per_node.values())} ({nodes})")
    lines.append(
        "camera       node      mode                       frames    fps  "
        "missing-in-sets  drops/gaps"
    )
    for c in s["cameras"]:
        g = s["drops_and_gaps"].get(str(c["serial"]), {})
        gtext = ", ".join(f"{k} {v}" for k, v in sorted(g.items())) or "none"
        lines.append(
            f"SN{c['serial']:<10} {_safe(c['node_id']):<9} {c['mode']:<26} {c['frames']:>6} "
            f"{c['fps_measured']:>6.2f} {c['missing_in_sets']:>16}  {gtext}"
        )
    return "\n".join(lines)


def open_session(args: argparse.Namespace, needs: str) -> SessionReader:
    """``args.file`` opened with ``--identity`` (or ``$EGOSURG_IDENTITY``); a sealed session
    opened without one is refused in one line naming its recipients, as ``needs`` it."""
    reader = SessionReader(args.file, identity=identity_from_args(args))
    try:
        reader.require_identity(needs)
    except BaseException:
        reader.close()
        raise
    return reader


def sealed_line(reader: SessionReader) -> str | None:
    """For a sealed session opened without an identity: what it is sealed for and what needs
    the key (docs/session.md, "Sealed sessions": its structure reads without one)."""
    if reader.can_open:
        return None
    names = ", ".join(r.label() for r in reader.recipients)
    return (
        f"sealed for {names}: the case's metadata values, the rig text and the images need the "
        f"identity of one of them (--identity FILE or {IDENTITY_ENV})"
    )


def cmd_info(args: argparse.Namespace) -> int:
    with SessionReader(args.file, identity=identity_from_args(args)) as reader:
        s = summarise(reader)
        sealed = sealed_line(reader)
    print(json.dumps(s, indent=2) if args.json else format_info(s))
    if sealed and not args.json:
        print(_safe(sealed))
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    # without an identity a sealed session's images are checked by their checksums (taken over
    # the ciphertext); with one, each is also opened (reader.verify)
    with SessionReader(args.file, identity=identity_from_args(args)) as reader:
        problems = reader.verify(check_images=not args.quick)
        events = describe_events(reader)  # what happened in the take: not problems
    errors = [p for p in problems if p.startswith("error")]
    for p in problems:
        print(p)
    for line in events:
        print(line)
    print(
        f"{args.file}: {'OK' if not errors else f'{len(errors)} problem(s)'}"
        f"{f' ({len(problems) - len(errors)} note(s))' if len(problems) > len(errors) else ''}"
    )
    return 0 if not errors else 1


def cmd_export(args: argparse.Namespace) -> int:
    out = Path(args.out)
    sides = ("left", "right") if args.side == "both" else (args.side,)
    written = 0
    skipped: list[str] = []  # "SN<serial> row <r> <side>" of the damaged images not written
    with open_session(args, "every image") as reader:
        info = reader.info
        serials = info.camera_serials
        if args.camera is not None:
            if args.camera not in serials:
                raise CommandArgumentError(
                    f"no camera {args.camera} in {args.file}; cameras: "
                    f"{', '.join(map(str, serials))}"
                )
            serials = (args.camera,)

        def write(path: Path, serial: int, row: int, side: str) -> int:
            ci = info.camera(serial)
            try:
                data = reader.image_bytes(serial, row, side)
            except ImageChecksumError as exc:  # skipped and listed: the others are still useful
                print(_safe(f"warning: skipped {exc}"), file=sys.stderr)
                skipped.append(f"SN{serial} row {row} {side}")
                return 0
            img = decode_image(data, ci.encoding, ci.width, ci.height)
            path.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(path), img):
                raise OSError(f"could not write {path}")
            make_owner_only(path)  # a frame from an earlier export kept its mode when rewritten
            return 1

        if args.by_camera:
            for serial in serials:
                table = reader.frame_table(serial)
                for row in _slice(args.frames, len(table["frame_index"]))[:: args.every]:
                    for side in sides:
                        idx = int(table["frame_index"][row])
                        name = out / f"SN{serial}" / f"{side}_{idx:06d}.png"
                        written += write(name, serial, row, side)
        else:
            sets = reader.sets()
            cols = [list(info.camera_serials).index(s) for s in serials]
            for k in _slice(args.sets, len(sets.set_unix_ns))[:: args.every]:
                for serial, col in zip(serials, cols, strict=True):
                    row = int(sets.members[k, col])
                    if row < 0:
                        continue
                    for side in sides:
                        name = out / f"set_{k:06d}" / f"SN{serial}_{side}.png"
                        written += write(name, serial, row, side)
    print(f"wrote {written} PNG(s) to {out}/")
    if written:
        print(plaintext_notice(f"{written} frame(s) as PNG", f"{out}/"), file=sys.stderr)
    if skipped:
        print(
            f"skipped {len(skipped)} damaged image(s) (checksum mismatch): {', '.join(skipped)}; "
            "'egosurg session verify' lists every damaged image",
            file=sys.stderr,
        )
    return 1 if skipped else 0


def cmd_recover(args: argparse.Namespace) -> int:
    report = recover_session(args.file, args.out)
    for line in report.lines():
        print(_safe(line))
    return 0 if sum(report.frames_kept.values()) else 1


def main(argv: list[str]) -> int:
    parser = command_parser("egosurg session", __doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = add_subcommand(sub, "info", "cameras, duration, sets, drops and spread", cmd_info)
    p.add_argument("file")
    add_identity_argument(p)
    p.add_argument("--json", action="store_true")
    p = add_subcommand(
        sub, "verify", "check the file's integrity (exit 1 on a problem)", cmd_verify
    )
    p.add_argument("file")
    p.add_argument("--quick", action="store_true", help="skip reading every image")
    add_identity_argument(p)
    p = add_subcommand(
        sub,
        "export-frames",
        "write frames as PNG; a damaged image (checksum mismatch) is skipped, listed, exit 1",
        cmd_export,
    )
    p.add_argument("file")
    p.add_argument("--out", required=True)
    add_identity_argument(p)
    p.add_argument("--camera", type=int, help="only this camera serial")
    p.add_argument("--side", choices=("left", "right", "both"), default="both")
    p.add_argument("--sets", help="set range, e.g. 0:30 (default: all)")
    p.add_argument("--by-camera", action="store_true", help="export per camera, not per set")
    p.add_argument("--frames", help="with --by-camera: row range, e.g. 0:100")
    p.add_argument("--every", type=int, default=1, help="take every Nth set or frame")
    p = add_subcommand(
        sub,
        "recover",
        "copy every intact frame and set of a damaged file into a new session",
        cmd_recover,
    )
    p.add_argument("file")
    p.add_argument("--out", required=True, help="the new session file (must not exist)")
    args = parser.parse_args(argv)
    if getattr(args, "every", 1) < 1:
        raise CommandArgumentError("--every must be 1 or more")
    try:
        return int(args.func(args))
    except (UserError, BrokenPipeError):
        raise
    except READ_ERRORS as exc:  # a damaged file must give one line (exit 2), not a traceback
        raise SessionFormatError(
            f"{args.file}: cannot {args.command} it ({type(exc).__name__}: {exc}); the file may be "
            "damaged: 'egosurg session recover' copies what is intact"
        ) from None
