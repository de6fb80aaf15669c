"""Replay and line of sight on a tiny reconstructed case (96 px, 3 steps, 3 timestamps), through
the real ``egosurg sim roles``, ``egosurg replay`` and ``egosurg sightline`` commands, and the
line-of-sight depth test against the simulator's ray-cast truth."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import av
import numpy as np
import pytest

from protocol.camera import Pose
from protocol.formats.site import read_site
from protocol.formats.trajectory import Keyframe, Trajectory, read_trajectories, write_trajectories
from reconstructor.errors import TrajectoryTimeError
from reconstructor.replay.models import CaseModels, ModelSource
from reconstructor.replay.path import CameraPath
from tests.helpers import egosurg_in_process, one_camera_session, run_egosurg
from tests.reconstructor.tiny import tiny_config_toml, tiny_eval_session

egosurg = egosurg_in_process


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict[str, Path]:
    """Four sets (2.0-2.2 s) of the intraoperative sim, a case of three timestamps, the sim's
    true roles and site boxes."""
    root = tmp_path_factory.mktemp("replay")
    h5 = tiny_eval_session(root, sets=4) / "session.h5"
    (root / "tiny.toml").write_text(tiny_config_toml(3))
    done = run_egosurg("reconstruct", str(h5), "--config", str(root / "tiny.toml"),
                       "--every", "0.0667s", "--out", str(root / "case"), timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    roles = run_egosurg("sim", "roles", str(h5), "--every", "0.05", "--out",
                        str(root / "roles.toml"), "--site-out", str(root / "site.toml"),
                        )  # fmt: skip
    assert roles.returncode == 0, roles.stderr
    bad = run_egosurg("sim", "roles", "--out", str(root / "x.toml"))
    assert bad.returncode == 2 and "give --from and --to" in bad.stderr
    return {"root": root, "case": root / "case", "roles": root / "roles.toml",
            "site": root / "site.toml", "session": h5}  # fmt: skip


def test_sim_roles_are_the_true_head_poses_at_each_keyframe(case):
    from sim.world import World

    world = World.from_seed(3, phase="intraoperative")
    roles = {t.name: t for t in read_trajectories(case["roles"])}
    assert "surgeon" in roles and "anaesthetist" in roles
    for name, tr in roles.items():
        assert [round(k.time_s, 3) for k in tr.keyframes] == [2.0, 2.05, 2.1, 2.15, 2.2]
        for k in tr.keyframes:
            truth = world.head_poses(k.time_s)[name]  # eval-set sessions: case time = sim time
            pose = k.pose()
            assert np.allclose(pose.centre_m, truth.centre_m, atol=2e-6)
            assert np.allclose(pose.R, truth.R, atol=1e-5)
    boxes = read_site(case["site"])
    assert {"monitor-a", "monitor-b"} <= set(boxes)


def test_a_path_passes_through_its_keyframes_and_turns_smoothly_between(tmp_path):
    a = Pose.look_at(np.array([0.0, 0.0, 1.6]), np.array([1.0, 0.0, 1.6]))
    b = Pose.look_at(np.array([1.0, 1.0, 1.6]), np.array([1.0, 2.0, 1.6]))
    keys = (Keyframe.from_pose(0.0, a, 80), Keyframe.from_pose(2.0, b, 100))
    path_file = write_trajectories(tmp_path / "t.toml", [Trajectory(name="walk", keyframes=keys)])
    path = CameraPath(read_trajectories(path_file)[0])
    assert np.allclose(path.pose(0.0).matrix, a.matrix, atol=1e-5)
    assert np.allclose(path.pose(2.0).matrix, b.matrix, atol=1e-5)
    mid = path.pose(1.0)
    # halfway through a 90 degree turn about +z: looking along (1, 1, 0) / sqrt 2
    assert np.allclose(mid.R[2], [np.sqrt(0.5), np.sqrt(0.5), 0.0], atol=1e-6)
    assert path.fov_deg(1.0) == pytest.approx(90.0)


def test_a_keyframe_made_at_a_case_timestamp_covers_it_after_the_file_round_trip(tmp_path):
    # case timestamps are set times in nanoseconds (15 fps: 2.0666666667 s); the file keeps
    # microseconds, so the role read back starts 3e-7 s after the timestamp it was made at
    t0_s, t1_s = 2.0 + 1 / 15, 2.0 + 4 / 15
    a = Pose.look_at(np.array([0.0, 0.0, 1.6]), np.array([1.0, 0.0, 1.6]))
    keys = (Keyframe.from_pose(t0_s, a, 80), Keyframe.from_pose(t1_s, a, 80))
    path_file = write_trajectories(tmp_path / "t.toml", [Trajectory(name="eye", keyframes=keys)])
    path = CameraPath(read_trajectories(path_file)[0])
    assert path.span_s[0] != t0_s  # the round trip really moved it
    for t_s in (t0_s, t1_s):
        assert np.allclose(path.pose(t_s).centre_m, [0.0, 0.0, 1.6])
    for t_s in (t0_s - 0.001, t1_s + 0.001):  # a millisecond outside is outside
        with pytest.raises(TrajectoryTimeError, match="outside trajectory 'eye'"):
            path.pose(t_s)


def test_replay_writes_an_h264_mp4_with_the_model_of_each_instant(case, capsys, tmp_path):
    out = tmp_path / "surgeon.mp4"
    done = egosurg(capsys, "replay", str(case["case"]), "--role", "surgeon", "--roles",
                       str(case["roles"]), "--out", str(out), "--fps", "20", "--size", "160x100",
                       "--pip")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        assert stream.codec_context.name == "h264"
    # 2.0 .. 2.1 s at 20 fps: the roles run to 2.2 s, the case's last model is at 2.133 s
    assert len(frames) == 3 and frames[0].shape == (100, 160, 3)
    # the burned-in time code's band: dark with white text, at the top left of every frame
    assert all(f[2:10, 2:40].max() > 200 and f[2:10, 2:40].min() < 40 for f in frames)


def test_the_model_shown_is_the_last_one_at_or_before_each_instant_and_preload_gives_the_same(
    case,
):
    models = CaseModels(case["case"])
    names = [models.entry_at(t).name for t in (2.0, 2.05, 2.0667, 2.1, 2.2)]
    assert names == ["t00002.000", "t00002.000", "t00002.067", "t00002.067", "t00002.133"]
    order = [models.entry_at(t) for t in np.arange(2.0, 2.2, 0.02)]
    with (
        ModelSource(models, order, preload=True) as pre,
        ModelSource(models, order, preload=False) as plain,
    ):
        for e in order:
            assert np.array_equal(pre.get(e).means_m.numpy(), plain.get(e).means_m.numpy())


def test_a_damaged_model_is_refused_by_its_checksum(case, capsys, tmp_path):
    import shutil

    copy = tmp_path / "case"
    shutil.copytree(case["case"], copy)
    index = json.loads((copy / "case.json").read_text())
    victim = copy / index["timestamps"][1]["model"]
    blob = bytearray(victim.read_bytes())
    blob[-3] ^= 0xFF
    victim.write_bytes(bytes(blob))
    done = egosurg(capsys, "replay", str(copy), "--role", "surgeon", "--roles", str(case["roles"]),
                       "--out", str(tmp_path / "x.mp4"), "--size", "64x40")  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "fails its checksum" in done.stderr
    assert not (tmp_path / "x.mp4").exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--role", "janitor"), "no role 'janitor'"),
        (("--role", "surgeon", "--from", "1.0"), "outside trajectory"),
        (("--role", "surgeon", "--size", "97x60"), "even sides"),
        ((), "holds 6 trajectories"),
    ],
)
def test_bad_replay_input_gets_one_clear_line(case, capsys, tmp_path, extra, message):
    done = egosurg(capsys, "replay", str(case["case"]), "--roles", str(case["roles"]),
                       "--out", str(tmp_path / "x.mp4"), *extra)  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert message in done.stderr


def test_sightline_writes_the_csv_the_timeline_and_the_worst_instants(case, capsys, tmp_path):
    out = tmp_path / "los"
    done = egosurg(capsys, "sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                       str(case["roles"]), "--target", "monitor-b", "--site", str(case["site"]),
                       "--offset", "1m left-posterior", "--out", str(out))  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader((out / "sightline.csv").open()))
    assert [r["position"] for r in rows] == ["actual", "1m left-posterior"] * 3
    assert all(0.0 <= float(r["visible_fraction"]) <= 1.0 for r in rows)
    for a, b in zip(rows[::2], rows[1::2], strict=True):  # the offset is 1 m, horizontal
        d = np.subtract([float(b[k]) for k in ("eye_x_m", "eye_y_m", "eye_z_m")],
                        [float(a[k]) for k in ("eye_x_m", "eye_y_m", "eye_z_m")])  # fmt: skip
        assert np.linalg.norm(d) == pytest.approx(1.0, abs=2e-3) and abs(d[2]) < 1e-3
    assert (out / "timeline.png").stat().st_size > 5000
    assert len(list(out.glob("worst_*.png"))) == 2
    bad = egosurg(capsys, "sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                      str(case["roles"]), "--target", "xray", "--site", str(case["site"]),
                      "--out", str(out))  # fmt: skip
    assert bad.returncode == 2 and "no target 'xray'" in bad.stderr


def _flip_left_images(session: Path, only: tuple[int, int] | None = None) -> list[str]:
    """One byte changed in the middle of every camera's left images, or ``only`` the one of
    (serial, row): "SN<serial> row <r> left" of each."""
    import h5py

    damaged = []
    with h5py.File(session, "r+") as f:
        for name in f["cameras"]:
            g = f[f"cameras/{name}"]
            for row in range(g["left_offset"].shape[0]):
                if only is not None and only != (int(name), row):
                    continue
                off, n = int(g["left_offset"][row]), int(g["left_length"][row])
                g["left_bytes"][off + n // 2] ^= 0x01
                damaged.append(f"SN{name} row {row} left")
    return damaged


def test_replay_pip_shows_a_damaged_real_frame_as_damaged_and_lists_it(case, capsys, tmp_path):
    import shutil

    session = tmp_path / "session.h5"
    shutil.copy(case["session"], session)
    damaged = _flip_left_images(session)
    copy = tmp_path / "case"
    shutil.copytree(case["case"], copy)
    index = json.loads((copy / "case.json").read_text())
    index["session"] = str(session)
    (copy / "case.json").write_text(json.dumps(index))
    out = tmp_path / "pip.mp4"
    done = egosurg(capsys, "replay", str(copy), "--role", "surgeon", "--roles",
                   str(case["roles"]), "--out", str(out), "--size", "160x100", "--pip")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "damaged real frame(s) not shown (checksum mismatch)" in done.stderr, done.stderr
    (line,) = [ln for ln in done.stderr.splitlines() if "checksum mismatch): " in ln]
    named = line.rsplit("checksum mismatch): ", 1)[1].strip().split(", ")
    assert named and set(named) <= set(damaged)
    assert out.stat().st_size > 0  # the replay itself is whole


def test_reconstruct_leaves_out_a_damaged_view_names_it_and_records_it(case, tmp_path):
    import shutil

    folder = tmp_path / "session"
    shutil.copytree(case["session"].parent, folder)
    from protocol.session import SessionReader

    with SessionReader(folder / "session.h5") as reader:  # the first camera's frame in set 0
        serial, row = reader.info.camera_serials[0], int(reader.sets().members[0, 0])
    (damaged,) = _flip_left_images(folder / "session.h5", only=(serial, row))
    out = tmp_path / "out"
    done = run_egosurg("reconstruct", str(folder / "session.h5"), "--config",
                       str(case["root"] / "tiny.toml"), "--at", "set:0", "--out", str(out),
                       timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"{damaged} image is damaged (checksum mismatch)" in done.stderr, done.stderr
    (summary_path,) = out.glob("*/summary.json")
    summary = json.loads(summary_path.read_text())
    assert summary["damaged_images"] == [damaged]
    assert not any(name.startswith(f"SN{serial}-") for name in summary["sensors"])


# ---- no silent wrong answers: files of another session, the span, stale models --------------


def _demo_style_session(path: Path) -> Path:
    """A session as the demo records one: live, named by the rig, started on 2026-11-28 at
    09:00 UTC, of the same sim seed and phase as the case's, its sets at 2.0-2.2 s."""
    start = 1_795_856_400_000_000_000
    return one_camera_session(
        path, name="demo-or1", started_unix_ns=start,
        set_unix_ns=[start + 2_000_000_000 + k * 66_666_667 for k in range(4)],
        metadata={"source": "egosurg demo", "seed": "3", "phase": "intraoperative"},
    )  # fmt: skip


