"""The case folder's index, ``case.json``: which timestamps the case holds and where each stands.

Format (``CASE_FORMAT_VERSION``; docs/case.md has the whole folder)::

    {"format": "egosurg-case", "format_version": 1,
     "session": "/abs/CASE.h5", "session_started_unix_ns": 1767225600000000000,
     "config_hash": "9f2c...", "warm_start": false, "created_unix_ns": ...,
     "timestamps": [
       {"name": "t00002.000", "t_s": 2.0, "set_index": 0, "chain": 0,
        "model": "models/t00002.000.ply", "xxh3_64": "1b0f...", "bytes": 3300000,
        "status": "done", "seconds": 5.2, "gaussians": 194185, "config_hash": "9f2c...",
        "warm_from": "", "error": ""}, ...]}

A sealed session's case adds ``"sealing": {"session_uid": "<32 hex>", "recipients": [{"name",
"kind", "key_id", "public"}, ...]}``: its models are sealed for those recipients.

``status`` is ``pending`` (not started, or started and interrupted), ``done`` or ``failed``.
The file is replaced atomically (a temp file, fsync, ``os.replace``) after each timestamp, and an
entry is marked done only after its model has been renamed into place, so the index never
names a partial file.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import xxhash

from protocol.durable import atomic_write_bytes
from reconstructor.errors import CaseFolderError

CASE_FORMAT = "egosurg-case"
CASE_FORMAT_VERSION = 1
INDEX_NAME = "case.json"
Status = Literal["pending", "done", "failed"]


@dataclass(frozen=True, kw_only=True)
class Entry:
    name: str  # "t<seconds of the set>", also the model's file stem
    t_s: float  # the set's time, seconds since the session started
    set_index: int
    chain: int = 0  # warm start: entries of one chain train one after another
    model: str = ""  # relative to the case folder; set once done
    xxh3_64: str = ""
    bytes: int = 0
    status: Status = "pending"
    seconds: float = 0.0  # wall time of this timestamp's reconstruction
    gaussians: int = 0
    config_hash: str = ""
    warm_from: str = ""  # the entry whose model this one started from ("" cold)
    error: str = ""


@dataclass(frozen=True, kw_only=True)
class CaseIndex:
    session: str
    session_started_unix_ns: int
    config_hash: str
    warm_start: bool
    created_unix_ns: int
    timestamps: tuple[Entry, ...] = field(default_factory=tuple)
    # a sealed session's case: {"session_uid": hex, "recipients": [...]} (reconstructor/case/
    # sealing.py); its models are sealed for those recipients. None (and absent from the file)
    # for a plaintext session's case
    sealing: dict[str, Any] | None = None

    def by_name(self) -> dict[str, Entry]:
        return {e.name: e for e in self.timestamps}

    def with_entry(self, entry: Entry) -> CaseIndex:
        rows = tuple(entry if e.name == entry.name else e for e in self.timestamps)
        return replace(self, timestamps=rows)

    def counts(self) -> dict[str, int]:
        out = {"done": 0, "pending": 0, "failed": 0}
        for e in self.timestamps:
            out[e.status] += 1
        return out

    def to_json(self) -> str:
        table = {"format": CASE_FORMAT, "format_version": CASE_FORMAT_VERSION, **asdict(self)}
        if table["sealing"] is None:  # a plaintext session's case.json is as it always was
            del table["sealing"]
        return json.dumps(table, indent=1) + "\n"

    def write(self, folder: Path) -> None:
        atomic_write_bytes(folder / INDEX_NAME, self.to_json().encode())

    @classmethod
    def read(cls, folder: Path) -> CaseIndex:
        path = folder / INDEX_NAME
        try:
            table = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise CaseFolderError(
                f"{path} cannot be read as a case index ({exc}); restore it or start the case "
                "in a new --out folder"
            ) from None
        if not isinstance(table, dict) or table.get("format") != CASE_FORMAT:
            raise CaseFolderError(f"{path} is not an egosurg case index; use another --out folder")
        version = table.get("format_version")
        if version != CASE_FORMAT_VERSION:
            raise CaseFolderError(
                f"{path} has case format {version}; this egosurg reads format "
                f"{CASE_FORMAT_VERSION}: use the egosurg version that wrote it"
            )
        try:
            rows = tuple(Entry(**row) for row in table["timestamps"])
            return cls(
                session=table["session"],
                session_started_unix_ns=int(table["session_started_unix_ns"]),
                config_hash=table["config_hash"],
                warm_start=bool(table["warm_start"]),
                created_unix_ns=int(table["created_unix_ns"]),
                timestamps=rows,
                sealing=table.get("sealing"),
            )
        except (KeyError, TypeError) as exc:
            raise CaseFolderError(f"{path} is damaged ({exc}); restore it") from None


def checksum_file(path: Path) -> tuple[str, int]:
    """(xxh3-64 hex digest, size in bytes) of the file."""
    h = xxhash.xxh3_64()
    size = 0
    with path.open("rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
            size += len(chunk)
    return h.hexdigest(), size


ModelState = Literal["ok", "size ok", "unchecked", "missing", "damaged"]


def check_model(folder: Path, entry: Entry, *, read: bool) -> tuple[ModelState, str]:
    """Whether a done entry's model is still what was written, and what is wrong if not.

    Without ``read`` only the file's presence and size are checked (a stat: cheap for any case);
    with it, its checksum too ("ok"). An entry from before checksums were recorded is
    "unchecked" (its file's presence still is)."""
    path = folder / entry.model
    if not entry.model or not path.is_file():
        return "missing", f"model {entry.model or '(none)'} is missing"
    if not entry.xxh3_64:
        return "unchecked", "no checksum was recorded for this model"
    size = path.stat().st_size
    if size != entry.bytes:
        return "damaged", f"model {entry.model} is {size} bytes, {entry.bytes} were written"
    if not read:
        return "size ok", ""
    digest, _ = checksum_file(path)
    if digest != entry.xxh3_64:
        return "damaged", f"model {entry.model} does not match its checksum (xxh3_64)"
    return "ok", ""


def verify(folder: Path, entry: Entry) -> bool:
    """True when a done entry's model is there with its recorded checksum."""
    if entry.status != "done" or not entry.model:
        return False
    path = folder / entry.model
    if not path.is_file():
        return False
    return checksum_file(path) == (entry.xxh3_64, entry.bytes)
