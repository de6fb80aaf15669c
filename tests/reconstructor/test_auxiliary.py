"""Auxiliary views (pose sampling, rendering, refining, training on them) and the ablation
switches (config, random init, CLI options), on small sim scenes so that the file runs in
seconds."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from protocol.camera import Camera, Intrinsics, Pose, Resolution
from protocol.command import CommandArgumentError
from reconstructor.cli import _with_options, reconstruct_parser
from reconstructor.config import ReconstructConfig
from reconstructor.data.frames import SensorFrame, Timestamp
from reconstructor.data.views import View, view_from_image
from reconstructor.depth.fusion import FusionConfig
from reconstructor.errors import ReconstructConfigError, RefinerNotFoundError, RefinerOutputError
from reconstructor.pipeline import reconstruct
from reconstructor.raster import RasterConfig
from reconstructor.refine.auxiliary import (
    AuxiliaryConfig,
    make_auxiliary_views,
    sample_auxiliary_poses,
)
from reconstructor.refine.base import Refined, Refiner, RefineRequest
from reconstructor.refine.eye_views import EyeViewConfig
from reconstructor.refine.refiners import load_refiner
from reconstructor.splats.gaussians import init_random, random_init_box
from reconstructor.splats.train import (
    TrainConfig,
    Trainer,
    ViewGroup,
    mixed_schedule,
    render,
    scene_extent_m,
)
from tests.helpers import run_egosurg
from tests.reconstructor.small_scene import ROOM, T_S, TruthRefiner, mean_psnr, true_depth_scene

SIZE = (80, 50)  # pixels: small enough for training runs of a few seconds
pytestmark = pytest.mark.usefixtures("one_thread")


def _look_at_camera(eye, target, size=(160, 100), hfov_deg=90.0) -> Camera:
    return Camera(
        name="cam",
        intrinsics=Intrinsics.from_fov(size[0], size[1], hfov_deg),
        pose=Pose.look_at(np.array(eye, float), np.array(target, float)),
    )


# ---- pose sampling ---------------------------------------------------------------------------
def test_poses_lie_in_the_half_shell_toward_the_scene_and_look_at_the_target():
    eye, aim = np.array([2.0, -2.0, 2.4]), np.array([0.0, 0.0, 1.0])
    cam = _look_at_camera(eye, aim)
    forward = (aim - eye) / np.linalg.norm(aim - eye)
    target = eye + 3.0 * forward  # the input camera's look-at point at 3 m along its axis
    poses = sample_auxiliary_poses(
        cam, 15, 0.4, np.random.default_rng(1), min_radius_m=0.1, look_at_depth_m=3.0
    )
    assert len(poses) == 15
    right_in, down_in = cam.pose.R[0], cam.pose.R[1]  # the input's image x and y in the world
    for p in poses:
        d = p.centre_m - eye
        assert 0.1 - 1e-9 <= np.linalg.norm(d) <= 0.4 + 1e-9
        assert d @ forward >= -1e-9  # on the scene's side of the camera
        # the target projects onto the principal point: it lies on the optical axis, in front
        cam_pt = p.transform(target[None])[0]
        assert cam_pt[2] > 0 and np.hypot(cam_pt[0], cam_pt[1]) < 1e-9 * cam_pt[2] + 1e-9
        # no roll against the input: image-right stays perpendicular to the input's image-up,
        # and both image axes keep the input's sense (no flip)
        x_axis, y_axis = p.R[0], p.R[1]
        assert abs(x_axis @ down_in) < 1e-9 and x_axis @ right_in > 0.95
        assert y_axis @ down_in > 0.95 and y_axis[2] < 0  # image-down is world-down
    centres = np.array([p.centre_m for p in poses])
    assert len(np.unique(centres.round(6), axis=0)) == 15


def test_pose_centres_fill_the_half_shell_uniformly():
    """Uniform in the half shell's volume: the cosine to the axis is uniform on [0, 1] (mean
    1/2), and half the samples lie inside the radius that halves the shell's volume."""
    eye = np.array([0.0, 0.0, 1.5])
    cam = _look_at_camera(eye, [3.0, 0.0, 1.5])
    r_min, r_max, n = 0.1, 0.4, 3000
    poses = sample_auxiliary_poses(
        cam, n, r_max, np.random.default_rng(2), min_radius_m=r_min, look_at_depth_m=3.0
    )
    d = np.array([p.centre_m for p in poses]) - eye
    r = np.linalg.norm(d, axis=1)
    cos = d[:, 0] / r  # the camera looks along +x
    assert len(poses) == n and cos.min() >= 0
    assert abs(cos.mean() - 0.5) < 0.02
    r_half = ((r_min**3 + r_max**3) / 2) ** (1 / 3)
    assert abs((r < r_half).mean() - 0.5) < 0.03
    # every direction of the half ball is used: the sideways components take both signs
    assert (d[:, 1] > 0.3).any() and (d[:, 1] < -0.3).any() and (d[:, 2] > 0.3).any()


