"""``egosurg view``: a case in the browser, through viser (a maintained web viewer that draws
Gaussian splats with WebGL; nerfstudio's viewer is built on it).

The page has a time slider in case time (seconds since the session started; it shows the
nearest done timestamp, and the panel gives its time of day) and a play button (each step shows
the case's next done timestamp), the role cameras at the shown time (drawn as frustums; pick one
to look through it), the site's target and field boxes, and "Save viewpoint", which adds the
browser's current camera at the shown time to a trajectory file that ``egosurg replay
--trajectory`` reads, with the case's session in its ``[session]`` table. The roles, site and
field files (and a ``--save-to`` file that exists) are checked against the case's session
(``session_check.py``): a file made for another session is refused in one line. With a people
file (``--people``, from ``egosurg people``) the page also draws each track at the shown time
and names tracks as roles into the roles file (``view_people.py``); the roles named there
become role cameras at once.

Security: the server binds 127.0.0.1 unless told otherwise, and serves the case only to its own
page: the right Origin and Host and the token in the URL it prints (``view_boundary``); control
values are checked before viser stores them (``view_inputs``), and "Save viewpoint" writes only
for a page that passed. Viser's "share" feature, which would tunnel the page through a
public relay, is switched off in the page and refused by the server. A client that sends a
message viser cannot read (garbage, a wrong field, a 50 MB blob: viser's own size limit) loses
its connection; the server, the shown case and every other browser go on, and the log says so
in one line instead of a traceback (``OneLineClientErrors``).
"""

from __future__ import annotations

import contextlib
import io
import logging
import socket
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from protocol.errors import UserError
from protocol.formats.site import SiteBox
from protocol.formats.trajectory import Keyframe, Trajectory
from protocol.sealing import Identity
from reconstructor.case.index import Entry
from reconstructor.errors import ViewerError
from reconstructor.replay.clock import CaseClock, pick_zone
from reconstructor.replay.models import CaseModels
from reconstructor.replay.path import CameraPath
from reconstructor.replay.session_check import CaseInputs
from reconstructor.replay.view_boundary import WILDCARD_HOSTS, Boundary, BrowserGate, netloc
from reconstructor.replay.view_people import PeopleNaming, default_roles_path
from reconstructor.replay.view_scene import (
    VIEWER_UNIT_M,
    ViserCamera,
    box_wxyz,
    check_viewpoint_file,
    hfov_deg,
    in_viewer_units,
    pose_from_viser,
    save_viewpoint,
    splat_arrays,
    viser_camera,
)

log = logging.getLogger(__name__)

TIME_SLIDER = "Case time (s)"  # the slider's label: seconds since the session started
ROLE_COLOUR = (40, 110, 220)
# a role's camera where nobody followed them (inside a gap of its trajectory, or before or after
# its keyframes): drawn where the path would put it, grey, and labelled so
NOT_FOLLOWED_COLOUR = (150, 150, 150)
NO_ROLE = "(no role named yet)"  # the role menu's only entry before a track is named
TARGET_COLOUR = (250, 170, 20)
FIELD_COLOUR = (220, 30, 30)


@dataclass(frozen=True, kw_only=True)
class ViewConfig:
    host: str = "127.0.0.1"  # loopback only: anything else shows the case to the network
    port: int = 8080  # 0: any free port
    roles: Path | None = None  # a roles TOML (egosurg people name, egosurg sim roles)
    people: Path | None = None  # a people file (egosurg people): its tracks, named in the page
    sites: tuple[Path, ...] = ()  # site files: target boxes (monitors)
    fields: tuple[Path, ...] = ()  # site files: sterile field boxes
    save_to: Path = Path("viewpoints.toml")
    viewpoint_name: str = "viewer"  # the trajectory "Save viewpoint" adds to
    start: Keyframe | None = None  # the page's first camera (default: the first role's)
    start_aspect: float = 1.6  # width / height the start camera's horizontal fov is for
    play_speed: float = 1.0  # case seconds per second when playing
    timezone: str | None = None  # the time of day's zone (IANA name); None: the machine's

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ViewerError(f"--port {self.port}: give 1 to 65535 (0: any free port)")
        if not 0.01 <= self.play_speed <= 100:
            raise ViewerError(f"play speed {self.play_speed}: give 0.01 to 100")
        if not self.viewpoint_name.replace("-", "").replace("_", "").isalnum():
            raise ViewerError(
                f"viewpoint name {self.viewpoint_name!r}: use letters, digits, '-' or '_'"
            )


