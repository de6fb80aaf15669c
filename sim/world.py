"""The simulated OR as one object: build it from a seed, render any camera at any time.

Example::

    from sim import World
    world = World.from_seed(3, phase="setup")
    left, right = world.render_stereo(0, t_s=2.0, resolution="SVGA")
    cam = world.virtual_camera(world.head_poses(2.0)["anaesthetist"], hfov_deg=90)
    view = world.render(cam, t_s=2.0)      # egocentric ground truth
"""

from __future__ import annotations

import functools
import logging
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol.camera import Camera, Intrinsics, Pose, Resolution
from protocol.formats.wand import WandSpec
from sim.contact import contact_script
from sim.geometry import Mesh, cylinder
from sim.people import Person, PersonState, Waypoint, person_objects, person_state
from sim.phases import phase_script
from sim.render import (
    FrameScene,
    RayImage,
    Spheres,
    moving_region,
    render_over_background,
    render_view,
)
from sim.rig import ZedUnit, build_rig
from sim.room import Footprint, RoomSpec, SceneObject, build_room, footprints
from sim.sensor import SensorSpec, encode_ideal, expose
from sim.textures import build_textures
from sim.timing import SIM_EPOCH_UNIX_NS, ClockSpec, FrameClock, require_time
from sim.wand import ROD_RADIUS_M, WandMotion

log = logging.getLogger(__name__)

WAND_SPHERE_ALBEDO = (0.95, 0.42, 0.08)  # matte orange: stands out from scrubs and walls


@dataclass(frozen=True, kw_only=True)
class WorldConfig:
    seed: int = 0
    phase: str = "intraoperative"
    room: RoomSpec = field(default_factory=RoomSpec)
    clock: ClockSpec = field(default_factory=ClockSpec)
    sensor: SensorSpec = field(default_factory=SensorSpec)
    wand: WandSpec = field(default_factory=WandSpec)
    show_wand: bool | None = None  # None: the phase decides (only 'wand' shows it)
    wand_floor_lie_s: float = 2.0
    contact: bool = False  # the scripted sterile-field contact (sim/contact.py)

    def __post_init__(self) -> None:
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"WorldConfig.seed={self.seed!r} must be a non-negative integer")


@dataclass(frozen=True)
class Render:
    """One rendered view.

    ``image_rgb`` is (H, W, 3) uint8 RGB; ``depth_m`` is (H, W) float32, the z distance in the
    camera frame (inf where nothing was hit); ``object_index`` labels each pixel's object.
    """

    image_rgb: np.ndarray
    depth_m: np.ndarray
    object_index: np.ndarray
    camera: Camera
    t_s: float


