"""The guided refiner against ground truth (an analytic plane and the simulator), the identity
refiner, and load_refiner's names, plug-ins and errors."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.bench_refiners import make_case, psnr
from protocol.camera import Camera, Intrinsics, Pose
from protocol.errors import UserError
from reconstructor.errors import (
    ReconstructConfigError,
    RefinerNotFoundError,
    RefinerWeightsError,
)
from reconstructor.refine.base import IdentityRefiner, Refined, Refiner, RefineRequest
from reconstructor.refine.guided import GuidedConfig, GuidedRefiner
from reconstructor.refine.refiners import ENTRY_POINT_GROUP, available_refiners, load_refiner

# ---- an analytic scene: a textured plane Z = 2 m, the reference at the origin -------------------

PLANE_Z_M = 2.0
SHIFT_M = 0.2  # the auxiliary camera sits this far along +x
W, H = 160, 120


def _texture(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """(…, 3) smooth colours of the plane point (X, Y)."""
    return np.stack(
        [
            0.5 + 0.4 * np.sin(6 * X) * np.cos(4 * Y),
            0.5 + 0.4 * np.cos(5 * X + 1),
            0.5 + 0.4 * np.sin(7 * Y + 2),
        ],
        axis=-1,
    ).astype(np.float32)


def _plane_view(intr: Intrinsics, centre_x_m: float) -> np.ndarray:
    """What a camera with R = I at (centre_x_m, 0, 0) sees of the plane."""
    u = np.arange(intr.width_px)[None, :]
    v = np.arange(intr.height_px)[:, None]
    X, Y = np.broadcast_arrays(
        centre_x_m + (u - intr.cx_px) / intr.fx_px * PLANE_Z_M,
        (v - intr.cy_px) / intr.fy_px * PLANE_Z_M,
    )
    return _texture(X, Y)


def _plane_request(*, ref_scale: float = 1.0) -> tuple[RefineRequest, np.ndarray]:
    """(request, truth): the aux render is flat grey with true depth; the reference is the plane
    seen from the origin, stored at ``ref_scale`` times its camera's resolution."""
    intr = Intrinsics.from_fov(W, H, 70.0)
    ref_cam = Camera(name="ref", intrinsics=intr, pose=Pose(R=np.eye(3)))
    aux_cam = Camera(
        name="aux", intrinsics=intr, pose=Pose(R=np.eye(3), t_m=np.array([-SHIFT_M, 0, 0]))
    )
    ref_intr = dataclasses.replace(
        intr,
        width_px=round(W * ref_scale),
        height_px=round(H * ref_scale),
        fx_px=intr.fx_px * ref_scale,
        fy_px=intr.fy_px * ref_scale,
        cx_px=(intr.cx_px + 0.5) * ref_scale - 0.5,
        cy_px=(intr.cy_px + 0.5) * ref_scale - 0.5,
    )
    reference = _plane_view(ref_intr, 0.0)
    truth = _plane_view(intr, SHIFT_M)
    req = RefineRequest(
        rendered=np.full((H, W, 3), 0.5, np.float32),
        rendered_alpha=np.ones((H, W), np.float32),
        rendered_depth_m=np.full((H, W), PLANE_Z_M, np.float32),
        camera=aux_cam,
        reference=reference,
        reference_mask=np.ones(reference.shape[:2], bool),
        reference_depth_m=np.full(reference.shape[:2], PLANE_Z_M, np.float32),
        reference_camera=ref_cam,
    )
    return req, truth


def _u_in_reference(intr: Intrinsics) -> np.ndarray:
    """(W,) the reference column each aux column of the plane lands in (worked out by hand)."""
    return np.arange(W) + intr.fx_px * SHIFT_M / PLANE_Z_M


RAW = GuidedConfig(use_inpaint=False, use_guided_filter=False)


