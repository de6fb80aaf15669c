"""The seal of what is made from a sealed session (``protocol.sealing.derived``): its uid and
its recipients, as the session stores them (readable without a key), and the reader's identity.

A case records the same two values in its index (``sealing``), so its models open, and new
ones are sealed, without the session at hand: ``sealing_record`` and ``seal_from_record``.
"""

from __future__ import annotations

import json
from typing import Any

from protocol.sealing import Identity, KeyBlock
from protocol.sealing.derived import DerivedSeal
from protocol.session.read import SessionReader
from protocol.session.sealed import recipients_from_json, recipients_to_json


def derived_seal(reader: SessionReader, identity: Identity | None) -> DerivedSeal | None:
    """The seal of a sealed session's derived data; None for a plaintext session. The
    recipients are those the session lists (checked against their sealed copy when the
    reader was opened with an identity)."""
    stored = reader.stored_seal()
    if stored is None:
        return None
    uid = KeyBlock.from_bytes(stored.key_block).session_uid
    return DerivedSeal(uid, reader.recipients, identity)


def sealing_record(seal: DerivedSeal) -> dict[str, Any]:
    """What a case's index keeps of the seal: the session uid (hex) and the recipients (each
    ``{name, kind, key_id, public}``, as the session's ``recipients_json``)."""
    return {
        "session_uid": seal.session_uid.hex(),
        "recipients": json.loads(recipients_to_json(seal.recipients)),
    }


def seal_from_record(record: dict[str, Any], identity: Identity | None) -> DerivedSeal:
    """The seal a ``sealing_record`` describes; ``ValueError`` (and friends) if it is damaged."""
    uid = bytes.fromhex(record["session_uid"])
    return DerivedSeal(uid, recipients_from_json(json.dumps(record["recipients"])), identity)