class World:
    def __init__(self, config: WorldConfig | None = None) -> None:
        self.config = config or WorldConfig()
        cfg = self.config
        self.script = phase_script(cfg.phase, cfg.seed)
        self.textures = build_textures(cfg.seed)
        self.static_objects, self.lights = build_room(
            cfg.room,
            with_patient=self.script.with_patient,
            with_mobile_equipment=self.script.with_mobile_equipment,
        )
        self.rig: tuple[ZedUnit, ...] = build_rig(cfg.seed, cfg.room)
        self.wand_motion = WandMotion(
            spec=cfg.wand,
            seed=cfg.seed,
            floor_lie_s=cfg.wand_floor_lie_s,
            cameras=tuple(
                Camera(
                    name=f"SN{u.serial}",
                    intrinsics=u.factory.stereo("HD1200").left,
                    pose=u.left_pose,
                )
                for u in self.rig
            ),
            half_room_m=(cfg.room.length_x_m / 2, cfg.room.width_y_m / 2),
        )
        self.show_wand = self.script.with_wand if cfg.show_wand is None else cfg.show_wand
        self._scene_cache = functools.lru_cache(maxsize=2)(self._build_scene)
        self._moving_cache = functools.lru_cache(maxsize=2)(self._build_moving_scene)
        self._static_scene = FrameScene(list(self.static_objects), self.lights, self.textures)
        self._backgrounds: dict[tuple, RayImage] = {}
        self.contact = contact_script(cfg.seed) if cfg.contact else None

    @classmethod
    def from_seed(cls, seed: int, phase: str = "intraoperative", **kwargs: object) -> World:
        return cls(WorldConfig(seed=seed, phase=phase, **kwargs))  # type: ignore[arg-type]

    # ---- what is in the room -------------------------------------------------------------
    @property
    def people_scripts(self) -> tuple[Person, ...]:
        return self.script.people

    def people(self, t_s: float) -> list[PersonState]:
        t = require_time(t_s)
        states = [person_state(p, t) for p in self.script.people]
        op = self._wand_operator(t)
        if op is not None:
            states.append(op[1])
        if self.contact is not None:
            states.append(self.contact.state(t))
        return states

    def head_poses(self, t_s: float) -> dict[str, Pose]:
        """Each person's egocentric camera pose (world-to-camera, OpenCV axes) at ``t_s``."""
        return {s.name: s.eye_pose() for s in self.people(t_s)}

    def wand_centres(self, t_s: float) -> np.ndarray | None:
        """(3, 3) sphere centres in metres (order of the wand spec), or None if no wand."""
        t = require_time(t_s)
        return self.wand_motion.sphere_centres(t) if self.show_wand else None

    def footprints(self) -> list[Footprint]:
        return footprints(self.script.with_patient, self.script.with_mobile_equipment)

    def clock(
        self, unit: int | ZedUnit, spec: ClockSpec | None = None, epoch_unix_ns: int | None = None
    ) -> FrameClock:
        """The camera's free-running frame clock (``spec`` overrides the world's ClockSpec)."""
        u = self.unit(unit)
        return FrameClock(
            spec or self.config.clock,
            self.config.seed,
            u.serial,
            SIM_EPOCH_UNIX_NS if epoch_unix_ns is None else int(epoch_unix_ns),
        )

    # ---- cameras ---------------------------------------------------------------------------
    def unit(self, unit: int | ZedUnit) -> ZedUnit:
        if isinstance(unit, ZedUnit):
            return unit
        if not 0 <= int(unit) < len(self.rig):
            raise IndexError(f"camera index {unit} is out of range: the rig has {len(self.rig)}")
        return self.rig[int(unit)]

    def unit_by_serial(self, serial: int) -> ZedUnit:
        for u in self.rig:
            if u.serial == serial:
                return u
        known = ", ".join(str(u.serial) for u in self.rig)
        raise KeyError(f"no simulated camera with serial {serial}; the rig has {known}")

    def sensor(self, unit: int | ZedUnit, side: str, resolution: Resolution | str) -> Camera:
        return self.unit(unit).sensor(side, resolution)

    def virtual_camera(
        self,
        pose: Pose,
        intrinsics: Intrinsics | None = None,
        *,
        hfov_deg: float = 90.0,
        size_px: tuple[int, int] = (960, 600),
        name: str = "virtual",
    ) -> Camera:
        """A pinhole anywhere inside the room (egocentric, exocentric, counterfactual)."""
        self.config.room.require_inside(pose.centre_m, f"camera '{name}'")
        intr = intrinsics or Intrinsics.from_fov(size_px[0], size_px[1], hfov_deg)
        return Camera(name=name, intrinsics=intr, pose=pose)

    def write_factory_files(self, directory: Path | str) -> list[Path]:
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        return [u.factory.write(out) for u in self.rig]

    # ---- rendering -------------------------------------------------------------------------
    def scene_at(self, t_s: float) -> FrameScene:
        return self._scene_cache(require_time(t_s))

    def render(self, camera: Camera, t_s: float) -> Render:
        """An ideal view: no noise, vignetting or exposure change (ground truth)."""
        t = require_time(t_s)
        self.config.room.require_inside(camera.pose.centre_m, f"camera '{camera.name}'")
        img = self._render_view(camera, t)
        return Render(encode_ideal(img.radiance), img.depth_m, img.object_index, camera, t)

    def render_sensor(
        self,
        unit: int | ZedUnit,
        side: str,
        t_s: float,
        resolution: Resolution | str = Resolution.HD1200,
        *,
        noise: bool = True,
    ) -> Render:
        """What one ZED X sensor delivers at ``t_s``: through its distortion, with sensor noise
        keyed by (seed, serial, side, time) so the same frame always looks the same."""
        t = require_time(t_s)
        u = self.unit(unit)
        cam = u.sensor(side, resolution)
        img = self._render_view(cam, t)
        if noise:
            key = [self.config.seed, u.serial, 0 if side == "left" else 1, round(t * 1e9)]
            noise_key = int(np.random.SeedSequence(key).generate_state(1, np.uint64)[0])
            gain_rng = np.random.default_rng([self.config.seed, u.serial, 0xE7])
            spec = self.config.sensor
            gain = spec.exposure_gain * float(gain_rng.uniform(0.92, 1.08))
            spec = SensorSpec(
                exposure_gain=gain,
                full_well_e=spec.full_well_e,
                read_noise_e=spec.read_noise_e,
                vignetting=spec.vignetting,
                gamma=spec.gamma,
            )
            image = expose(img.radiance, cam.intrinsics, spec, noise_key)
        else:
            image = encode_ideal(img.radiance)
        return Render(image, img.depth_m, img.object_index, cam, t)

    def render_stereo(
        self,
        unit: int | ZedUnit,
        t_s: float,
        resolution: Resolution | str = Resolution.HD1200,
        *,
        noise: bool = True,
    ) -> tuple[Render, Render]:
        return (
            self.render_sensor(unit, "left", t_s, resolution, noise=noise),
            self.render_sensor(unit, "right", t_s, resolution, noise=noise),
        )

    # ---- internals -------------------------------------------------------------------------
    def _wand_operator(self, t: float) -> tuple[Person, PersonState] | None:
        if not (self.show_wand and self.config.phase == "wand"):
            return None
        first, direction = self.wand_motion.pose(t)
        handle = self.wand_motion.handle_end(t)
        away = -direction[:2] / max(np.linalg.norm(direction[:2]), 1e-3)
        behind = handle[:2] + 0.5 * away
        standby = np.array([2.6, -2.2])
        lie = self.wand_motion.floor_lie_s
        u = float(np.clip((t - lie) / self.wand_motion.pickup_s, 0.0, 1.0))
        pos = (1 - u) * standby + u * behind
        wp = Waypoint(
            x_m=float(pos[0]),
            y_m=float(pos[1]),
            dwell_s=1.0,
            focus_xyz_m=(float(first[0]), float(first[1]), float(first[2])),
        )
        person = Person(
            name="wand_operator",
            role="calibration operator",
            scrub_tint=(0.52, 0.66, 0.86),
            cap_tint=(0.35, 0.5, 0.85),
            height_m=1.75,
            waypoints=(wp,),
        )
        state = person_state(person, t)
        return person, state

    def _background(self, camera: Camera) -> RayImage:
        key = (camera.name, camera.intrinsics, camera.pose.matrix.tobytes())
        img = self._backgrounds.get(key)
        if img is None:
            if len(self._backgrounds) >= 16:
                self._backgrounds.pop(next(iter(self._backgrounds)))
            img = self._backgrounds[key] = render_view(self._static_scene, camera)
        return img

    def _render_view(self, camera: Camera, t: float) -> RayImage:
        """Ray-cast only the moving objects, only where they are; the static room comes from a
        cached render.

        Fixed cameras (the rig) see most of their pixels unchanged from frame to frame, so this
        is many times faster there; a camera seen once (a virtual view) is rendered whole.
        """
        if not camera.name.startswith("SN"):
            return render_view(self.scene_at(t), camera)
        moving = self._moving_cache(t)
        region = moving_region(camera, [o.mesh for o in moving.objects])
        return render_over_background(
            moving, camera, self._background(camera), len(self.static_objects), region
        )

    def _moving_objects(self, t: float) -> tuple[list[SceneObject], Spheres | None]:
        """Everything that moves at ``t``: the people, the contact script's objects, the wand."""
        objects: list[SceneObject] = []
        for person in self.script.people:
            objects += person_objects(person, person_state(person, t))
        if self.contact is not None:
            objects += self.contact.objects(t)
        spheres = None
        if self.show_wand:
            centres = self.wand_motion.sphere_centres(t)
            handle = self.wand_motion.handle_end(t)
            rod: Mesh = cylinder(handle, centres[-1], ROD_RADIUS_M, segments=10)
            objects.append(SceneObject("wand_rod", rod, "rubber"))
            spheres = Spheres(centres, self.config.wand.radius_m, WAND_SPHERE_ALBEDO)
            op = self._wand_operator(t)
            if (
                op is not None
                and t > self.wand_motion.floor_lie_s + 0.5 * self.wand_motion.pickup_s
            ):
                objects += person_objects(op[0], op[1], hand_target_m=handle)
            elif op is not None:
                objects += person_objects(op[0], op[1])
        return objects, spheres

    def _build_scene(self, t: float) -> FrameScene:
        moving, spheres = self._moving_objects(t)
        return FrameScene([*self.static_objects, *moving], self.lights, self.textures, spheres)

    def _build_moving_scene(self, t: float) -> FrameScene:
        moving, spheres = self._moving_objects(t)
        return FrameScene(moving, self.lights, self.textures, spheres)


def stable_hash(text: str) -> int:
    return zlib.crc32(text.encode())