def test_the_warp_reproduces_the_plane_where_the_reference_sees_it():
    req, truth = _plane_request()
    out = GuidedRefiner(RAW).refine(req)
    u_ref = _u_in_reference(req.camera.intrinsics)
    seen = np.broadcast_to(u_ref <= W - 1, (H, W))
    unseen = np.broadcast_to(u_ref >= W - 0.5, (H, W))  # half a pixel off: nearest is outside
    assert 0.5 < seen.mean() < 1.0 and unseen.mean() > 0.05
    err = np.abs(out.image - truth).max(axis=-1)
    assert err[seen].max() < 0.01  # bilinear sampling of a smooth texture
    np.testing.assert_array_equal(out.image[unseen], req.rendered[unseen])  # render kept
    # the loss sees the reference's pixels, not the render kept where the reference is blind
    assert out.mask[seen].all() and not out.mask[unseen].any()
    with_render = GuidedRefiner(dataclasses.replace(RAW, supervise_rendered=True)).refine(req)
    assert with_render.mask.all()  # a confident render everywhere


def test_a_reference_stored_at_half_size_warps_to_the_same_place():
    req, truth = _plane_request(ref_scale=0.5)
    out = GuidedRefiner(RAW).refine(req)
    seen = np.broadcast_to(_u_in_reference(req.camera.intrinsics) <= W - 2, (H, W))
    err = np.abs(out.image - truth).max(axis=-1)
    assert np.median(err[seen]) < 0.01 and err[seen].max() < 0.05