def test_poses_stay_inside_the_room():
    """A camera in a corner just under the ceiling: some draws fall outside and are redrawn."""
    eye = np.array([3.3, 2.8, 2.85])
    cam = _look_at_camera(eye, [0.0, 0.0, 1.0])
    poses = sample_auxiliary_poses(
        cam, 40, 0.4, np.random.default_rng(3), look_at_depth_m=3.0, bounds_m=ROOM
    )
    assert len(poses) == 40
    centres = np.array([p.centre_m for p in poses])
    assert (centres >= ROOM[0]).all() and (centres <= ROOM[1]).all()
    unbounded = sample_auxiliary_poses(cam, 200, 0.4, np.random.default_rng(3), look_at_depth_m=3)
    outside = [p for p in unbounded if (p.centre_m > ROOM[1]).any()]
    assert outside, "the corner camera must be close enough to the walls for this test"


def test_bad_sampling_arguments_are_refused():
    cam = _look_at_camera([0, 0, 1.5], [3, 0, 1.5])
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"look_at_depth_m=0\.3 must exceed radius_m=0\.4"):
        sample_auxiliary_poses(cam, 3, 0.4, rng, look_at_depth_m=0.3)
    with pytest.raises(ValueError, match=r"min_radius_m=0\.5"):
        sample_auxiliary_poses(cam, 3, 0.4, rng, min_radius_m=0.5)


# ---- a small sim scene -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene(world):
    return true_depth_scene(world, SIZE)


