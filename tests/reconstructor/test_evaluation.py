"""The evaluation: temporal metrics, LPIPS, reading an evaluation set and planning the protocols
on it, and ``egosurg evaluate`` end to end at tiny settings on a small set that the real
``egosurg sim eval-set`` writes once for this module."""

from __future__ import annotations

import csv
import dataclasses
import importlib.metadata
import importlib.util
import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from protocol.cli import main as egosurg
from protocol.command import CommandArgumentError
from protocol.formats.eval_set import EvalSet, EvalSetError
from protocol.formats.rig_calibration import RigCalibration
from reconstructor.errors import LpipsWeightsError
from reconstructor.evaluation.doc import measured_order, order_holds
from reconstructor.evaluation.lpips import backbone_state_dict, load_lpips
from reconstructor.evaluation.methods import PROTOCOLS, EvalSettings
from reconstructor.evaluation.plan import plan
from reconstructor.evaluation.run import check_plan
from reconstructor.evaluation.runner import EvalSource
from reconstructor.evaluation.temporal import pair_flicker, pair_psnr, pair_ssim, temporal_scores
from tests.helpers import run_egosurg

PHASE = "intraoperative"


@pytest.fixture(scope="module")
def eval_set(tmp_path_factory) -> EvalSet:
    """One scene, three sets (the temporal protocol's smallest useful sequence), egocentric
    reference views at set 0, small enough to render in a blink."""
    out = tmp_path_factory.mktemp("evalset")
    done = run_egosurg(
        "sim", "eval-set", "--out", str(out), "--phases", PHASE, "--sets", "3",
        "--eval-sets", "0", "--resolution", "SVGA", "--view-size", "160x100", "--instants", "1",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return EvalSet.read(out)


def _texture(h: int = 64, w: int = 96, seed: int = 0) -> np.ndarray:
    """A smooth, textured uint8 image with values in [20, 200] (no clipping when brightened)."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(20, 200, (h // 8, w // 8, 3)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC).clip(20, 200).astype(np.uint8)


# ---- temporal metrics ------------------------------------------------------------------------


def test_a_schedule_too_short_for_the_refiner_says_so():
    """The recorded views keep 95 % of the refinement steps: at 10 steps (7 of refinement) the
    refiner's views get none, so "EgoSurg" is "EgoSurg w/o refinement" under another name. The
    table's settings line says how many steps the refiner got, and the fewest --steps that
    give it one are known."""
    short = EvalSettings(steps=10, methods=("no-refinement", "egosurg"))
    assert short.auxiliary_steps("no-refinement") is None
    assert short.auxiliary_steps("egosurg") == 0
    assert "0 of the 7 refinement steps on its views" in short.describe()
    enough = short.steps_for_auxiliary("egosurg")
    assert 10 < enough <= 40  # 5 % of the refinement steps: one within the first 20 or so
    assert dataclasses.replace(short, steps=enough).auxiliary_steps("egosurg") == 1
    assert dataclasses.replace(short, steps=enough - 1).auxiliary_steps("egosurg") == 0
    paper = dataclasses.replace(short, steps=2000)  # 1500 refinement steps, 5 % of them
    assert abs(paper.auxiliary_steps("egosurg") - 75) <= 1  # type: ignore[operator]


def test_identical_frames_are_perfectly_stable():
    img = _texture()
    assert pair_psnr(img, img) == math.inf
    assert pair_ssim(img, img) == pytest.approx(1.0, abs=1e-6)
    assert pair_flicker(img, img) == 0.0
    sc = temporal_scores([img, img.copy(), img.copy()])
    assert (sc.t_psnr_db, sc.flicker, sc.pairs) == (math.inf, 0.0, 2)
    assert sc.t_ssim == pytest.approx(1.0, abs=1e-6)


def test_a_uniform_brightness_change_gives_the_hand_computed_scores():
    img = _texture()
    brighter = img + np.uint8(10)
    # every pixel differs by 10/255: MSE = (10/255)², PSNR = 20 log10(255 / 10) = 28.13 dB
    assert pair_psnr(img, brighter) == pytest.approx(28.1308, abs=1e-3)
    # luminance rises by 10/255 in every block (the weights sum to 1), contrast is unchanged:
    # flicker = (10/255) / 2
    assert pair_flicker(img, brighter) == pytest.approx(0.5 * 10 / 255, rel=1e-9)
    # float images: 0.5 -> 0.6 is an MSE of 0.01, 20 dB
    grey = np.full((16, 16, 3), 0.5)
    assert pair_psnr(grey, grey + 0.1) == pytest.approx(20.0, abs=1e-9)


def test_flicker_counts_a_change_of_local_structure():
    flat = np.full((16, 16, 3), 0.5)
    checker = flat.copy()
    checker[::2, ::2] = checker[1::2, 1::2] = 0.6
    checker[::2, 1::2] = checker[1::2, ::2] = 0.4
    # same block means; the contrast (SD) rises from 0 to 0.1 in every 8x8 block: flicker 0.1
    assert pair_flicker(flat, checker) == pytest.approx(0.1, abs=1e-9)


def _moving_square(frames: int, flicker_amplitude: float) -> list[np.ndarray]:
    base = _texture().astype(np.float64) / 255
    seq = []
    for k in range(frames):
        img = base.copy()
        img[24:40, 8 + 4 * k : 24 + 4 * k] = 0.95  # a person-sized object walking across
        img = img + (flicker_amplitude if k % 2 else -flicker_amplitude)
        seq.append(img.clip(0, 1))
    return seq


def test_flicker_orders_a_flickering_sequence_above_a_steady_one():
    steady = temporal_scores(_moving_square(8, 0.0))
    flickering = temporal_scores(_moving_square(8, 0.03))
    assert flickering.flicker > 2 * steady.flicker
    assert flickering.t_psnr_db < steady.t_psnr_db and flickering.t_ssim < steady.t_ssim


def test_temporal_scores_refuse_too_short_or_mismatched_sequences():
    with pytest.raises(ValueError, match="at least two frames"):
        temporal_scores([_texture()])
    with pytest.raises(ValueError, match="differ in shape"):
        pair_flicker(_texture(), _texture(32, 48))


# ---- LPIPS -----------------------------------------------------------------------------------

needs_lpips = pytest.mark.skipif(
    importlib.util.find_spec("lpips") is None, reason="the lpips package (linear heads) is absent"
)


@needs_lpips
def test_lpips_is_zero_for_identical_images_and_grows_with_distortion(tmp_path):
    # AlexNet only: a random VGG16 is 59 MB to write and read for the same code path
    torch.manual_seed(0)
    weights = tmp_path / "alex.pth"
    torch.save(backbone_state_dict("alex"), weights)  # torchvision's layout, random values
    model = load_lpips(weights)
    assert model.net == "alex"
    img = _texture(64, 96).astype(np.float32) / 255
    rng = np.random.default_rng(1)
    assert model.distance(img, img) == pytest.approx(0.0, abs=1e-7)
    d = [
        model.distance(img, (img + rng.normal(0, s, img.shape)).clip(0, 1).astype(np.float32))
        for s in (0.02, 0.08, 0.3)
    ]
    assert 0 < d[0] < d[1] < d[2]
    # uint8 input is the same image scaled by 1/255
    u8 = (img * 255 + 0.5).astype(np.uint8)
    assert model.distance(u8, u8) == pytest.approx(0.0, abs=1e-7)


@needs_lpips
def test_lpips_refuses_weights_that_are_not_alexnet_or_vgg(tmp_path):
    with pytest.raises(LpipsWeightsError, match="does not exist"):
        load_lpips(tmp_path / "missing.pth")
    partial = {k: v for k, v in backbone_state_dict("alex").items() if k.startswith("features.0")}
    torch.save(partial, tmp_path / "partial.pth")
    with pytest.raises(LpipsWeightsError, match="AlexNet"):
        load_lpips(tmp_path / "partial.pth")


# ---- the evaluation set: reading it, and planning the protocols on it -----------------------


def test_a_timestamp_is_the_session_s_set_with_its_calibration(eval_set):
    scene = eval_set.scenes[0]
    source = EvalSource(eval_set)
    calibration = RigCalibration.read(eval_set.path(scene.calibration))
    ts = source.timestamp(scene.name, 2)
    assert ts.set_index == 2 and ts.missing_serials == ()
    assert ts.t_s == pytest.approx(2.0 + 2 / 15, abs=1e-6)  # session time is sim time
    assert len(ts.frames) == 8 and len(ts.stereo_pairs()) == 4
    for frame in ts.frames:
        sensor = calibration.sensor(frame.camera_serial, frame.side)
        np.testing.assert_allclose(frame.camera.pose.matrix, sensor.pose.matrix, atol=1e-12)
        assert frame.image_rgb.shape == (600, 960, 3) and frame.image_rgb.dtype == np.uint8
    assert source.timestamp(scene.name, 2) is ts  # read once for the jobs of one timestamp
    assert source.timestamp(scene.name, 0).set_index == 0
    assert source.set_count(scene.name) == 3


def test_plan_reuses_reconstructions_across_protocols(eval_set):
    s = EvalSettings(protocols=("near-field", "phases", "temporal"))
    jobs = plan(s, eval_set)
    # sets 0, 1, 2 of the one scene; set 0 serves near-field, phases and the sequence's start
    assert [(j.scene.label, j.train_views) for j in jobs] == [
        (f"{PHASE}@set0", "left"), (f"{PHASE}@set1", "left"), (f"{PHASE}@set2", "left")
    ]  # fmt: skip
    first = jobs[0]
    assert first.scene.phase == PHASE
    assert first.held_out_protocols == ["near-field", "phases"]
    assert [j.temporal for j in jobs] == [[(f"{PHASE}@set0", k)] for k in range(3)]
    assert jobs[1].held_out_protocols == [] and jobs[2].ego_views == []


def test_plan_egocentric_takes_every_reference_view_of_the_set(eval_set):
    scene = eval_set.scenes[0]
    jobs = plan(EvalSettings(protocols=PROTOCOLS), eval_set)
    # a timestamp's jobs run one after the other: left (held out, temporal), then all (views)
    assert [(j.scene.set_index, j.train_views) for j in jobs] == [
        (0, "left"), (0, "all"), (1, "left"), (2, "left")
    ]  # fmt: skip
    ego = jobs[1]
    assert ego.ego_views == scene.views_at(0) and len(ego.ego_views) >= 2
    assert {v.role for v in ego.ego_views} >= {"surgeon", "anaesthetist"}


def test_a_protocol_the_set_cannot_serve_is_refused_by_name(eval_set):
    bare = dataclasses.replace(
        eval_set,
        scenes=tuple(
            dataclasses.replace(sc, views=(), temporal_sets=(0,), phase="")
            for sc in eval_set.scenes
        ),
    )
    for protocol, words in (
        ("egocentric", "reference views"),
        ("temporal", "at least two temporal_sets"),
        ("phases", "a phase"),
    ):
        with pytest.raises(CommandArgumentError, match=f"--protocol {protocol}: .*{words}"):
            plan(EvalSettings(protocols=(protocol,)), bare)
    assert len(plan(EvalSettings(protocols=("near-field",)), bare)) == 1


def test_scenes_and_phases_choose_among_the_set_s_scenes(eval_set):
    with pytest.raises(CommandArgumentError, match=f"--scenes nope: .* it has {PHASE}"):
        plan(EvalSettings(scenes=("nope",)), eval_set)
    with pytest.raises(CommandArgumentError, match=f"--phases empty: .*phases: {PHASE}"):
        plan(EvalSettings(phases=("empty",)), eval_set)
    assert len(plan(EvalSettings(scenes=(PHASE,), phases=(PHASE,)), eval_set)) == 1


def test_a_set_index_the_session_lacks_fails_before_any_work(eval_set):
    late = dataclasses.replace(
        eval_set, scenes=(dataclasses.replace(eval_set.scenes[0], eval_sets=(0, 7)),)
    )
    jobs = plan(EvalSettings(), late)
    with pytest.raises(EvalSetError, match=f"scene '{PHASE}' asks for set 7 .* holds 3 sets"):
        check_plan(jobs, EvalSource(late))


def test_steps_split_like_the_papers_500_plus_1500():
    for steps, warmup, refine in ((2000, 500, 1500), (8, 2, 6), (10, 3, 7), (1, 0, 1)):
        s = EvalSettings(steps=steps)
        assert (s.warmup_steps, s.refine_steps) == (warmup, refine)


@pytest.mark.parametrize(
    ("given", "protocols"),
    [
        (["egocentric", "near-field"], ("near-field", "egocentric")),  # the paper's order
        (["phases", "phases"], ("phases",)),
        (["near-field", "all"], PROTOCOLS),
    ],
)
def test_several_protocols_can_be_chosen_at_once(given, protocols):
    from reconstructor.evaluation.cli import build_parser, settings_from_args

    args = build_parser().parse_args(["set", "--out", "o", "--protocol", *given])
    assert settings_from_args(args).protocols == protocols


def test_ordering_check_on_the_papers_own_tables():
    # Table 3A PSNR follows depth reprojection < image-only < w/o diffusion < EgoSurg
    psnr_3a = {
        "depth-reprojection": 16.4,
        "image-only": 18.0,
        "no-refinement": 24.3,
        "egosurg": 26.8,
    }
    assert order_holds(psnr_3a, "psnr_db")
    # LPIPS is lower-is-better: the same ordering with falling values
    lpips_3a = {"depth-reprojection": 0.8, "image-only": 0.416, "no-refinement": 0.182}
    assert order_holds(lpips_3a, "lpips")
    # Table 4 SSIM does not: image-only .694 is above w/o diffusion .641
    ssim_4 = {
        "depth-reprojection": 0.239,
        "image-only": 0.694,
        "no-refinement": 0.641,
        "egosurg": 0.766,
    }
    assert not order_holds(ssim_4, "ssim")
    assert measured_order(ssim_4, "ssim") == [
        "depth-reprojection", "no-refinement", "image-only", "egosurg"
    ]  # fmt: skip
    assert order_holds({"egosurg": 20.0}, "psnr_db") is None  # one method: nothing to order


# ---- the command -----------------------------------------------------------------------------


@pytest.mark.slow  # the whole reconstruction chain
def test_evaluate_command_writes_tables_pictures_and_the_report(eval_set, tmp_path, caplog):
    out, doc = tmp_path / "eval", tmp_path / "EVALUATION.md"
    args = [
        "evaluate", str(eval_set.root), "--out", str(out), "--steps", "8", "--train-width", "160",
        "--methods", "depth-reprojection", "no-refinement", "--write-doc", str(doc),
    ]  # fmt: skip
    caplog.set_level("INFO", logger="reconstructor.evaluation.runner")
    assert egosurg(args) == 0  # in this process: the fixture ran the command as a subprocess
    assert "[1/1] no-refinement" in caplog.text and "ETA" in caplog.text

    with open(out / "near-field" / "scores.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 4 * 2  # four held-out right cameras, two methods
    assert {r["method"] for r in rows} == {"depth-reprojection", "no-refinement"}
    calibration = RigCalibration.read(eval_set.path(eval_set.scenes[0].calibration))
    assert {r["view"] for r in rows} == {f"SN{s}-right" for s in calibration.camera_serials}
    assert {(r["phase"], r["scene"]) for r in rows} == {(PHASE, f"{PHASE}@set0")}
    for r in rows:
        assert 5.0 < float(r["psnr_db"]) < 40.0 and 0.0 < float(r["ssim"]) < 1.0
        assert r["lpips"] == ""
    # even 8 steps of training beat drawing the fused points (measured: 11.9 dB against 9.7)
    by_method = {m: np.mean([float(r["psnr_db"]) for r in rows if r["method"] == m]) for m in
                 ("depth-reprojection", "no-refinement")}  # fmt: skip
    assert by_method["no-refinement"] > by_method["depth-reprojection"] + 1.0, by_method
    table = (out / "near-field" / "table.md").read_text()
    assert "steps 8 (2 warm-up + 6 refinement), training width 160 px" in table
    assert eval_set.description in table
    assert "| EgoSurg w/o refinement |" in table and "n/a (no --lpips-weights)" in table
    pngs = sorted((out / "near-field" / "png").glob("*.png"))
    assert len(pngs) == 4
    img = cv2.imread(str(pngs[0]))
    assert img.shape == (100, 3 * 160, 3)  # recorded | depth reprojection | w/o refinement
    assert (out / "configs" / "no-refinement-left.toml").exists()
    settings = json.loads((out / "settings.json").read_text())
    assert settings["eval_set"] == str(eval_set.root)
    assert settings["eval_set_description"] == eval_set.description

    report = doc.read_text()
    # both steps that made it: the evaluation set, with every option the fixture gave it (its
    # description carries the command), and the evaluation
    made = next(x for x in report.splitlines() if "egosurg sim eval-set --out" in x)
    command = made.split("#")[0].split()
    assert command[:4] == ["egosurg", "sim", "eval-set", "--out"]
    given = {"--out": str(eval_set.root), "--phases": PHASE, "--sets": "3", "--eval-sets": "0",
             "--resolution": "SVGA", "--view-size": "160x100"}  # fmt: skip
    for option, value in given.items():
        assert command[command.index(option) + 1] == value, made
    assert "egosurg evaluate " + " ".join(args[1:]) in report
    assert "Table 3A" in report and "16.4 ± 0.2" in report  # the paper's number beside ours
    assert "PSNR (dB) ↑: the paper's ordering" in report
    assert "Not run in this evaluation (add `--protocol egocentric`" in report


def test_egocentric_scores_are_also_summarised_over_instants_as_the_paper_does():
    """The paper's mean ± SD is over instants: each instant's views are averaged first, so an
    instant with six people counts once, not six times."""
    from reconstructor.evaluation.tables import EvalResults, ImageScore, egocentric_breakdowns

    def view(instant: str, name: str, psnr: float) -> ImageScore:
        return ImageScore(
            "egocentric", "egosurg", PHASE, f"{instant}/{name}", name, psnr, 0.5, None
        )

    results = EvalResults(
        settings=EvalSettings(protocols=("egocentric",), methods=("egosurg",)),
        image_scores=[
            view("a@set0", "surgeon@0", 20.0),
            view("a@set0", "nurse@0", 22.0),
            view("b@set1", "surgeon@1", 25.0),
        ],
    )
    text = egocentric_breakdowns(results)
    row = next(line for line in text.splitlines() if line.startswith("| EgoSurg"))
    # instants 21.0 and 25.0: mean 23.0, SD 2.83 (over the three views it would be 22.3)
    assert row.strip("| ").split(" | ")[1:4] == ["23.0 ± 2.8", ".500 ± .000", "2"], row


def test_the_warm_start_row_continues_each_frame_from_the_one_before(eval_set, tmp_path, caplog):
    """Table 3B's warm-start row is a real warm chain: the first frame is EgoSurg's own cold
    model (identical renders), each later frame starts from the previous frame's warm model
    (the warm start's kept/dropped/added log, once per later frame) and is scored for stability
    and against the recorded right images like the paper's rows."""
    out, config = tmp_path / "warm", tmp_path / "quick.toml"
    # stereo at a quarter size, no hole fill, two auxiliary views per camera: the mechanism,
    # not the quality, is under test (a fifth of the default settings' time)
    config.write_text(
        "[stereo]\nmatch_scale = 0.25\n[fill]\nenabled = false\n"
        "[fusion]\nmax_points = 20000\n[auxiliary]\nnum_views = 2\n"
    )
    args = [
        "evaluate", str(eval_set.root), "--out", str(out), "--protocol", "temporal",
        "--steps", "8", "--train-width", "96", "--methods", "egosurg", "egosurg-warm",
        "--warm-steps", "3", "--refiner", "none", "--config", str(config),
    ]  # fmt: skip
    caplog.set_level("INFO")
    assert egosurg(args) == 0
    assert caplog.text.count("warm start: kept") == 2  # sets 1 and 2, not set 0
    assert "egosurg-warm (EgoSurg's cold model) at intraoperative@set0" in caplog.text
    with open(out / "temporal" / "scores.csv") as fh:
        temporal = list(csv.DictReader(fh))
    assert {r["method"] for r in temporal} == {"egosurg", "egosurg-warm", "recorded"}
    assert all(int(r["pairs"]) == 2 for r in temporal)
    with open(out / "temporal" / "fidelity_scores.csv") as fh:
        fidelity = list(csv.DictReader(fh))
    psnr = {(r["method"], r["scene"], r["view"]): float(r["psnr_db"]) for r in fidelity}
    assert len(psnr) == 2 * 3 * 4  # two rows, three sets, four held-out right cameras
    for (method, scene, view), value in psnr.items():
        if method == "egosurg-warm":
            cold = psnr[("egosurg", scene, view)]
            assert (value == cold) == scene.endswith("@set0"), (scene, view, value, cold)
    table = (out / "temporal" / "table.md").read_text()
    assert "| EgoSurg, warm start (3 steps per later frame) |" in table
    assert "against the recorded right images" in table


def _quick_config(path: Path) -> Path:
    """Stereo at a quarter size, no hole fill, two auxiliary views per camera: for tests of a
    mechanism, not of quality (a fifth of the default settings' time)."""
    path.write_text(
        "[stereo]\nmatch_scale = 0.25\n[fill]\nenabled = false\n"
        "[fusion]\nmax_points = 20000\n[auxiliary]\nnum_views = 2\n"
    )
    return path


def _quick_run(eval_set: EvalSet, tmp_path: Path, *extra: str) -> tuple[Path, list[str]]:
    """``OUT`` and the arguments of a quick run (8 steps of EgoSurg w/o refinement)."""
    out = tmp_path / "o"
    config = _quick_config(tmp_path / "quick.toml")
    args = ["evaluate", str(eval_set.root), "--out", str(out), *extra, "--steps", "8",
            "--train-width", "96", "--methods", "no-refinement",
            "--config", str(config)]  # fmt: skip
    return out, args


def test_a_stopped_run_resumes_where_it_stopped_with_the_same_numbers(eval_set, tmp_path, caplog):
    """An overnight evaluation that is stopped (killed, machine given back) keeps every
    timestamp it finished: ``--resume`` loads them, runs the rest, and the tables are the ones
    an uninterrupted run makes, the warm chain and the temporal scores across the stop
    included. A record made with other settings is refused by name, and without ``--resume``
    an earlier run's records are never overwritten."""
    config = _quick_config(tmp_path / "quick.toml")
    common = [
        "--protocol", "near-field", "temporal", "egocentric", "--steps", "8", "--train-width",
        "96", "--methods", "depth-reprojection", "egosurg", "egosurg-warm", "--warm-steps", "3",
        "--refiner", "none", "--config", str(config),
    ]  # fmt: skip
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    assert egosurg(["evaluate", str(eval_set.root), "--out", str(whole), *common]) == 0
    records = sorted(p.name for p in (whole / "jobs").glob("*.json"))
    # sets 0 (left and all views), 1 and 2 (left): four timestamps
    assert len(records) == 4, records
    # a stop during set 2: sets 0 and 1 recorded, set 2's arrays written, its record half-way
    shutil.copytree(whole, stopped)
    last = stopped / "jobs" / "intraoperative_set2_left.json"
    last.rename(last.with_name(last.name + ".tmp"))
    for name in ("summary.md", "temporal/scores.csv"):
        (stopped / name).unlink()

    def run(out: Path, *extra: str) -> int:
        return egosurg(["evaluate", str(eval_set.root), "--out", str(out), *common, *extra])

    caplog.set_level("INFO")
    caplog.clear()  # only the resumed run's lines (an earlier test may have set INFO already)
    assert run(stopped, "--resume") == 0
    assert caplog.text.count("resumed from its record") == 3
    assert "[1/2] egosurg at intraoperative@set2" in caplog.text  # only set 2 ran again
    # set 2's warm frame started from set 1's recorded warm model
    assert caplog.text.count("warm start: kept") == 1
    for table in ("near-field/scores.csv", "egocentric/scores.csv", "temporal/scores.csv",
                  "temporal/fidelity_scores.csv"):  # fmt: skip
        assert (stopped / table).read_text() == (whole / table).read_text(), table


def test_a_resume_over_changed_code_says_the_tables_mix_versions(eval_set, tmp_path, caplog):
    """Resuming after a fix is legitimate, so records made by other code are loaded, with a
    warning that says so (the reconstructor's sources are digested into every record)."""
    out, args = _quick_run(eval_set, tmp_path)
    assert egosurg(args) == 0
    (record,) = (out / "jobs").glob("*.json")
    data = json.loads(record.read_text())
    assert len(data["code"]) == 16  # an xxh3-64 digest
    caplog.set_level("INFO", logger="reconstructor.evaluation")
    caplog.clear()
    assert egosurg([*args, "--resume"]) == 0
    assert "other code" not in caplog.text and "resumed from its record" in caplog.text
    record.write_text(json.dumps({**data, "code": "0" * 16}))
    caplog.clear()
    assert egosurg([*args, "--resume"]) == 0
    assert "1 of 1 recorded job(s) were made by other code" in caplog.text
    assert "resumed from its record" in caplog.text and "[1/" not in caplog.text


@pytest.mark.skipif(torch.cuda.is_available(), reason="states what a machine without CUDA does")
def test_a_run_split_over_machines_is_merged_by_copying_its_jobs(eval_set, tmp_path, capsys):
    """A long evaluation can be spread by ``--scenes`` over processes or machines (a GPU server
    among them): each part's ``jobs/`` copied into one folder and resumed there gives the
    tables, with nothing run again. Which scenes a part chose is not compared, and a resume with
    nothing left to run needs no GPU, though its records were made with ``--device cuda``; with
    work left, the missing GPU is still one line before any work."""
    config = _quick_config(tmp_path / "quick.toml")
    part, merged = tmp_path / "part", tmp_path / "merged"
    common = ["--steps", "8", "--train-width", "96", "--methods", "no-refinement",
              "--config", str(config)]  # fmt: skip
    assert egosurg(["evaluate", str(eval_set.root), "--out", str(part), *common,
                    "--scenes", PHASE]) == 0  # fmt: skip
    (merged / "jobs").mkdir(parents=True)
    for record in (part / "jobs").glob("*.json"):  # as if made on a GPU server
        data = json.loads(record.read_text())
        assert data["settings"]["device"] == ""
        data["settings"]["device"] = "cuda"
        (merged / "jobs" / record.name).write_text(json.dumps(data))
    args = ["evaluate", str(eval_set.root), "--out", str(merged), *common, "--device", "cuda",
            "--resume"]  # fmt: skip
    capsys.readouterr()
    assert egosurg(args) == 0, capsys.readouterr().err
    table = "near-field/scores.csv"
    assert (merged / table).read_text() == (part / table).read_text()
    next(merged.joinpath("jobs").glob("*.json")).unlink()  # one timestamp left to run
    capsys.readouterr()
    assert egosurg(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--device cuda" in err, err


def test_the_report_names_the_libraries_that_made_the_depth_and_says_when_they_differ(
    eval_set, tmp_path, capsys, caplog
):
    """Another OpenCV gives other depths (5.0 against 4.x), and a run spread over
    machines, or resumed on an upgraded one, can mix them: each job's record names the
    libraries that made its depth stage, and the tables say which, or that they differ."""
    out, args = _quick_run(eval_set, tmp_path, "--protocol", "temporal")
    assert egosurg(args) == 0
    here = {"opencv": cv2.__version__, "open3d": importlib.metadata.version("open3d")}
    records = sorted((out / "jobs").glob("*.json"))
    assert len(records) >= 2
    for record in records:
        assert json.loads(record.read_text())["depth_made_by"] == [here]
    said = f"made with OpenCV {cv2.__version__}, open3d {here['open3d']} ({len(records)} jobs)"
    assert said in (out / "summary.md").read_text()

    # one job's depth made elsewhere with another OpenCV, one record from before they were kept
    data = json.loads(records[0].read_text())
    records[0].write_text(json.dumps({**data, "depth_made_by": [{**here, "opencv": "4.0.0"}]}))
    data = json.loads(records[1].read_text())
    records[1].write_text(json.dumps({k: v for k, v in data.items() if k != "depth_made_by"}))
    caplog.clear()
    assert egosurg([*args, "--resume"]) == 0
    summary = (out / "summary.md").read_text()
    assert "Depth stages made by different libraries" in summary
    assert f"OpenCV 4.0.0, open3d {here['open3d']} (1 job)" in summary
    assert "unknown libraries (made before the depth cache kept their versions) (1 job)" in summary
    assert any("made by different libraries" in r.message for r in caplog.records)


@pytest.mark.parametrize(
    "damage",
    [
        "truncated",
        "not_an_object",
        "no_scores",
        "bad_score",
        "no_settings",
        "frames_missing",
        "bad_made_by",
    ],
)
def test_a_damaged_record_is_named_in_one_line_and_the_rest_is_kept(
    damage, eval_set, tmp_path, capsys
):
    """A record cut short, edited or missing its arrays stops a resume before any work with one
    line that names the file and says to delete it, never a traceback; nothing is deleted."""
    out, args = _quick_run(eval_set, tmp_path, "--protocol", "temporal")
    assert egosurg(args) == 0
    record = out / "jobs" / "intraoperative_set1_left.json"
    data = json.loads(record.read_text())
    text = {
        "truncated": record.read_text()[:40],
        "not_an_object": "[1, 2]",
        "no_scores": json.dumps({k: v for k, v in data.items() if k != "image_scores"}),
        "bad_score": json.dumps({**data, "image_scores": [{"psnr": "x"}]}),
        "no_settings": json.dumps({k: v for k, v in data.items() if k != "settings"}),
        "frames_missing": record.read_text(),
        "bad_made_by": json.dumps({**data, "depth_made_by": "OpenCV 4"}),
    }[damage]
    record.write_text(text)
    if damage == "frames_missing":
        (out / "jobs" / "intraoperative_set1_left.frames.npz").unlink()
    files = sorted(p.name for p in (out / "jobs").iterdir())
    capsys.readouterr()
    assert egosurg([*args, "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "intraoperative_set1_left.json" in err and "delete" in err, err
    assert sorted(p.name for p in (out / "jobs").iterdir()) == files


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        ([], ["holds 1 finished job", "--resume", "another --out"]),
        (["--resume", "--steps", "9"], ["other settings", "steps 8 (now 9)"]),
    ],
)
def test_a_resume_that_would_mix_runs_is_one_line(extra, words, eval_set, tmp_path, capsys):
    out = tmp_path / "o"
    config = _quick_config(tmp_path / "quick.toml")
    common = ["--steps", "8", "--train-width", "96", "--methods", "no-refinement",
              "--config", str(config)]  # fmt: skip
    assert egosurg(["evaluate", str(eval_set.root), "--out", str(out), *common]) == 0
    before = (out / "near-field" / "scores.csv").read_text()
    capsys.readouterr()
    args = ["evaluate", str(eval_set.root), "--out", str(out), *common, *extra]
    if "--steps" in extra:
        args.remove("8")
        args.remove("--steps")
    assert egosurg(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and all(w in err for w in words), err
    assert (out / "near-field" / "scores.csv").read_text() == before  # nothing lost


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--methods", "egosurg-warm"], ["egosurg-warm", "--protocol temporal"]),
        (["--protocol", "temporal", "--warm-steps", "0"], ["--warm-steps 0"]),
    ],
)
def test_a_warm_start_row_that_cannot_work_is_one_line(extra, words, eval_set, tmp_path, capsys):
    assert egosurg(["evaluate", str(eval_set.root), "--out", str(tmp_path / "o"), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and all(w in err for w in words), err


@pytest.mark.slow  # the whole reconstruction chain
def test_egocentric_scores_renders_against_the_set_s_reference_views(eval_set, tmp_path, capsys):
    out = tmp_path / "ego"
    args = ["evaluate", str(eval_set.root), "--out", str(out), "--protocol", "egocentric"]
    assert egosurg([*args, "--methods", "depth-reprojection", "--train-width", "160"]) == 0
    views = eval_set.scenes[0].views_at(0)
    with open(out / "egocentric" / "scores.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["view"] for r in rows) == sorted(v.name for v in views)
    assert len({r["scene"] for r in rows}) == len(views)  # mean ± SD over views
    for r in rows:
        # the fused points seen from a person's eyes resemble the reference only roughly
        assert 3.0 < float(r["psnr_db"]) < 30.0 and -0.2 < float(r["ssim"]) < 1.0, r
    pngs = sorted((out / "egocentric" / "png").glob("*.png"))
    assert len(pngs) == len(views)
    # the reference view at its own size (160 x 100) beside the render at the same camera
    assert cv2.imread(str(pngs[0])).shape == (100, 2 * 160, 3)
    assert "| Depth reprojection |" in capsys.readouterr().out
    # where the mean comes from: one row per person, their PSNR over their own views
    table = (out / "egocentric" / "table.md").read_text()
    by_role = table.split("Per person")[1]
    for v in views:
        psnr = next(float(r["psnr_db"]) for r in rows if r["view"] == v.name)
        assert f"| {v.role} | {psnr:.1f} | 1 |" in by_role, (v.role, psnr, by_role)


def test_a_missing_or_bad_evaluation_set_is_one_line(eval_set, tmp_path, capsys):
    assert egosurg(["evaluate", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("egosurg evaluate: error: ") and "egosurg sim eval-set" in err
    # a set whose scenes have no reference views cannot serve the egocentric protocol
    bare = dataclasses.replace(
        eval_set, scenes=tuple(dataclasses.replace(sc, views=()) for sc in eval_set.scenes)
    )
    manifest = eval_set.root / "no_views.toml"  # beside the set: its paths are relative
    manifest.write_text(bare.to_toml())
    args = ["evaluate", str(manifest), "--out", str(tmp_path / "o"), "--protocol", "egocentric"]
    assert egosurg(args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert "--protocol egocentric" in err and "reference views" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--protocol", "sideways"], ["--protocol", "sideways"]),
        (["--methods", "nerf"], ["--methods nerf", "depth-reprojection"]),
        (["--steps", "0"], ["--steps 0"]),
        (["--steps", "many"], ["--steps", "many"]),
        (["--phases", "wand"], ["--phases wand", PHASE]),
        (["--scenes", "or-2"], ["--scenes or-2", PHASE]),
        (["--lpips-weights", "/nonexistent/alexnet.pth"], ["/nonexistent/alexnet.pth"]),
        (["--refiner", "no-such-refiner"], ["no-such-refiner"]),
    ],
)
def test_bad_arguments_give_one_line_errors(extra, words, eval_set, tmp_path, capsys):
    assert egosurg(["evaluate", str(eval_set.root), "--out", str(tmp_path / "o"), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("egosurg evaluate: error:")
    for w in words:
        assert w in err
    assert not (tmp_path / "o").exists()  # nothing written before the arguments are good


def test_a_bad_value_is_named_in_exactly_one_line(eval_set, tmp_path, capsys):
    assert egosurg(["evaluate", str(eval_set.root), "--out", str(tmp_path), "--steps", "0"]) == 2
    err = capsys.readouterr().err
    assert err == "egosurg evaluate: error: --steps 0: must be at least 1 (the paper uses 2000)\n"


def test_the_evaluation_set_and_out_are_required(tmp_path, capsys):
    assert egosurg(["evaluate", "--out", str(tmp_path / "o")]) == 2
    assert "EVALSET" in capsys.readouterr().err
    target = tmp_path / "file.txt"
    target.write_text("x")
    assert egosurg(["evaluate", str(tmp_path), "--out", str(target)]) == 2
    assert "is a file" in capsys.readouterr().err
    assert Path(target).read_text() == "x"
