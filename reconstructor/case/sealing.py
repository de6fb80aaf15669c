"""A sealed session's case: its models are sealed for the session's recipients, and every
reader opens them with the identity given to its command.

The case's index records the seal (``CaseIndex.sealing``: the session's uid and recipients,
public values), so a case is read, and resumed, without its session at hand; a reader without
an identity is refused at once, in one line naming the recipients. The byte format is
``protocol.sealing.derived``'s; docs/case.md ("Sealed cases") says what is sealed.
"""

from __future__ import annotations

import binascii
from pathlib import Path

from protocol.sealing import Identity, load_identity
from protocol.sealing.derived import DerivedSeal
from reconstructor.case.index import CaseIndex
from reconstructor.errors import CaseFolderError


def case_seal(folder: Path, index: CaseIndex, identity: Identity | None) -> DerivedSeal | None:
    """The seal of a sealed case's models, with ``identity`` to open them; None for a
    plaintext case. A damaged record is one line naming the index."""
    if index.sealing is None:
        return None
    from protocol.session.derived import seal_from_record  # h5py: only for a sealed case

    try:
        return seal_from_record(index.sealing, identity)
    except (ValueError, TypeError, KeyError, binascii.Error) as exc:
        raise CaseFolderError(
            f"{folder / 'case.json'}: its sealing record is damaged ({exc}); restore the file"
        ) from None


def reader_seal(
    folder: Path, index: CaseIndex, identity: Identity | None, what: str
) -> DerivedSeal | None:
    """``case_seal`` for a command that reads the case's models: refused now, in one line
    naming the recipients, when the case is sealed and no identity was given."""
    seal = case_seal(folder, index, identity)
    if seal is not None:
        seal.require_identity(f"case {folder} ({what})")
    return seal


def identity_file_seal(folder: Path, index: CaseIndex, identity_path: str) -> DerivedSeal | None:
    """``case_seal`` with the identity loaded from its file (a worker's, or the runner's: the
    jobs carry the path, never the secret)."""
    identity = load_identity(Path(identity_path)) if identity_path else None
    return reader_seal(folder, index, identity, "its models")


def is_sealed_case(folder: Path) -> bool:
    """Whether the case at ``folder`` is a sealed session's (so its readers need an identity);
    False for a plaintext case and for a folder that is no case (its reader then says so)."""
    from reconstructor.case.index import INDEX_NAME

    if not (Path(folder) / INDEX_NAME).is_file():
        return False
    try:
        return CaseIndex.read(Path(folder)).sealing is not None
    except CaseFolderError:
        return False
