"""The sterile-field and line-of-sight outputs a report shows, read from the folders
``egosurg sterile --out`` and ``egosurg sightline --out`` wrote (their CSVs and pictures).

Each folder is checked against the case's session first (``made_for.toml``,
``reconstructor/replay/session_check.py``): a folder made for another session is refused in
one line. Pictures are read as bytes here and embedded by the page; a picture the CSV names
but the folder lacks is reported missing, never silently dropped.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path

from reconstructor.replay.session_check import CaseInputs
from reconstructor.report.facts import ReportInputError

log = logging.getLogger(__name__)
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class SterileEvent:
    number: int
    field: str
    contact: bool  # False: a sterile role's allowed entry
    role: str
    start_s: float
    end_s: float
    peak_t_s: float
    contact_m: tuple[float, float, float]
    viewpoint: str
    unoccluded: float
    pictures: tuple[tuple[str, bytes], ...]  # (file name, bytes) of the event's evidence
    missing: tuple[str, ...] = ()  # evidence the CSV names but the folder lacks
    camera: str = ""  # the real camera that saw it best ("" from an older sterile run)
    camera_still: str = ""  # that camera's still (one of ``pictures``)
    clip: str = ""  # that camera's clip, beside events.csv (not embedded: a page, not a video)


@dataclass(frozen=True)
class SterileReview:
    folder: Path
    about: str
    events: tuple[SterileEvent, ...]
    timeline_png: bytes | None

    @property
    def contacts(self) -> tuple[SterileEvent, ...]:
        return tuple(e for e in self.events if e.contact)


@dataclass(frozen=True)
class SightRow:
    t_s: float
    position: str  # "actual" or a counterfactual offset's text
    target: str
    visible: float
    rests_on_inferred: bool


@dataclass(frozen=True)
class SightlineReview:
    folder: Path
    about: str  # "anaesthetist sees monitor-a"
    rows: tuple[SightRow, ...]
    timeline_png: bytes | None
    worst: tuple[tuple[str, bytes], ...] = field(default_factory=tuple)

    @property
    def target(self) -> str:
        return self.rows[0].target if self.rows else ""


def _folder(path: str | Path, main_file: str, option: str) -> Path:
    """The output folder of ``path`` (the folder, or its ``main_file`` named directly)."""
    p = Path(path)
    if p.is_file() and p.name == main_file:
        p = p.parent
    if not (p / main_file).is_file():
        raise ReportInputError(
            f"{option} {path}: no {main_file} there; give the folder that "
            f"'egosurg {option.lstrip('-')} ... --out FOLDER' wrote"
        )
    return p


def _rows(path: Path) -> list[dict[str, str]]:
    try:
        with path.open(newline="") as fh:
            return list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ReportInputError(f"cannot read {path}: {exc}") from None


def _float(row: dict[str, str], key: str, where: Path) -> float:
    try:
        return float(row[key])
    except (KeyError, TypeError, ValueError):
        raise ReportInputError(
            f"{where}: column {key!r} missing or not a number ({row.get(key)!r}); rerun the "
            "command that wrote it"
        ) from None


def _picture(folder: Path, name: str) -> bytes | None:
    p = folder / name
    return p.read_bytes() if p.is_file() else None


def read_sterile(path: str | Path, inputs: CaseInputs) -> SterileReview:
    folder = _folder(path, "events.csv", "--sterile")
    made = inputs.review_output(folder, "sterile")
    events = []
    for row in _rows(folder / "events.csv"):
        pictures, missing = [], []
        # every column naming a picture is evidence (the render, the real camera's still)
        for value in row.values():
            if value and Path(value).suffix.lower() in PICTURE_SUFFIXES:
                data = _picture(folder, value)
                if data is None:
                    missing.append(value)
                else:
                    pictures.append((value, data))
        where = folder / "events.csv"
        contact = tuple(_float(row, f"contact_{a}_m", where) for a in "xyz")
        unoccluded = row.get("unoccluded_fraction", "") or "nan"
        events.append(SterileEvent(
            number=int(_float(row, "event", where)), field=row.get("field", ""),
            contact=row.get("kind") == "contact", role=row.get("role", "") or "unknown role",
            start_s=_float(row, "start_s", where), end_s=_float(row, "end_s", where),
            peak_t_s=_float(row, "peak_t_s", where), contact_m=contact,  # type: ignore[arg-type]
            viewpoint=row.get("viewpoint", ""), unoccluded=float(unoccluded),
            pictures=tuple(pictures), missing=tuple(missing), camera=row.get("camera", ""),
            camera_still=row.get("camera_still", ""), clip=row.get("clip", ""),
        ))  # fmt: skip
    return SterileReview(
        folder=folder, about=made.about if made else "", events=tuple(events),
        timeline_png=_picture(folder, "timeline.png"),
    )  # fmt: skip


def read_sightline(path: str | Path, inputs: CaseInputs) -> SightlineReview:
    folder = _folder(path, "sightline.csv", "--sightline")
    made = inputs.review_output(folder, "sightline")
    where = folder / "sightline.csv"
    rows = tuple(
        SightRow(
            t_s=_float(r, "t_s", where),
            position=r.get("position", "actual"),
            target=r.get("target", ""),
            visible=_float(r, "visible_fraction", where),
            rests_on_inferred=r.get("rests_on_inferred", "0") == "1",
        )
        for r in _rows(where)
    )
    worst = tuple((p.name, p.read_bytes()) for p in sorted(folder.glob("worst_*.png")))
    return SightlineReview(
        folder=folder, about=made.about if made else "", rows=rows,
        timeline_png=_picture(folder, "timeline.png"), worst=worst,
    )  # fmt: skip