def _import_viser() -> Any:
    try:
        import viser
    except ImportError:
        raise ViewerError(
            "egosurg view needs the viser web viewer: pip install 'egosurg[view]'"
        ) from None
    return viser


class OneLineClientErrors(logging.Filter):
    """websockets logs a client whose message broke viser's handler with the whole traceback
    ("connection handler failed"); the viewer keeps serving, so one warning line says it."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.getMessage() == "connection handler failed":
            exc = record.exc_info[1]
            record.msg = "viewer: closed a browser connection whose message viser cannot read (%s)"
            record.args = (f"{type(exc).__name__}: {exc}"[:200],)
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            record.exc_info, record.exc_text = None, None
        return True


_CLIENT_ERRORS = OneLineClientErrors()


def _check_port_free(host: str, port: int) -> None:
    """Viser quietly moves to the next port when one is taken; a user who typed --port must get
    that port or a clear refusal."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ViewerError(
                f"port {port} on {host} is in use or not allowed ({exc.strerror}): stop the "
                "other server or pick another with --port"
            ) from None


class CaseViewer:
    """A case served to the browser; starts in the constructor, ``close()`` stops it."""

    def __init__(
        self,
        folder: Path | str,
        config: ViewConfig | None = None,
        identity: Identity | None = None,
    ) -> None:
        self.config = config = config or ViewConfig()
        self.models = CaseModels(folder, identity)  # a sealed session's case opens with it
        self.inputs = CaseInputs(Path(folder))  # each file checked against the case's session
        self.clock = CaseClock.for_case(Path(folder), pick_zone(config.timezone))
        self.naming: PeopleNaming | None = None
        if config.people is not None:  # names go to --roles, or roles.toml beside the file
            roles_to = config.roles or default_roles_path(config.people)
            self.naming = PeopleNaming(config.people, roles_to, self.inputs, self.set_roles)
            self.roles = self._read_roles(roles_to if roles_to.is_file() else None)
        else:
            self.roles = self._read_roles(config.roles)
        sites, fields = config.sites, config.fields
        self.boxes = [(b, TARGET_COLOUR) for p in sites for b in self.inputs.boxes(p).values()]
        self.boxes += [(b, FIELD_COLOUR) for p in fields for b in self.inputs.boxes(p).values()]
        check_viewpoint_file(config.save_to)
        if config.save_to.is_file():  # saving into another session's file would mix two cases
            self.inputs.trajectories(config.save_to)
        viser = _import_viser()
        _check_port_free(config.host, config.port)
        logging.getLogger("websockets.server").addFilter(_CLIENT_ERRORS)  # once: a set
        first = self.models.load(self.models.entries[0])  # a damaged case fails before serving
        self._lock = threading.RLock()
        self._cache: dict[str, dict[str, np.ndarray]] = {}
        self._loader = ThreadPoolExecutor(1, thread_name_prefix="view-preload")
        self._ahead: dict[str, Future[dict[str, np.ndarray]]] = {}
        self._play = threading.Event()
        self._closed = threading.Event()
        self.index = -1
        self.splats: Any = None
        self.frustums: dict[str, Any] = {}  # role -> its frustum in the scene
        self.labels: dict[str, Any] = {}  # role -> its frustum's label
        self.box_nodes: dict[str, Any] = {}  # site box -> its wireframe
        self._player = threading.Thread(target=self._play_loop, name="view-play", daemon=True)

        # viser is imported on first use (an optional extra), so its server class is a value
        # here; typed Any, mypy accepts it as the base class.
        viser_server: Any = viser.ViserServer

        class LocalServer(viser_server):
            def request_share_url(self, verbose: bool = True) -> str | None:
                log.warning("refused a request to share the case through a public relay")
                return None

        # viser prints its own banner with the page's address and no token, which would not
        # connect: the viewer prints the address to open (its ``url``) instead
        with contextlib.redirect_stdout(io.StringIO()):
            self.server = LocalServer(host=config.host, port=config.port, verbose=False)
        try:
            self.gate = BrowserGate(Boundary.for_address(config.host, self.server.get_port()))
            self.gate.install(self.server)
            self._start(first)
        except BaseException:
            self.close()
            raise

    def _start(self, first: Any) -> None:
        config = self.config
        if config.port and self.server.get_port() != config.port:
            taken = self.server.get_port()
            raise ViewerError(
                f"port {config.port} on {config.host} is in use (viser took {taken}): stop the "
                "other server or pick another with --port"
            )
        self.server.gui.configure_theme(show_share_button=False, show_logo=False)
        self.server.scene.set_up_direction("+z")
        self._cache[self.models.entries[0].name] = in_viewer_units(splat_arrays(first))
        self._build_gui()
        self._draw_boxes()
        self._set_start_camera()
        self.show(0)
        self._player.start()

    @property
    def url(self) -> str:
        """The page's address, with the websocket's (and its token) as viser's page reads it.
        A wildcard bind is shown as 127.0.0.1: 0.0.0.0 is no address to open a page at."""
        host = "127.0.0.1" if self.config.host in WILDCARD_HOSTS else self.config.host
        ws_url = self.gate.boundary.websocket_url(host)
        return f"http://{netloc(host)}:{self.server.get_port()}/?websocket={ws_url}"

    @property
    def entry(self) -> Entry:
        return self.models.entries[self.index]

    # --- time -----------------------------------------------------------------------------
    def show_time(self, t_s: float) -> None:
        """Show the done timestamp nearest case time ``t_s`` (what the slider does)."""
        self.show(int(np.argmin(np.abs(np.asarray(self.models.times_s) - float(t_s)))))

    def show(self, index: int) -> None:
        """Show the case's ``index``-th done timestamp (and the roles at its time)."""
        entries = self.models.entries
        index = int(np.clip(index, 0, len(entries) - 1))
        with self._lock:
            if index == self.index:
                return
            entry = entries[index]
            try:
                arrays = self._arrays(entry)
            except UserError as exc:  # a damaged model: say so, keep showing the last one
                log.error("%s", exc)
                self.server.add_notification("Cannot show this model", str(exc), color="red")
                return
            self.splats = self.server.scene.add_gaussian_splats(
                "/case/splats", **arrays, scale=VIEWER_UNIT_M
            )
            self.index = index
            self.time_text.content = self.time_markdown(entry, index, arrays["centers"].shape[0])
            if self.slider.value != entry.t_s:
                self.slider.value = entry.t_s
            self._draw_roles(entry.t_s)
            if self.naming is not None:
                self.naming.draw(entry.t_s)
            self._preload(index + 1)

    def time_markdown(self, entry: Entry, index: int, gaussians: int) -> str:
        """The panel's line: case time, time of day and date, the case, and the model."""
        when = self.clock.time_of_day(entry.t_s)
        day = f" · **{when}** on {self.clock.date(entry.t_s)}" if when else ""
        return (
            f"**{entry.t_s:.3f} s** of the case{day} · case {self.clock.case_id} "
            f"(model {entry.name}, {index + 1} of {len(self.models.entries)}, "
            f"{gaussians:,} Gaussians)"
        )

    def _arrays(self, entry: Entry) -> dict[str, np.ndarray]:
        if entry.name in self._cache:
            return self._cache[entry.name]
        fut = self._ahead.pop(entry.name, None)
        arrays = fut.result() if fut is not None else self._convert(entry)
        self._cache = {entry.name: arrays}  # one model kept besides the one read ahead
        return arrays

    def _convert(self, entry: Entry) -> dict[str, np.ndarray]:
        return in_viewer_units(splat_arrays(self.models.load(entry)))

    def _preload(self, index: int) -> None:
        entries = self.models.entries
        if index >= len(entries) or entries[index].name in self._ahead:
            return
        for fut in self._ahead.values():
            fut.cancel()
        self._ahead = {entries[index].name: self._loader.submit(self._convert, entries[index])}

    def _play_loop(self) -> None:
        times = self.models.times_s
        while not self._closed.is_set():
            if not self._play.wait(timeout=0.5):
                continue
            k = self.index
            if k + 1 >= len(times):
                self._set_playing(False)
                continue
            dt = (times[k + 1] - times[k]) / self.config.play_speed
            if self._closed.wait(timeout=float(np.clip(dt, 0.05, 5.0))):
                return
            if self._play.is_set():
                self.show(k + 1)

    def _set_playing(self, on: bool) -> None:
        if on and self.index + 1 >= len(self.models.entries):
            self.show(0)  # play from the start after the end
        (self._play.set if on else self._play.clear)()
        self.play_button.label = "Pause" if on else "Play"

    # --- page -----------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui, n = self.server.gui, len(self.models.entries)
        self.time_text = gui.add_markdown("")
        t0, t1 = (float(t) for t in self.models.span_s)
        self.slider = gui.add_slider(
            TIME_SLIDER, min=t0, max=t1 if n > 1 else t0 + 1.0, step=0.001, initial_value=t0,
            marks=self._slider_marks(), disabled=n < 2,
        )  # fmt: skip
        self.slider.on_update(lambda _: self.show_time(float(self.slider.value)))
        self.play_button = gui.add_button("Play", disabled=n < 2)
        self.play_button.on_click(lambda _: self._set_playing(not self._play.is_set()))
        if self.roles or self.naming:  # with a people file, named roles come as they are named
            self.role_menu = gui.add_dropdown("Role", tuple(self.roles) or (NO_ROLE,))
            self.look_button = gui.add_button("Look through role", disabled=not self.roles)
            self.look_button.on_click(
                lambda event: self.look_through(self.role_menu.value, event.client)
            )
        save = gui.add_button("Save viewpoint", hint=f"adds it to {self.config.save_to}")
        save.on_click(lambda event: event.client and self.save_from_client(event.client))
        if self.naming is not None:
            self.naming.build(self.server, self.gate.trusts)

    def _slider_marks(self) -> tuple[tuple[float, str], ...]:
        """The case's first and last timestamps, labelled with their time of day."""
        t0, t1 = (float(t) for t in self.models.span_s)
        ends = (t0, t1) if t1 > t0 else (t0,)
        return tuple((t, self.clock.time_of_day(t)[:8] or f"{t:.1f} s") for t in ends)

    def _draw_boxes(self) -> None:
        for box, colour in self.boxes:
            self._draw_box(box, colour)

    def _draw_box(self, box: SiteBox, colour: tuple[int, int, int]) -> None:
        scene = self.server.scene
        self.box_nodes[box.name] = scene.add_box(
            f"/boxes/{box.name}", color=colour, dimensions=box.size_m, wireframe=True,
            wxyz=box_wxyz(box), position=box.centre_m,
        )  # fmt: skip
        top = np.add(box.centre_m, (0.0, 0.0, box.size_m[2] / 2 + 0.05))
        scene.add_label(f"/boxes/{box.name}/label", box.name, position=top - box.centre_m)

    def _read_roles(self, path: Path | None) -> dict[str, CameraPath]:
        if path is None:
            return {}
        return {t.name: CameraPath(t) for t in self.inputs.trajectories(path)}

    def set_roles(self, roles: tuple[Trajectory, ...]) -> None:
        """The roles just named in the page: their cameras drawn, offered under "Role"."""
        with self._lock:
            for name in set(self.frustums) - {r.name for r in roles}:
                self.frustums.pop(name).remove()  # a name taken back: its camera goes
                self.labels.pop(name, None)
            self.roles = {t.name: CameraPath(t) for t in roles}
            self.role_menu.options = tuple(self.roles)
            self.look_button.disabled = False
            if self.index >= 0:
                self._draw_roles(self.entry.t_s)
                if self.naming is not None:
                    self.naming.draw(self.entry.t_s)  # the balls' colours and labels

    def _role_camera(self, name: str, t_s: float) -> tuple[ViserCamera, float]:
        path = self.roles[name]
        t = float(np.clip(t_s, *path.span_s))  # before or after its keyframes: the nearest
        aspect = self.config.start_aspect
        return viser_camera(path.pose(t), path.fov_deg(t), aspect), aspect

    def role_label(self, name: str, t_s: float) -> str:
        """The role camera's label at ``t_s``: its name, and where nobody followed that person
        (a gap of its trajectory, before or after its keyframes) that it is not followed there,
        so a camera on the path's guess is never taken for their eye."""
        path = self.roles[name]
        gap = path.gap_at(t_s)
        if gap is not None:
            return f"{name} (not followed {gap[0]:.1f}-{gap[1]:.1f} s)"
        t0, t1 = path.span_s
        if t_s < t0 - 1e-6 or t_s > t1 + 1e-6:
            return f"{name} (followed {t0:.1f}-{t1:.1f} s only)"
        return name

    def _draw_roles(self, t_s: float) -> None:
        for name in self.roles:
            cam, aspect = self._role_camera(name, t_s)
            label = self.role_label(name, t_s)
            colour = ROLE_COLOUR if label == name else NOT_FOLLOWED_COLOUR
            frustum = self.server.scene.add_camera_frustum(
                f"/roles/{name}", fov=cam.fov_rad, aspect=aspect, scale=0.15,
                color=colour, wxyz=cam.wxyz, position=cam.position,
            )  # fmt: skip
            frustum.on_click(lambda event, name=name: self.look_through(name, event.client))
            self.frustums[name] = frustum
            self.labels[name] = self.server.scene.add_label(f"/roles/{name}/label", label)

    def _set_start_camera(self) -> None:
        start = self.config.start
        if start is not None:
            cam = viser_camera(start.pose(), start.fov_deg, self.config.start_aspect)
        elif self.roles:
            cam, _ = self._role_camera(next(iter(self.roles)), float(self.models.times_s[0]))
        else:
            return
        initial = self.server.initial_camera
        initial.position, initial.look_at = cam.position, cam.look_at
        initial.up, initial.fov = cam.up, cam.fov_rad

    def look_through(self, role: str, client: Any = None) -> None:
        """Put one browser's camera (every browser's without ``client``) on a role's eye."""
        if role not in self.roles:  # the page offers only the case's roles: a forged message
            log.warning("viewer: a browser asked for role %.80r, which the case has none of", role)
            return
        cam, _ = self._role_camera(role, self.entry.t_s)
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            with c.atomic():
                c.camera.position = cam.position
                c.camera.look_at = cam.look_at
                c.camera.up_direction = cam.up
                c.camera.fov = cam.fov_rad

    # --- viewpoints -------------------------------------------------------------------------
    def client_keyframe(self, client: Any) -> Keyframe:
        """A browser's current camera at the shown time, as a trajectory keyframe."""
        cam = client.camera
        pose = pose_from_viser(cam.wxyz, cam.position)
        return Keyframe.from_pose(self.entry.t_s, pose, hfov_deg(cam.fov, cam.aspect))

    def save(self, keyframe: Keyframe) -> Trajectory:
        with self._lock:
            return save_viewpoint(
                self.config.save_to, self.config.viewpoint_name, keyframe, self.inputs.session
            )

    def save_from_client(self, client: Any) -> Keyframe | None:
        """What "Save viewpoint" does: that browser's camera, at the shown time, into the file.
        A camera that is no camera (a forged message: not finite, a zero rotation, a field of
        view outside 1-179 degrees) is refused and the file left as it was, and so is a browser
        that did not come through the gate (view_boundary)."""
        if not self.gate.trusts(client.client_id):
            log.warning("viewer: not saved: the request came from a page without the token")
            return None
        try:
            key = self.client_keyframe(client)
        except (ValueError, ZeroDivisionError, np.linalg.LinAlgError) as exc:
            log.warning("viewer: not saved: the browser's camera is not a valid view (%s)", exc)
            client.add_notification("Viewpoint not saved", str(exc)[:200], color="red")
            return None
        self.save(key)
        log.info("saved the viewpoint at %.3f s to %s", key.time_s, self.config.save_to)
        client.add_notification(
            "Viewpoint saved",
            f"{self.config.viewpoint_name} at {key.time_s:.3f} s in {self.config.save_to}",
            auto_close_seconds=4.0,
        )
        return key

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until closed (or ``timeout_s``); True when closed."""
        return self._closed.wait(timeout_s)

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._play.clear()
        self._loader.shutdown(wait=False, cancel_futures=True)
        self.server.stop()
        if self._player.is_alive():
            self._player.join(timeout=5.0)

    def __enter__(self) -> CaseViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