def test_review_files_of_another_session_are_refused_in_one_line_naming_both(case, capsys):
    """The demo's roles (a real ``egosurg sim roles`` of another session, covering the case's
    times) on this case: a viewer's eye a metre from where that person stood. Refused, by
    sightline, replay and sterile alike, with both sessions named."""
    root = case["root"]
    demo = _demo_style_session(root / "demo.h5")
    done = run_egosurg("sim", "roles", str(demo), "--every", "0.05", "--out",
                       str(root / "demo_roles.toml"), "--site-out",
                       str(root / "demo_site.toml"))  # fmt: skip
    assert done.returncode == 0, done.stderr
    los = egosurg(capsys, "sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                  str(root / "demo_roles.toml"), "--target", "monitor-b", "--site",
                  str(case["site"]), "--out", str(root / "los_demo"))  # fmt: skip
    assert los.returncode == 2 and "Traceback" not in los.stderr, los.stderr
    (line,) = los.stderr.strip().splitlines()
    assert "demo_roles.toml was made for session 'demo-or1' started 2026-11-28 09:00:00.000" in line
    assert "session 'sim-intraoperative-seed3' started 2026-01-01 00:00:00.000 UTC" in line
    assert not (root / "los_demo" / "sightline.csv").exists()
    site = egosurg(capsys, "sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                   str(case["roles"]), "--target", "monitor-b", "--site",
                   str(root / "demo_site.toml"), "--out", str(root / "los_demo"))  # fmt: skip
    assert site.returncode == 2 and "demo_site.toml was made for session 'demo-or1'" in site.stderr
    video = egosurg(capsys, "replay", str(case["case"]), "--role", "surgeon", "--roles",
                    str(root / "demo_roles.toml"), "--out", str(root / "demo.mp4"))  # fmt: skip
    assert video.returncode == 2 and "made for session 'demo-or1'" in video.stderr
    field = egosurg(capsys, "sterile", str(case["case"]), "--field", str(root / "demo_site.toml"),
                    "--out", str(root / "sterile_demo"))  # fmt: skip
    assert field.returncode == 2 and "made for session 'demo-or1'" in field.stderr


