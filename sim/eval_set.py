"""``egosurg sim eval-set``: an evaluation set of the simulated OR, with its exact ground truth.

For each workflow phase it writes what the rig would have recorded, and what nobody can record
on a real site: the exact view from each person's eyes at the same instant.

- ``<phase>/session.h5``: ``sets`` consecutive synchronised sets at ``fps`` from ``t_start_s``,
  every sensor's image with the sim's sensor noise, JPEG-encoded at the agents' quality, stored
  through the session writer as the recorder stores them (skipping the agents and the network
  saves a recording per scene; the capture tests cover that path);
- ``<phase>/calibration.toml``: the rig's true calibration;
- ``<phase>/views/<role>@<set>.png``: each person's egocentric view (noise-free pinhole);
- ``<phase>-later/``: the same phase at ``instants - 1`` later instants, ``instant_every_s``
  apart (a second scene of the same phase: its session is one set per instant), each with every
  person's view; the first ``near_field_instants`` instants (counting set 0 of ``<phase>``)
  are also near-field instants;
- ``eval_set.toml``: the manifest (format in ``protocol/formats/eval_set.py``).

The defaults are the paper's scale: every phase at 5 instants 8 s apart, each with
every person's view (60 egocentric views over the three phases that have people: setup 3,
intraoperative 6, turnover 3 a instant), 3 near-field instants per phase, and 10 consecutive
sets at 15 fps for temporal stability.

Example::

    egosurg sim eval-set --out evalset/ --seed 3 --phases empty,setup,intraoperative,turnover
    egosurg sim eval-set --out small/ --phases intraoperative --sets 3 --instants 1  # one instant
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol import __version__
from protocol.camera import Resolution
from protocol.formats.eval_set import SIM_COMMAND_MARK, EvalScene, EvalSet, ReferenceView
from protocol.images import encode_image
from protocol.session import CameraInfo, SessionWriter
from sim.phases import PHASES
from sim.timing import SIM_EPOCH_UNIX_NS
from sim.truth import true_rig_calibration
from sim.world import World

log = logging.getLogger(__name__)

# the workflow phases (the wand phase is a calibration session, not a case)
WORKFLOW_PHASES = tuple(p for p in PHASES if p != "wand")


@dataclass(frozen=True, kw_only=True)
class EvalSetSpec:
    seed: int = 3
    phases: tuple[str, ...] = WORKFLOW_PHASES
    resolution: str = "SVGA"
    fps: float = 15.0
    t_start_s: float = 2.0
    sets: int = 10  # consecutive sets per phase (the temporal protocol uses 10)
    eval_sets: tuple[int, ...] = (0,)  # the sets the near-field and egocentric protocols use
    jpeg_quality: int = 90  # the agents' default
    view_size_px: tuple[int, int] = (960, 600)
    view_hfov_deg: float = 90.0
    contact: bool = False  # the scripted sterile-field contact (sim/contact.py)
    # instants of each phase with egocentric truth: set 0 and instants - 1 later ones
    instants: int = 5
    instant_every_s: float = 8.0  # seconds between instants (people move between them)
    near_field_instants: int = 3  # of those, the first ones the near-field protocol uses (all
    # of them if there are fewer)

    def __post_init__(self) -> None:
        bad = [p for p in self.phases if p not in WORKFLOW_PHASES]
        if bad or not self.phases:
            raise ValueError(
                f"phases {list(self.phases)}: choose from {', '.join(WORKFLOW_PHASES)}"
            )
        Resolution.parse(self.resolution)
        if self.sets < 1:
            raise ValueError(f"sets={self.sets}: must be at least 1")
        if any(not 0 <= k < self.sets for k in self.eval_sets) or not self.eval_sets:
            raise ValueError(f"eval_sets {list(self.eval_sets)}: must be in 0..{self.sets - 1}")
        if not self.fps > 0 or self.t_start_s < 0:
            raise ValueError("fps must be > 0 and t_start_s >= 0")
        if self.instants < 1:
            raise ValueError(f"instants={self.instants}: must be at least 1 (set 0)")
        if self.instants > 1 and not self.instant_every_s >= self.sets / self.fps:
            raise ValueError(
                f"instant_every_s={self.instant_every_s:g}: the later instants must come "
                f"after the {self.sets} consecutive sets ({self.sets / self.fps:g} s): give at "
                "least that, or --instants 1 for set 0 alone"
            )
        if self.near_field_instants < 1:
            raise ValueError(
                f"near_field_instants={self.near_field_instants}: must be at least 1 (set 0)"
            )

    @property
    def later_instants_s(self) -> tuple[float, ...]:
        """Sim times of the instants after set 0 (the ``<phase>-later`` scene's sets)."""
        return tuple(self.t_start_s + k * self.instant_every_s for k in range(1, self.instants))

    def command_options(self) -> str:
        """The ``egosurg sim eval-set`` options that make this spec (all of them, so the
        command repeats the set even if a default changes)."""
        w, h = self.view_size_px
        return (
            f"--seed {self.seed} --phases {','.join(self.phases)} --resolution "
            f"{self.resolution} --fps {self.fps:g} --t-start {self.t_start_s:g} --sets "
            f"{self.sets} --eval-sets {','.join(map(str, self.eval_sets))} --jpeg-quality "
            f"{self.jpeg_quality} --view-size {w}x{h} --view-hfov {self.view_hfov_deg:g}"
            + f" --instants {self.instants} --instant-every {self.instant_every_s:g}"
            f" --near-field-instants {self.near_field_instants}"
            + (" --contact" if self.contact else "")
        )


def write_eval_set(out: Path | str, spec: EvalSetSpec) -> EvalSet:
    """Render and write the set; returns its manifest (also written to ``out``)."""
    root = Path(out)
    scenes = []
    for phase in spec.phases:
        t0 = time.perf_counter()
        world = World.from_seed(spec.seed, phase=phase, contact=spec.contact)
        scenes.append(_write_scene(root, phase, world, spec))
        if spec.instants > 1:
            scenes.append(_write_later_scene(root, phase, world, spec))
        log.info("phase %s written in %.1f s", phase, time.perf_counter() - t0)
    eval_set = EvalSet(
        root=root,
        description=(
            f"simulated OR, seed {spec.seed}, {spec.resolution} at {spec.fps:g} fps, "
            f"{spec.sets} sets from t = {spec.t_start_s:g} s"
            + (
                f", {spec.instants} instants {spec.instant_every_s:g} s apart"
                if spec.instants > 1
                else ""
            )
            + f"{SIM_COMMAND_MARK}{spec.command_options()}"
        ),
        scenes=tuple(scenes),
    )
    eval_set.write()
    return eval_set


def _write_scene(root: Path, phase: str, world: World, spec: EvalSetSpec) -> EvalScene:
    """The phase's consecutive sets at ``fps`` from ``t_start_s`` (temporal stability), with
    every person's view at the ``eval_sets``."""
    times_s = [spec.t_start_s + k / spec.fps for k in range(spec.sets)]
    views = _write_session(root, phase, phase, world, spec, times_s, spec.fps, spec.eval_sets)
    return EvalScene(
        name=phase,
        phase=phase,
        session=f"{phase}/session.h5",
        calibration=f"{phase}/calibration.toml",
        eval_sets=tuple(spec.eval_sets),
        temporal_sets=tuple(range(spec.sets)),
        views=tuple(views),
        room_bounds_m=room_bounds(world),
    )


def _write_later_scene(root: Path, phase: str, world: World, spec: EvalSetSpec) -> EvalScene:
    """The phase at its later instants: one set per instant, every person's view at each; the
    first ``near_field_instants - 1`` are near-field instants too (set 0 of the phase's own
    scene is the first)."""
    name = f"{phase}-later"
    times_s = list(spec.later_instants_s)
    every = range(len(times_s))
    views = _write_session(root, name, phase, world, spec, times_s, 1 / spec.instant_every_s, every)
    return EvalScene(
        name=name,
        phase=phase,
        session=f"{name}/session.h5",
        calibration=f"{name}/calibration.toml",
        eval_sets=tuple(range(min(spec.near_field_instants, spec.instants) - 1)),
        temporal_sets=(),
        views=tuple(views),
        room_bounds_m=room_bounds(world),
    )


def _write_session(
    root: Path,
    name: str,
    phase: str,
    world: World,
    spec: EvalSetSpec,
    times_s: list[float],
    fps: float,
    view_sets: range | tuple[int, ...],
) -> list[ReferenceView]:
    """``<name>/session.h5`` with one synchronised set at each of ``times_s`` (sim seconds),
    its calibration, and the egocentric views at the sets ``view_sets``."""
    res = Resolution.parse(spec.resolution)
    folder = root / name
    (folder / "views").mkdir(parents=True, exist_ok=True)
    true_rig_calibration(world, res).write(folder / "calibration.toml")
    session = folder / "session.h5"
    session.unlink(missing_ok=True)
    cameras = [
        CameraInfo(
            camera_serial=u.serial,
            node_id="sim-eval-set",
            resolution=res.value,
            width=res.width,
            height=res.height,
            fps_nominal=fps,
            encoding="jpeg",
            factory_conf_text=u.factory.to_text(),
        )
        for u in world.rig
    ]
    period_ns = round(1e9 / fps)
    views: list[ReferenceView] = []
    with SessionWriter(
        session,
        # the seed in the name: every eval-set session starts at the sim epoch, and a roles
        # file of one seed must not pass for another's (protocol/formats/session_id.py)
        session_name=f"sim-{name}-seed{spec.seed}{'-contact' if spec.contact else ''}",
        case_metadata={"source": "egosurg sim eval-set", "phase": phase, "seed": str(spec.seed)}
        | ({"contact": "1"} if spec.contact else {}),
        cameras=cameras,
        tolerance_ns=period_ns // 2,
        software_version=__version__,
        started_unix_ns=SIM_EPOCH_UNIX_NS,  # session time = sim time
    ) as writer:
        for k, t_s in enumerate(times_s):
            stamp_ns = SIM_EPOCH_UNIX_NS + round(t_s * 1e9)
            members = []
            for unit in world.rig:
                left, right = world.render_stereo(unit, t_s, res)
                members.append(
                    writer.append_frame(
                        unit.serial,
                        left=_jpeg(left.image_rgb, spec.jpeg_quality),
                        right=_jpeg(right.image_rgb, spec.jpeg_quality),
                        capture_unix_ns=stamp_ns,
                        host_receive_unix_ns=stamp_ns,
                        recorder_receive_unix_ns=stamp_ns,
                        frame_index=round(t_s * fps),
                        seq=k,
                        ptp_offset_ns=0,
                        ptp_locked=True,
                    )
                )
            writer.append_set(stamp_ns, members, 0)
            if k in view_sets:
                views += _egocentric_views(folder, name, world, t_s, k, spec)
        writer.close(SIM_EPOCH_UNIX_NS + round((times_s[-1] + 1 / fps) * 1e9))
    return views


def room_bounds(world: World) -> tuple[float, ...]:
    room = world.config.room
    (x0, x1), (y0, y1) = room.x_range_m, room.y_range_m
    return (x0, y0, 0.0, x1, y1, room.height_z_m)


def _egocentric_views(
    folder: Path, scene: str, world: World, t_s: float, set_index: int, spec: EvalSetSpec
) -> list[ReferenceView]:
    out = []
    for role, pose in world.head_poses(t_s).items():
        name = f"{role}@{set_index}"
        camera = world.virtual_camera(
            pose, hfov_deg=spec.view_hfov_deg, size_px=spec.view_size_px, name=name
        )
        image = world.render(camera, t_s).image_rgb
        rel = f"{scene}/views/{name}.png"
        cv2.imwrite(str(folder.parent / rel), np.ascontiguousarray(image[:, :, ::-1]))
        out.append(
            ReferenceView(
                name=name,
                kind="egocentric",
                role=role,
                set_index=set_index,
                image=rel,
                camera=camera,
            )
        )
    return out


def _jpeg(image_rgb: np.ndarray, quality: int) -> bytes:
    return encode_image(np.ascontiguousarray(image_rgb[:, :, ::-1]), "jpeg", quality)