def test_auxiliary_views_have_the_input_size_names_and_the_refiners_masks(scene, world, tmp_path):
    views, gaussians = scene
    cfg = AuxiliaryConfig(num_views=3, seed=4)
    refiner = load_refiner("guided")
    sheet = tmp_path / "aux.jpg"
    timings: dict[str, float] = {}
    aux = make_auxiliary_views(
        gaussians, views, cfg, RasterConfig(), refiner, bounds_m=ROOM, sheet_path=sheet,
        timings_s=timings,
    )  # fmt: skip
    assert [a.name for a in aux[:4]] == ["aux:cam0:0", "aux:cam0:1", "aux:cam0:2", "aux:cam1:0"]
    assert len(aux) == 12 and set(timings) == {"render", "refine"}
    for k, a in enumerate(aux):
        src = views[k // 3]
        assert (a.width_px, a.height_px) == SIZE and torch.equal(a.K, src.K)
        assert a.image.shape == (SIZE[1], SIZE[0], 3) and a.image.dtype == torch.float32
        assert 0 <= a.image.min() and a.image.max() <= 1
        assert a.mask.shape == (SIZE[1], SIZE[0]) and set(a.mask.unique().tolist()) <= {0.0, 1.0}
        assert 0.0 < a.mask.mean() < 1.0  # the guided refiner supervises warped pixels only
        dist = np.linalg.norm(a.pose.centre_m - src.pose.centre_m)
        assert cfg.min_radius_m - 1e-5 <= dist <= cfg.radius_m + 1e-5

    # the refiner gets the model's render from the auxiliary camera, and the input as reference
    truth = TruthRefiner(world)
    aux = make_auxiliary_views(gaussians, views[:1], cfg, RasterConfig(), truth, bounds_m=ROOM)
    for req, a in zip(truth.requests, aux, strict=True):
        assert np.array_equal(req.reference, views[0].image.numpy())
        assert np.array_equal(req.reference_mask, views[0].mask.numpy() > 0.5)
        assert np.allclose(req.reference_camera.pose.matrix, views[0].pose.matrix)
        with torch.no_grad():
            own = render(gaussians, a, RasterConfig())
            ref = render(gaussians, views[0], RasterConfig())
        np.testing.assert_allclose(req.rendered, own.image.clamp(0, 1).numpy(), atol=1e-6)
        np.testing.assert_allclose(req.rendered_depth_m, own.depth_m.numpy(), atol=1e-6)
        np.testing.assert_allclose(req.reference_depth_m, ref.depth_m.numpy(), atol=1e-6)
        sim = world.render(a.camera, T_S).image_rgb
        np.testing.assert_allclose(a.image.numpy() * 255, sim, atol=1e-3)

    # the contact sheet: 3 tiles (reference, render, refined) side by side, 4 rows (a view each)
    img = cv2.imread(str(sheet))
    assert img is not None and img.std() > 10
    tile_w = img.shape[1] / 3
    assert img.shape[0] == pytest.approx(4 * tile_w * SIZE[1] / SIZE[0], abs=4)


def test_a_refiner_returning_the_wrong_shape_is_refused(scene):
    views, gaussians = scene

    class Halving(Refiner):
        name = "halving"

        def refine(self, request: RefineRequest) -> Refined:
            img = request.rendered[::2, ::2]
            return Refined(image=img, mask=np.ones(img.shape[:2], bool))

    with pytest.raises(RefinerOutputError, match=r"halving.*\(50, 80, 3\)"):
        make_auxiliary_views(gaussians, views[:1], AuxiliaryConfig(num_views=1), RasterConfig(),
                             Halving())  # fmt: skip


def test_training_on_true_auxiliary_views_improves_held_out_views(scene, world):
    """The refinement stage's premise, with a perfect refiner: after the same warm-up and the
    same number of steps, a model that also trained on auxiliary views renders held-out views
    near the input cameras better than one trained on the input views alone.

    At 80x50 pixels the paper's R = 0.4 m moves a point 3 m away by under a pixel, so the
    auxiliary and held-out views would be the input views again; R = 1 m gives them parallax.
    Measured over seeds 0-2 of this setup: +0.8 to +1.3 dB."""
    views, g0 = scene
    raster = RasterConfig()
    train = TrainConfig(warmup_steps=30, refine_steps=100, seed=0, log_every_steps=1000)
    gaussians = g0.detach_clone()
    trainer = Trainer(gaussians, train, raster, scene_extent_m(views))
    trainer.run(views, train.warmup_steps)
    aux_cfg = AuxiliaryConfig(num_views=6, radius_m=1.0, min_radius_m=0.5)
    aux = make_auxiliary_views(
        gaussians, views, aux_cfg, raster, TruthRefiner(world), bounds_m=ROOM
    )
    assert len(aux) == 24

    rng = np.random.default_rng(99)  # held-out poses: drawn apart from the auxiliary ones
    held = []
    for v in views:
        for pose in sample_auxiliary_poses(
            v.camera, 2, 0.9, rng, min_radius_m=0.6, look_at_depth_m=2.5, bounds_m=ROOM
        ):
            cam = Camera(name="held", intrinsics=v.intrinsics, pose=pose)
            held.append(view_from_image(cam, world.render(cam, T_S).image_rgb))

    scores = {}
    warm = gaussians.detach_clone()
    for arm, train_views in (("inputs", views), ("inputs + auxiliary", [*views, *aux])):
        model = warm.detach_clone()
        t = Trainer(model, train, raster, scene_extent_m(views))
        t.step_index = train.warmup_steps  # the refinement stage's learning-rate schedule
        t.run(train_views, train.refine_steps)
        scores[arm] = mean_psnr(model, held, raster)
    print(f"held-out PSNR: {scores}")
    assert scores["inputs + auxiliary"] > scores["inputs"] + 0.4


def test_the_loss_weight_scales_a_views_image_loss(scene):
    """Weight 0: only the opacity regulariser acts, so the colours do not move; weight 1: they
    do. A wrong number of weights is refused."""
    views, g0 = scene
    raster = RasterConfig()
    cfg = TrainConfig(warmup_steps=1, refine_steps=1, random_background=False)
    moved = {}
    for weight in (0.0, 1.0):
        g = g0.detach_clone()
        before = g.sh_dc.detach().clone()
        Trainer(g, cfg, raster, 3.0).step(views[0], weight)
        moved[weight] = float((g.sh_dc.detach() - before).abs().max())
    assert moved[0.0] == 0.0 and moved[1.0] > 1e-4
    with pytest.raises(ValueError, match="1 weights for 2 views"):
        Trainer(g0.detach_clone(), cfg, raster, 3.0).run(views[:2], 1, weights=[1.0])


def test_mixed_groups_keep_their_share_of_the_steps(scene):
    """However many auxiliary views there are, the recorded views get their share of the steps,
    each of them in turn (shuffled passes), and the auxiliary group's weight applies to it."""
    views, g0 = scene
    raster = RasterConfig()
    cfg = TrainConfig(warmup_steps=0, refine_steps=40, random_background=False)
    inputs = [dataclasses.replace(views[0], name=f"in{i}") for i in range(2)]
    aux = [dataclasses.replace(views[1], name=f"aux{i}") for i in range(10)]
    t = Trainer(g0.detach_clone(), cfg, raster, 3.0)
    t.run_mixed([ViewGroup(inputs, 0.5), ViewGroup(aux, 0.5, 0.0)], 40)
    names = [s.view for s in t.log.steps]
    # the order is the schedule's, known before the run (what an evaluation reports)
    assert [int(n.startswith("aux")) for n in names] == mixed_schedule([0.5, 0.5], 40)
    assert sum(n.startswith("in") for n in names) == 20
    assert all(names.count(f"in{i}") == 10 for i in range(2))
    assert all(names.count(f"aux{i}") == 2 for i in range(10))
    # never more than one step off the share at any point
    for k in range(1, 41):
        assert abs(sum(n.startswith("in") for n in names[:k]) - k / 2) <= 1
    with pytest.raises(ReconstructConfigError, match="no views"):
        t.run_mixed([ViewGroup([], 1.0)], 1)
    with pytest.raises(ReconstructConfigError, match="input_share"):
        AuxiliaryConfig(input_share=1.0)


# ---- the ablation switches -----------------------------------------------------------------
def test_config_round_trips_with_the_ablation_fields():
    cfg = ReconstructConfig(
        init_method="random",
        random_init_count=5000,
        room_bounds_m=(-3.5, -3, 0, 3.5, 3, 3),
        auxiliary=AuxiliaryConfig(enabled=False, refiner="none", num_views=4, aux_weight=0.5),
    ).resolved(960)
    text = cfg.to_toml()
    assert "[auxiliary.guided]" in text and 'init_method = "random"' in text
    again = ReconstructConfig.from_toml(text)
    assert again == cfg and again.room_bounds_m == (-3.5, -3.0, 0.0, 3.5, 3.0, 3.0)
    part = ReconstructConfig.from_toml(
        "[auxiliary]\nnum_views = 7\nradius_m = 1\n[auxiliary.guided]\nmin_alpha = 0.25\n"
    )
    assert part.auxiliary.num_views == 7 and part.auxiliary.radius_m == 1.0
    assert part.auxiliary.guided.min_alpha == 0.25 and part.auxiliary.enabled


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ("[auxiliary]\nnum_views = 0\n", r"auxiliary\.num_views=0"),
        ("[auxiliary]\nmin_radius_m = 0.5\n", r"auxiliary\.min_radius_m=0\.5"),
        ("[auxiliary]\naux_weight = -1.0\n", r"auxiliary\.aux_weight=-1\.0"),
        ("[auxiliary]\nenabled = 1\n", r"auxiliary\.enabled = 1: must be true or false"),
        ('[auxiliary]\nrefiner = ""\n', r"auxiliary\.refiner=''"),
        ("[auxiliary]\nradius = 1.0\n", r"unknown option 'auxiliary\.radius'"),
        ('init_method = "sparse"\n', r"init_method = 'sparse': choose one of 'depth', 'random'"),
        ("random_init_count = 0\n", r"random_init_count=0"),
        ("room_bounds_m = [0, 0, 0, 1, 1]\n", r"room_bounds_m=\[0\.0, 0\.0, 0\.0, 1\.0, 1\.0\]"),
        ("room_bounds_m = [0, 0, 3, 1, 1, 0]\n", r"each min below its max"),
    ],
)
def test_bad_ablation_settings_name_the_field_and_value(toml, message):
    with pytest.raises(ReconstructConfigError, match=message):
        ReconstructConfig.from_toml(toml)