def test_a_file_that_names_no_session_is_used_with_a_one_line_warning(case, tmp_path):
    """A path written by hand (or by an egosurg before files named their session) still
    works, and the command says it could not check it."""
    from protocol.formats.site import site_toml

    hand = tmp_path / "hand.toml"
    write_trajectories(hand, read_trajectories(case["roles"]))  # no [session] table
    assert "[session]" not in hand.read_text() and "[session]" in case["roles"].read_text()
    site = tmp_path / "site.toml"
    site.write_text(site_toml(list(read_site(case["site"]).values())))
    done = run_egosurg("sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                       str(hand), "--target", "monitor-b", "--site", str(site), "--out",
                       str(tmp_path / "los"))  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    warnings = [ln for ln in done.stderr.splitlines() if "does not say which session" in ln]
    assert len(warnings) == 2, done.stderr  # one line for each file
    assert "hand.toml does not say which session it was made for" in warnings[0]
    assert (tmp_path / "los" / "sightline.csv").is_file()


def test_replay_spans_what_both_the_case_and_the_roles_cover_and_marks_stale_models(
    case, capsys, tmp_path
):
    """Roles that run on 0.87 s past the case's last model (2.133 s): by default the replay
    stops with the case; asked to go on (--to), every frame whose model is older than the
    case's spacing (1/15 s) says so on the picture and the command counts them."""
    long = tmp_path / "long.toml"
    done = run_egosurg("sim", "roles", str(case["session"]), "--from", "2.0", "--to", "3.0",
                       "--every", "0.1", "--out", str(long))  # fmt: skip
    assert done.returncode == 0, done.stderr
    out = tmp_path / "default.mp4"
    ran = egosurg(capsys, "replay", str(case["case"]), "--role", "surgeon", "--roles", str(long),
                  "--out", str(out), "--fps", "20", "--size", "320x200")  # fmt: skip
    assert ran.returncode == 0, ran.stderr[-2000:]
    assert "STALE" not in ran.stderr
    with av.open(str(out)) as container:
        assert container.streams.video[0].frames == 3  # 2.0, 2.05, 2.1: not to 3.0
    out = tmp_path / "asked.mp4"
    ran = egosurg(capsys, "replay", str(case["case"]), "--role", "surgeon", "--roles", str(long),
                  "--out", str(out), "--fps", "20", "--size", "320x200", "--to", "3.0")  # fmt: skip
    assert ran.returncode == 0, ran.stderr[-2000:]
    # 21 frames, 2.0-3.0 s; from 2.25 s on the 2.133 s model is more than 1/15 s old
    assert "16 of 21 frames show a model older than the case's spacing (0.067 s)" in ran.stderr
    with av.open(str(out)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    # the burned-in text's third line (STALE ...), below the time of day's and the model's:
    # white text on a dark band in the stale frame, where the fresh frame shows the picture
    top = slice(0, 60), slice(4, 100)
    fresh, stale = frames[4][top].max(axis=2), frames[5][top].max(axis=2)
    band = ((stale < 40).mean(axis=1) > 0.4) & ~((fresh < 40).mean(axis=1) > 0.4)
    rows = np.flatnonzero(band)
    assert len(rows) >= 6 and rows.min() > 15, rows  # a line's height, under the first two
    assert stale[rows].max() > 200  # with white text on it


def test_one_time_reads_as_one_time_and_a_span_as_a_span():
    from reconstructor.replay.video import seconds_span, timecode_span

    assert seconds_span(7.0, 7.0) == "at 7.000 s"  # an event seen at one timestamp
    assert seconds_span(6.32, 7.28) == "6.320-7.280 s"
    assert timecode_span(7.0, 7.0) == "at 00:00:07.000"
    assert timecode_span(6.32, 7.28) == "00:00:06.320 - 00:00:07.280"


# ---- frames a team can read: time of day, case id, "no data", the real cameras large -------


def _frames(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def _hatched(rgb: np.ndarray) -> np.ndarray:
    """Pixels tinted with the no-data hatch's magenta (through H.264's 4:2:0 chroma, and under
    a 3-step model's faint veil): nothing in the sim's room is that colour."""
    r, g, b = (rgb[..., k].astype(int) for k in range(3))
    return (r - g > 40) & (b - g > 30)


def test_frames_say_the_time_of_day_and_the_case_and_name_the_zone(case):
    """The case's session started 2026-01-01 00:00:00 UTC (the sim's epoch): case time 2.05 s
    is 00:00:02.050 there, 01:00:02.050 in Berlin; the case is the session's name."""
    from reconstructor.replay.clock import CaseClock, pick_zone
    from reconstructor.replay.run import frame_label

    models = CaseModels(case["case"])
    entry = models.entry_at(2.05)
    utc = CaseClock.for_case(case["case"], pick_zone("UTC"))
    lines = frame_label(2.05, "surgeon", entry, models.spacing_s, utc)
    assert lines[0] == "2026-01-01 00:00:02.050 UTC  case sim-intraoperative-seed3"
    assert lines[1].startswith("case time 00:00:02.050  surgeon")
    berlin = CaseClock.for_case(case["case"], pick_zone("Europe/Berlin"))
    assert berlin.time_of_day(2.05) == "01:00:02.050 CET"


def test_no_data_has_a_colour_of_its_own_with_a_legend_and_the_zone_is_checked(
    case, capsys, tmp_path
):
    """Looking up at the ceiling no camera saw: the picture is the no-data hatch, not black,
    and the legend at the bottom left says what it is. A wrong zone is one line."""
    up = tmp_path / "up.toml"
    eye = (0.0, 0.0, 1.7)
    write_trajectories(up, [Trajectory(name="up", keyframes=(
        Keyframe(time_s=2.0, eye_m=eye, look_at_m=(0.3, 0.0, 6.0), fov_deg=60.0),
        Keyframe(time_s=2.1, eye_m=eye, look_at_m=(0.3, 0.0, 6.0), fov_deg=60.0),
    ))])  # fmt: skip
    out = tmp_path / "up.mp4"
    done = egosurg(capsys, "replay", str(case["case"]), "--trajectory", str(up), "--out",
                   str(out), "--size", "320x200", "--timezone", "UTC")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    frame = _frames(out)[0]
    assert _hatched(frame[40:180]).mean() > 0.3  # black before: nothing here was seen
    legend = frame[-16:, :150]
    assert _hatched(legend[:, :16]).mean() > 0.2 and legend[:, 20:].max() > 200  # swatch, text
    bad = egosurg(capsys, "replay", str(case["case"]), "--trajectory", str(up), "--out",
                  str(tmp_path / "x.mp4"), "--timezone", "Mars/Olympus")  # fmt: skip
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert "--timezone 'Mars/Olympus' is not a time zone" in bad.stderr.strip().splitlines()[-1]


def test_grid_layout_puts_four_real_cameras_beside_the_render(case, capsys, tmp_path):
    """``--layout grid``: the video is twice as wide; its right half is four different real
    cameras' left images at the frame's set, each a quarter of the render."""
    import cv2

    from protocol.images import decode_image
    from protocol.session import SessionReader

    out = tmp_path / "grid.mp4"
    done = egosurg(capsys, "replay", str(case["case"]), "--role", "surgeon", "--roles",
                   str(case["roles"]), "--out", str(out), "--size", "320x200",
                   "--layout", "grid")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    frame = _frames(out)[0]  # 2.0 s: the session's first set
    assert frame.shape == (200, 640, 3)
    with SessionReader(case["session"]) as reader:
        members = reader.sets().members[0]
        real = []
        for col, serial in enumerate(reader.info.camera_serials):
            info = reader.info.camera(serial)
            left = reader.image_bytes(serial, int(members[col]), "left")
            bgr = decode_image(left, info.encoding, info.width, info.height)
            real.append(cv2.resize(bgr[:, :, ::-1], (160, 100), interpolation=cv2.INTER_AREA))
    matched = []
    for r in range(2):
        for c in range(2):
            cell = frame[r * 100 : (r + 1) * 100, 320 + c * 160 : 320 + (c + 1) * 160]
            lower = (slice(40, 96), slice(4, 156))  # below the label
            scores = [np.corrcoef(cell[lower].ravel(), img[lower].ravel())[0, 1] for img in real]
            assert max(scores) > 0.9, scores
            matched.append(int(np.argmax(scores)))
    assert len(set(matched)) == 4  # four different cameras
    both = egosurg(capsys, "replay", str(case["case"]), "--role", "surgeon", "--roles",
                   str(case["roles"]), "--out", str(tmp_path / "y.mp4"), "--pip",
                   "--layout", "grid")  # fmt: skip
    assert both.returncode == 2 and "--pip and --layout grid" in both.stderr


# ---- line of sight you can show: who blocks it, a plan, views aimed at the target ----------


def test_who_blocks_names_the_person_on_the_line_and_no_one_else():
    """A viewer at the origin, a screen 4 m ahead: the circulator standing halfway on the line
    blocks the points behind them; the nurse a metre to the side does not; a blocked point
    nobody stands in front of is "something else"; nothing blocked is "no obstruction"."""
    from reconstructor.replay.plan import OTHER, TURNED_AWAY, describe_blockers, who_blocks

    eye = np.array([0.0, 0.0, 1.7])
    points = np.array([[4.0, y, 1.5] for y in (-0.1, 0.0, 0.1, 0.2)] + [[4.0, -2.0, 1.5]])
    people = {"circulator": np.array([2.0, 0.0, 1.65]), "nurse": np.array([2.0, 1.2, 1.6])}
    blocked = np.array([True, True, True, False, True])  # the last: away from both, blocked
    shares = who_blocks(eye, points, blocked, people)
    assert shares == {"circulator": pytest.approx(0.6), OTHER: pytest.approx(0.2)}
    assert describe_blockers(shares, "monitor-a") == (
        "blocked by circulator (60% of monitor-a), something else (20%)"
    )
    assert who_blocks(eye, points, np.zeros(5, bool), people) == {}
    assert describe_blockers({}, "monitor-a") == "no obstruction"
    assert describe_blockers({TURNED_AWAY: 1.0}, "monitor-a") == (
        "monitor-a's face is turned away from the viewer"
    )
    short = {"child": np.array([2.0, 0.0, 0.9])}  # below the line (it passes 1.6 m up)
    assert who_blocks(eye, points, blocked, short) == {OTHER: pytest.approx(0.8)}


def test_sightline_aims_its_pictures_at_the_target_and_plans_each_answer(case, capsys, tmp_path):
    """The viewer faces straight away from the screen: today's worst pictures showed the wall
    behind them, without the target. Now each view is aimed at the target (its outline is in
    the picture), each timestamp has a plan, and the CSV and the summary say who blocks."""
    screen = read_site(case["site"])["monitor-b"]  # its face: the box's +x side
    eye = np.array(screen.centre_m) + screen.rotation @ np.array([2.0, 0.3, 0.2])
    away = tuple(float(v) for v in 2 * eye - np.array(screen.centre_m))
    walk = tmp_path / "away.toml"
    write_trajectories(walk, [Trajectory(name="visitor", keyframes=(
        Keyframe(time_s=2.0, eye_m=tuple(eye), look_at_m=away, fov_deg=70.0),
        Keyframe(time_s=2.2, eye_m=tuple(eye), look_at_m=away, fov_deg=70.0),
    ))])  # fmt: skip
    out = tmp_path / "los"
    done = egosurg(capsys, "sightline", str(case["case"]), "--viewer", "visitor", "--trajectory",
                   str(walk), "--target", "monitor-b", "--site", str(case["site"]), "--out",
                   str(out), "--timezone", "UTC")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    rows = list(csv.DictReader((out / "sightline.csv").open()))
    assert all(r["blocked_by"] == "no obstruction" or r["blocked_by"].startswith("blocked by ")
               for r in rows), rows  # fmt: skip
    assert sorted(p.name for p in out.glob("plan_*.png")) == [
        "plan_00002.000.png", "plan_00002.067.png", "plan_00002.133.png"]  # fmt: skip
    import cv2

    assert len(list(out.glob("worst_*.png"))) == 2
    for worst in out.glob("worst_*.png"):
        picture = cv2.imread(str(worst))[:, :, ::-1]
        view = picture[:300, :480]  # the view (480 x 300), left of the plan
        outline = (
            (view[..., 0] > 230) & (abs(view[..., 1].astype(int) - 210) < 30) & (view[..., 2] < 60)
        )
        assert outline.sum() > 50, worst  # the target's yellow outline is in the picture
        assert picture.shape[1] > 480  # and the plan beside it


def test_sightline_says_who_blocks_in_words_and_no_obstruction_when_none(case, capsys, tmp_path):
    from protocol.cli import main

    out = tmp_path / "los"
    capsys.readouterr()
    code = main(["sightline", str(case["case"]), "--viewer", "anaesthetist", "--roles",
                 str(case["roles"]), "--target", "monitor-b", "--site", str(case["site"]),
                 "--out", str(out)])  # fmt: skip
    printed = capsys.readouterr().out
    assert code == 0
    rows = list(csv.DictReader((out / "sightline.csv").open()))
    for r in rows:  # a fully visible screen has no obstruction, a blocked one names who
        if float(r["visible_fraction"]) == 1.0:
            assert r["blocked_by"] == "no obstruction"
        else:
            assert r["blocked_by"].startswith("blocked by ")
    clear = sum(r["blocked_by"] == "no obstruction" for r in rows)
    assert f"anaesthetist actual: no obstruction at {clear} of 3 timestamps" in printed