def test_an_occluder_in_front_of_the_reference_keeps_the_render_behind_it():
    req, truth = _plane_request()
    ref_depth = req.reference_depth_m.copy()
    ref_depth[:, : W // 2] = 1.0  # something at 1 m hides the left half of the plane
    req = dataclasses.replace(req, reference_depth_m=ref_depth)
    out = GuidedRefiner(RAW).refine(req)
    u_ref = np.broadcast_to(_u_in_reference(req.camera.intrinsics), (H, W))
    hidden = u_ref < W // 2 - 1
    visible = (u_ref > W // 2 + 1) & (u_ref <= W - 1)
    np.testing.assert_array_equal(out.image[hidden], req.rendered[hidden])
    assert np.abs(out.image - truth).max(axis=-1)[visible].max() < 0.01


def test_a_fully_occluded_or_masked_reference_changes_nothing_the_render_is_sure_of(sim_case):
    case = sim_case
    req = case.request
    confident = req.rendered_alpha >= GuidedConfig().min_alpha
    occluded = dataclasses.replace(req, reference_depth_m=np.full_like(req.reference_depth_m, 0.2))
    masked = dataclasses.replace(req, reference_mask=np.zeros_like(req.reference_mask))
    for r in (occluded, masked):
        out = GuidedRefiner().refine(r)
        np.testing.assert_array_equal(out.image[confident], req.rendered[confident])
        assert not out.mask.any()  # nothing came from the reference: nothing to supervise
        kept = GuidedRefiner(GuidedConfig(supervise_rendered=True)).refine(r)
        np.testing.assert_array_equal(kept.mask, confident)  # inpainted pixels left out
        raw = GuidedRefiner(RAW).refine(r)
        np.testing.assert_array_equal(raw.image[confident], req.rendered[confident])
        assert not raw.image[~confident].any()  # holes stay empty without inpainting


# ---- the simulator case, as the bench builds it ---------------------------------------------


@pytest.fixture(scope="module")
def sim_case():
    """One reference/auxiliary pair at half SVGA, rendered once for the module."""
    return make_case(baseline_m=0.3, rng_seed=0, scale=0.5)


def test_on_the_sim_the_refined_view_is_closer_to_the_truth_than_the_render(sim_case):
    case = sim_case
    req = case.request
    out = GuidedRefiner().refine(req)
    before_all, after_all = psnr(req.rendered, case.truth), psnr(out.image, case.truth)
    assert after_all > before_all + 8.0  # holes filled, colours corrected
    # where the render was confident too (colour blotches, blur, noise fixed by the warp)
    sure = req.rendered_alpha >= 1.0
    assert psnr(out.image, case.truth, sure) > psnr(req.rendered, case.truth, sure) + 3.0
    # the pixels handed to the loss are the good ones
    assert psnr(out.image, case.truth, out.mask) > after_all + 2.0
    assert out.mask.mean() > 0.8


def test_holes_are_filled(sim_case):
    case = sim_case
    req = case.request
    out = GuidedRefiner().refine(req)
    holes = case.holes
    assert holes.mean() > 0.03
    assert (out.image[holes].max(axis=-1) > 0).mean() > 0.99  # nothing left black
    assert psnr(out.image, case.truth, holes) > psnr(req.rendered, case.truth, holes) + 10.0
    kept_black = GuidedRefiner(dataclasses.replace(GuidedConfig(), use_inpaint=False))
    assert psnr(kept_black.refine(req).image, case.truth, holes) < psnr(
        out.image, case.truth, holes
    )


def test_supervise_inpainted_extends_the_mask_to_every_pixel(sim_case):
    case = sim_case
    every = GuidedConfig(supervise_inpainted=True, supervise_rendered=True)
    assert GuidedRefiner(every).refine(case.request).mask.all()
    default = GuidedRefiner().refine(case.request).mask
    out = GuidedRefiner(GuidedConfig(supervise_inpainted=True)).refine(case.request)
    assert (out.mask & ~default).sum() >= case.holes.sum() * 0.9  # the holes join the mask


def test_without_supervise_rendered_only_the_recorded_image_supervises(sim_case):
    """The loss then sees only pixels that came from the reference image: where the warp did
    not reach, the model's own render is not handed back to it as a target."""
    case = sim_case
    req = case.request
    full = GuidedRefiner(GuidedConfig(supervise_rendered=True)).refine(req)
    warped = GuidedRefiner().refine(req)  # the default
    assert np.array_equal(warped.image, full.image)  # the same picture, a smaller mask
    assert warped.mask.sum() < full.mask.sum() and not (warped.mask & ~full.mask).any()
    assert warped.mask.mean() > 0.5
    # every supervised pixel is the reference's colour at the truth's place: closer to the
    # truth than the render kept elsewhere
    kept = full.mask & ~warped.mask
    assert psnr(warped.image, case.truth, warped.mask) > psnr(full.image, case.truth, kept)


@pytest.mark.parametrize(
    "refiner",
    [
        GuidedRefiner(),
        GuidedRefiner(GuidedConfig(use_guided_filter=True, warp_weight=0.5)),
        IdentityRefiner(),
    ],
    ids=["guided", "guided-filter-blend", "none"],
)
def test_inputs_are_not_modified(refiner, sim_case):
    req = sim_case.request
    fields = {f.name: getattr(req, f.name) for f in dataclasses.fields(req)}
    copies = {k: v.copy() for k, v in fields.items() if isinstance(v, np.ndarray)}
    out = refiner.refine(req)
    for name, before in copies.items():
        np.testing.assert_array_equal(getattr(req, name), before, err_msg=name)
    assert not np.shares_memory(out.image, req.rendered)
    assert out.image.dtype == np.float32 and out.image.shape == req.rendered.shape
    assert out.image.min() >= 0.0 and out.image.max() <= 1.0
    assert out.mask.dtype == bool and out.mask.shape == req.rendered_alpha.shape


def test_the_identity_refiner_returns_the_render_and_its_confident_pixels(sim_case):
    req = sim_case.request
    out = IdentityRefiner().refine(req)
    np.testing.assert_array_equal(out.image, req.rendered)
    np.testing.assert_array_equal(out.mask, req.rendered_alpha > 0.5)


def test_a_request_with_mismatched_shapes_names_the_array():
    req, _ = _plane_request()
    bad = dataclasses.replace(req, rendered_depth_m=np.ones((H, W + 1), np.float32))
    with pytest.raises(ValueError, match="rendered_depth_m"):
        GuidedRefiner().refine(bad)


# ---- configuration -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("depth_tolerance", 0.0),
        ("min_alpha", 1.5),
        ("warp_weight", -0.1),
        ("inpaint_radius_px", 0),
        ("inpaint_scale", 2.0),
        ("guided_filter_radius_px", 100),
        ("guided_filter_eps", 0.0),
        ("seam_band_px", 0),
        ("use_inpaint", "yes"),
    ],
)
def test_config_errors_name_the_field_and_value(field, value):
    with pytest.raises(ReconstructConfigError) as info:
        GuidedConfig(**{field: value})
    assert f"GuidedConfig.{field}={value!r}" in str(info.value)
    assert isinstance(info.value, UserError) and isinstance(info.value, ValueError)


def test_describe_names_every_setting():
    text = GuidedRefiner(GuidedConfig(depth_tolerance=0.07)).describe()
    assert text.startswith("guided(") and "depth_tolerance=0.07" in text
    assert all(f.name in text for f in dataclasses.fields(GuidedConfig))