def test_random_init_is_uniform_in_its_box_with_the_requested_count():
    lo, hi = np.array([-3.5, -3.0, 0.0]), np.array([3.5, 3.0, 3.0])
    g = init_random(20_000, lo, hi, seed=5)
    means = g.means_m.numpy()
    assert g.num == 20_000 and (means >= lo).all() and (means <= hi).all()
    np.testing.assert_allclose(means.mean(axis=0), (lo + hi) / 2, atol=0.05)
    np.testing.assert_allclose(means.std(axis=0), (hi - lo) / np.sqrt(12), rtol=0.03)
    colours = g.colors().detach().numpy()
    assert colours.min() >= 0 and colours.max() <= 1 and abs(colours.mean() - 0.5) < 0.01
    assert torch.equal(
        init_random(100, lo, hi, seed=1).means_m, init_random(100, lo, hi, seed=1).means_m
    )
    with pytest.raises(ReconstructConfigError, match="random_init_count=0"):
        init_random(0, lo, hi)


def test_random_init_box_is_the_room_or_what_the_cameras_look_at(world):
    """Without bounds the box holds every camera and the operating table the rig looks at; with
    the floor known it starts there; with the room given it is the room."""
    views = [view_from_image(
        Camera(name=f"c{i}", intrinsics=Intrinsics.from_fov(*SIZE, 100.0), pose=u.left_pose),
        np.zeros((SIZE[1], SIZE[0], 3), np.uint8),
    ) for i, u in enumerate(world.rig)]  # fmt: skip
    lo, hi = random_init_box(views, None)
    centres = np.array([u.left_pose.centre_m for u in world.rig])
    table = np.array([0.0, 0.0, 1.0])
    assert (lo <= centres.min(axis=0)).all() and (hi >= centres.max(axis=0)).all()
    assert (lo <= table).all() and (table <= hi).all()
    floor = (np.array([-np.inf, -np.inf, 0.0]), np.full(3, np.inf))
    lo_f, hi_f = random_init_box(views, floor)
    assert lo_f[2] == 0.0 and np.array_equal(lo_f[:2], lo[:2]) and np.array_equal(hi_f, hi)
    lo_r, hi_r = random_init_box(views, ROOM)
    assert np.array_equal(lo_r, ROOM[0]) and np.array_equal(hi_r, ROOM[1])


