"""Evaluation sets: recorded scenes plus reference views, the input of ``egosurg evaluate``.

A reconstruction is judged against images that were not used to make it: the held-out right
sensors of the session itself (near-field), and views from elsewhere in the room taken at the
same instant (egocentric). On a site those are a hand-held point-of-view camera's frames with
poses registered by hand, as in the paper; on the simulated OR, ``egosurg sim eval-set`` writes
the sim's exact view from each person's eyes. Either way the reconstructor reads them through
this one format, so the ground truth never depends on the code it judges.

A set is a folder with ``eval_set.toml``, one session and calibration per scene, and the
reference views' PNGs; paths are relative to the folder (or absolute)::

    # EgoSurg evaluation set, format 1
    format_version = 1
    description = "simulated OR, seed 3"

    [[scenes]]
    name = "intraoperative"
    phase = "intraoperative"          # the workflow phase the scene shows ("" if unknown)
    session = "intraoperative/session.h5"
    calibration = "intraoperative/calibration.toml"
    eval_sets = [0]                   # set indices the near-field and egocentric protocols use
    temporal_sets = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]   # consecutive sets (temporal stability)
    room_bounds_m = [-3.5, -3.0, 0.0, 3.5, 3.0, 3.0]   # optional: the room's box, measured once

    [[scenes.views]]
    name = "surgeon@0"
    kind = "egocentric"
    role = "surgeon"
    set_index = 0                     # the set (instant) the view shows
    image = "intraoperative/views/surgeon@0.png"
    width_px = 960                    # an ideal pinhole: no distortion
    height_px = 600
    fx_px = 480.0
    fy_px = 480.0
    cx_px = 479.5
    cy_px = 299.5
    rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]   # world-to-camera
    translation_m = [0.0, 0.0, 0.0]

Poses are in the calibration's world frame (metres, OpenCV axes, ``x_cam = R @ x_world + t``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from protocol.camera import Camera
from protocol.errors import UserError
from protocol.formats.camera_toml import camera_lines, read_camera
from protocol.formats.camera_toml import toml_value as _v
from protocol.toml_config import load_toml

EVAL_SET_FORMAT_VERSION = 1
EVAL_SET_FILE = "eval_set.toml"


class EvalSetError(UserError, ValueError):
    """An evaluation set that is missing, of an unknown version, or inconsistent."""


# how a simulated set's description ends: the exact command options that made it, so a report
# can repeat the command (sim.eval_set writes it, reconstructor.evaluation.doc reads it)
SIM_COMMAND_MARK = "; made by: egosurg sim eval-set "


@dataclass(frozen=True)
class ReferenceView:
    """An image from a known pinhole camera at the instant of one set of a scene's session."""

    name: str
    kind: str  # "egocentric" (a person's eyes), "pov" (a hand-held camera), ...
    role: str  # whose view it is ("" if nobody's)
    set_index: int
    image: str  # PNG path relative to the set's folder
    camera: Camera  # pinhole (no distortion), in the calibration's world frame


@dataclass(frozen=True)
class EvalScene:
    name: str
    phase: str
    session: str  # relative to the set's folder
    calibration: str
    eval_sets: tuple[int, ...]
    temporal_sets: tuple[int, ...]
    views: tuple[ReferenceView, ...]
    room_bounds_m: tuple[float, ...] = ()  # (xmin, ymin, zmin, xmax, ymax, zmax), or unknown

    def views_at(self, set_index: int) -> list[ReferenceView]:
        return [v for v in self.views if v.set_index == set_index]