# ---- load_refiner ------------------------------------------------------------------------------


class EchoRefiner(Refiner):
    """A plug-in that needs weights; it remembers how it was made."""

    name = "echo"
    needs_weights = True

    def __init__(self, *, weights_path: Path | None, config: object | None) -> None:
        self.weights_path = weights_path
        self.config = config

    def refine(self, request: RefineRequest) -> Refined:
        return Refined(image=request.rendered.copy(), mask=request.rendered_alpha > 0)


class WeightlessRefiner(EchoRefiner):
    needs_weights = False


class NotARefiner:
    needs_weights = False

    def __init__(self, **kwargs: object) -> None:
        pass


def test_built_in_names():
    assert isinstance(load_refiner("guided"), GuidedRefiner)
    cfg = GuidedConfig(depth_tolerance=0.05)
    assert load_refiner("guided", config=cfg).config is cfg  # type: ignore[attr-defined]
    assert isinstance(load_refiner("none"), IdentityRefiner)
    assert available_refiners()[:3] == ["guided", "difix", "none"]
    with pytest.raises(ReconstructConfigError, match="GuidedConfig"):
        load_refiner("guided", config={"depth_tolerance": 0.05})


def test_an_unknown_name_lists_the_known_ones():
    with pytest.raises(RefinerNotFoundError) as info:
        load_refiner("nerf_magic")
    msg = str(info.value)
    assert "nerf_magic" in msg and ENTRY_POINT_GROUP in msg
    assert all(name in msg for name in ("guided", "difix", "none"))
    assert isinstance(info.value, LookupError) and isinstance(info.value, UserError)


def test_module_class_strings_load_a_plug_in(tmp_path):
    weights = tmp_path / "echo.bin"
    weights.write_bytes(b"w")
    r = load_refiner(f"{__name__}:EchoRefiner", weights, config="cfg")
    assert isinstance(r, EchoRefiner) and r.weights_path == weights and r.config == "cfg"
    assert isinstance(load_refiner(f"{__name__}:WeightlessRefiner"), WeightlessRefiner)
    with pytest.raises(RefinerNotFoundError, match="cannot be imported"):
        load_refiner("no_such_module_xyz:Thing")
    with pytest.raises(RefinerNotFoundError, match="not a Refiner"):
        load_refiner(f"{__name__}:NotARefiner")


def test_plug_in_weights_are_checked(tmp_path):
    with pytest.raises(RefinerWeightsError, match="needs a local weights path"):
        load_refiner(f"{__name__}:EchoRefiner")
    missing = tmp_path / "gone.bin"
    with pytest.raises(RefinerWeightsError) as info:
        load_refiner(f"{__name__}:EchoRefiner", missing)
    assert str(missing) in str(info.value) and "does not exist" in str(info.value)
    assert isinstance(info.value, FileNotFoundError)


def test_entry_points_are_found(tmp_path, monkeypatch):
    dist = tmp_path / "egosurg_refiner_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: egosurg-refiner-plugin\nVersion: 0.1\n"
    )
    (dist / "entry_points.txt").write_text(
        f"[{ENTRY_POINT_GROUP}]\n"
        f"weightless = {__name__}:WeightlessRefiner\n"
        "broken = no_such_module_xyz:Thing\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert {"weightless", "broken"} <= set(available_refiners())
    r = load_refiner("weightless", config=7)
    assert isinstance(r, WeightlessRefiner) and r.config == 7
    with pytest.raises(RefinerNotFoundError, match=r"broken.*failed to import"):
        load_refiner("broken")


def test_difix_needs_a_weights_folder_and_names_the_extra(tmp_path, monkeypatch):
    with pytest.raises(RefinerWeightsError, match="needs a local weights directory"):
        load_refiner("difix")
    with pytest.raises(RefinerWeightsError, match="does not exist"):
        load_refiner("difix", tmp_path / "nowhere")
    a_file = tmp_path / "difix.pkl"
    a_file.write_bytes(b"x")
    with pytest.raises(RefinerWeightsError, match="is a file"):
        load_refiner("difix", a_file)
    monkeypatch.setitem(sys.modules, "diffusers", None)  # as if the extra were not installed
    with pytest.raises(RefinerNotFoundError, match=r"pip install 'egosurg\[difix\]'"):
        load_refiner("difix", tmp_path)