def test_cli_options_set_the_ablation_switches():
    base = ["s.h5", "--at", "1", "--out", "o"]

    def options(*extra: str) -> ReconstructConfig:
        return _with_options(ReconstructConfig(), reconstruct_parser().parse_args([*base, *extra]))

    cfg = options("--init", "random", "--no-refinement")
    assert cfg.init_method == "random" and not cfg.auxiliary.enabled
    cfg = options("--refiner", "difix", "--refiner-weights", "/w/difix")
    assert cfg.auxiliary.refiner == "difix" and cfg.auxiliary.refiner_weights == "/w/difix"
    assert cfg.auxiliary.enabled and cfg.init_method == "depth"
    assert options() == ReconstructConfig()
    with pytest.raises(CommandArgumentError, match="--no-refinement"):
        options("--no-refinement", "--refiner", "difix")


def test_conflicting_cli_options_are_one_line(tmp_path, sim_true_rig):
    session = tmp_path / "s.h5"
    session.write_bytes(b"")
    sim_true_rig.write(tmp_path / "calibration.toml")
    done = run_egosurg(
        "reconstruct", str(session), "--at", "1", "--out", str(tmp_path / "o"),
        "--no-refinement", "--refiner", "difix",
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "--no-refinement" in done.stderr


# ---- the pipeline --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_timestamp(world) -> Timestamp:
    """Every sensor of the rig at 320x200 pixels (ideal pinholes), rendered by the sim."""
    frames = []
    for unit in world.rig:
        for side in ("left", "right"):
            pose = unit.sensor(side, Resolution.SVGA).pose
            cam = Camera(
                name=f"SN{unit.serial}-{side}",
                intrinsics=Intrinsics.from_fov(320, 200, 100.0),
                pose=pose,
            )
            image = world.render(cam, T_S).image_rgb
            frames.append(SensorFrame(cam, unit.serial, side, image, 0))
    return Timestamp(
        session=Path("sim-seed11"),
        set_index=0,
        set_unix_ns=0,
        t_s=T_S,
        frames=tuple(frames),
        missing_serials=(),
        resolution=Resolution.SVGA,
    )


def _small_config(**changes) -> ReconstructConfig:
    cfg = ReconstructConfig(
        train=TrainConfig(warmup_steps=2, refine_steps=2, log_every_steps=1000),
        train_max_width_px=160,
        fusion=FusionConfig(max_points=5000),  # few Gaussians: steps of milliseconds
        room_bounds_m=(-3.5, -3.0, 0.0, 3.5, 3.0, 3.0),
        auxiliary=AuxiliaryConfig(num_views=2),
    )
    return dataclasses.replace(cfg, **changes)


@pytest.mark.slow  # the whole reconstruction chain
def test_pipeline_random_init_with_auxiliary_views(small_timestamp, tmp_path):
    cfg = _small_config(init_method="random", random_init_count=3000)
    result = reconstruct(small_timestamp, cfg, tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["init_method"] == "random" and summary["gaussians"] == 3000
    aux = summary["auxiliary"]
    assert aux["enabled"] and aux["views"] == 2 * 8 and aux["refiner"].startswith("guided(")
    assert aux["size_px"] == [160, 100] and aux["seconds"] >= aux["render_s"] + aux["refine_s"]
    assert summary["steps"] == 4 and set(summary["ms_per_step"]) == {"warm-up", "refinement"}
    assert "auxiliary_views" in summary["timings_s"]
    assert cv2.imread(str(tmp_path / "auxiliary_views.jpg")) is not None
    # 4 small steps move a Gaussian by far less than 5 cm: all still inside the room
    means = result.gaussians.means_m.numpy()
    assert (means >= ROOM[0] - 0.05).all() and (means <= ROOM[1] + 0.05).all()
    assert result.fused.num > 1000  # stereo still ran, for points.ply and the baseline


@pytest.mark.slow  # the whole reconstruction chain
def test_pipeline_trains_eye_views_as_a_group_with_their_share(small_timestamp, tmp_path):
    """With ``[auxiliary.eye] num_views`` the refinement stage also trains on cameras at eye
    height, their share of the steps as configured; the summary counts them."""
    eye = EyeViewConfig(num_views=3, share=0.25)
    cfg = _small_config(
        auxiliary=AuxiliaryConfig(num_views=2, input_share=0.8, eye=eye),
        train=TrainConfig(warmup_steps=2, refine_steps=40, log_every_steps=1000),
    )
    result = reconstruct(small_timestamp, cfg, tmp_path)
    aux = json.loads((tmp_path / "summary.json").read_text())["auxiliary"]
    # a drawn eye view that no recorded view supervises at all is left out
    assert aux["views"] == 2 * 8 and 1 <= aux["eye_views"]["views"] <= 3
    steps = [s.view for s in result.trainer.log.steps[2:]]
    assert len(steps) == 40
    on_eye = sum(v.startswith("eye:") for v in steps)
    on_shell = sum(v.startswith("aux:") for v in steps)
    assert on_eye == 10  # a quarter of the refinement steps
    assert on_shell == round(40 * 0.75 * 0.2)  # the shell keeps its part of the rest
    trained = {v for v in steps if v.startswith("eye:")}
    assert len(trained) == aux["eye_views"]["views"] and trained <= {"eye:0", "eye:1", "eye:2"}


@pytest.mark.slow  # the whole reconstruction chain
def test_pipeline_without_refinement_and_with_a_callers_hook(small_timestamp, tmp_path):
    off = _small_config(auxiliary=AuxiliaryConfig(enabled=False, refiner="no-such-refiner"))
    result = reconstruct(small_timestamp, off, tmp_path / "off")
    summary = json.loads((tmp_path / "off" / "summary.json").read_text())
    assert summary["auxiliary"] == {"enabled": False}
    assert summary["gaussians"] == result.fused.num  # depth init: one per fused point
    assert not (tmp_path / "off" / "auxiliary_views.jpg").exists()

    bad = _small_config(auxiliary=AuxiliaryConfig(refiner="no-such-refiner"))
    with pytest.raises(RefinerNotFoundError, match="no-such-refiner"):
        reconstruct(small_timestamp, bad, None)  # before stereo: at once

    calls: list[int] = []

    def hook(trainer: Trainer, views) -> list[View]:
        calls.append(trainer.step_index)
        return [*views, views[0]]

    # the hook wins over the configured refiner (which would not even load)
    reconstruct(small_timestamp, bad, tmp_path / "hook", refine=hook)
    summary = json.loads((tmp_path / "hook" / "summary.json").read_text())
    assert calls == [2] and summary["auxiliary"]["views"] == 1
    assert summary["auxiliary"]["refiner"] == "caller's refine hook"