@dataclass(frozen=True)
class EvalSet:
    root: Path
    description: str
    scenes: tuple[EvalScene, ...]

    def path(self, relative: str) -> Path:
        return self.root / relative

    def image(self, view: ReferenceView) -> np.ndarray:
        """The view's image, (H, W, 3) uint8 RGB."""
        import cv2  # only readers of images need OpenCV

        p = self.path(view.image)
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            raise EvalSetError(f"{p}: reference view '{view.name}' cannot be read as an image")
        i = view.camera.intrinsics
        if bgr.shape[:2] != (i.height_px, i.width_px):
            raise EvalSetError(
                f"{p}: the image is {bgr.shape[1]}x{bgr.shape[0]} but view '{view.name}' says "
                f"{i.width_px}x{i.height_px}"
            )
        return np.ascontiguousarray(bgr[:, :, ::-1])

    # -- writing ------------------------------------------------------------------------------
    def to_toml(self) -> str:
        lines = [
            f"# EgoSurg evaluation set, format {EVAL_SET_FORMAT_VERSION}",
            f"format_version = {EVAL_SET_FORMAT_VERSION}",
            f"description = {_v(self.description)}",
        ]
        for s in self.scenes:
            lines += [
                "",
                "[[scenes]]",
                f"name = {_v(s.name)}",
                f"phase = {_v(s.phase)}",
                f"session = {_v(s.session)}",
                f"calibration = {_v(s.calibration)}",
                f"eval_sets = {_v(list(s.eval_sets))}",
                f"temporal_sets = {_v(list(s.temporal_sets))}",
            ]
            if s.room_bounds_m:
                lines.append(f"room_bounds_m = {_v(list(s.room_bounds_m))}")
            for v in s.views:
                lines += [
                    "",
                    "[[scenes.views]]",
                    f"name = {_v(v.name)}",
                    f"kind = {_v(v.kind)}",
                    f"role = {_v(v.role)}",
                    f"set_index = {v.set_index}",
                    f"image = {_v(v.image)}",
                    *camera_lines(v.camera.intrinsics, v.camera.pose, dist=False),
                ]
        return "\n".join(lines) + "\n"

    def write(self) -> Path:
        self.root.mkdir(parents=True, exist_ok=True)
        out = self.root / EVAL_SET_FILE
        out.write_text(self.to_toml())
        return out

    # -- reading ------------------------------------------------------------------------------
    @classmethod
    def read(cls, folder: Path | str) -> EvalSet:
        root = Path(folder)
        manifest = root / EVAL_SET_FILE if root.is_dir() else root
        if not manifest.is_file():
            raise EvalSetError(
                f"{root}: no {EVAL_SET_FILE} there; make an evaluation set with "
                f"'egosurg sim eval-set --out {root}' or write one (see docs/evaluation.md)"
            )
        data, _ = load_toml(manifest, "the evaluation set", error=EvalSetError)
        version = data.get("format_version")
        if version != EVAL_SET_FORMAT_VERSION:
            raise EvalSetError(
                f"{manifest}: format_version {version!r} is not supported (this reads "
                f"{EVAL_SET_FORMAT_VERSION})"
            )
        scenes = []
        for k, t in enumerate(data.get("scenes", [])):
            where = f"{manifest} [[scenes]] #{k + 1}"
            try:
                scenes.append(_scene(t, where))
            except KeyError as exc:
                raise EvalSetError(f"{where}: missing {exc.args[0]!r}") from None
            except (TypeError, ValueError) as exc:
                if isinstance(exc, UserError):
                    raise
                raise EvalSetError(f"{where}: {exc}") from None
        if not scenes:
            raise EvalSetError(f"{manifest}: the set lists no [[scenes]]")
        names = [s.name for s in scenes]
        if len(set(names)) != len(names):
            raise EvalSetError(f"{manifest}: scene names must be unique, got {names}")
        for s in scenes:
            for rel in (s.session, s.calibration):
                if not (manifest.parent / rel).is_file():
                    raise EvalSetError(
                        f"{manifest}: scene '{s.name}' names {rel}, which is missing"
                    )
        return cls(
            root=manifest.parent, description=str(data.get("description", "")), scenes=tuple(scenes)
        )


def _scene(t: dict[str, Any], where: str) -> EvalScene:
    views = []
    for j, v in enumerate(t.get("views", [])):
        vw = f"{where} view #{j + 1}"
        intr, pose = read_camera(v, vw, EvalSetError, dist=False)
        name = str(v["name"])
        views.append(
            ReferenceView(
                name=name,
                kind=str(v.get("kind", "")),
                role=str(v.get("role", "")),
                set_index=int(v["set_index"]),
                image=str(v["image"]),
                camera=Camera(name=name, intrinsics=intr, pose=pose),
            )
        )
    return EvalScene(
        name=str(t["name"]),
        phase=str(t.get("phase", "")),
        session=str(t["session"]),
        calibration=str(t["calibration"]),
        eval_sets=tuple(int(x) for x in t.get("eval_sets", [])),
        temporal_sets=tuple(int(x) for x in t.get("temporal_sets", [])),
        views=tuple(views),
        room_bounds_m=_bounds(t.get("room_bounds_m", []), where),
    )


def _bounds(value: Any, where: str) -> tuple[float, ...]:
    b = tuple(float(x) for x in value)
    if b and (len(b) != 6 or not all(lo < hi for lo, hi in zip(b[:3], b[3:], strict=True))):
        raise EvalSetError(f"{where}: room_bounds_m must be [xmin, ymin, zmin, xmax, ymax, zmax]")
    return b
