"""The Difix3D adapter on a tiny, randomly initialised model of the same architecture, built
offline in the test and saved in the diffusers layout the adapter loads."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

import torch
from safetensors.torch import load_file, save_file

from protocol.camera import Camera, Intrinsics, Pose
from reconstructor.errors import ReconstructConfigError, RefinerWeightsError
from reconstructor.refine.base import RefineRequest
from reconstructor.refine.difix import (
    PROMPT_EMBEDS_FILE,
    DifixConfig,
    DifixRefiner,
    FrameAttnProcessor,
    decode_with_skips,
    encode_with_skips,
    load_difix,
    one_step_x0,
    postprocess,
    preprocess,
    processing_size,
    render_frames,
    stack_views,
    write_prompt_embedding,
)
from reconstructor.refine.refiners import load_refiner

VAE_CHANNELS = (8, 16)
UNET_CHANNELS = (16, 32)
TEXT_DIM = 16
PROMPT = "remove degradation"


def _tiny_vae(seed: int):
    from diffusers import AutoencoderKL

    torch.manual_seed(seed)
    return AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * len(VAE_CHANNELS),
        up_block_types=("UpDecoderBlock2D",) * len(VAE_CHANNELS),
        block_out_channels=VAE_CHANNELS,
        layers_per_block=1,
        latent_channels=4,
        norm_num_groups=4,
        sample_size=32,
    )


def _skip_conv_shapes() -> list[tuple[int, int]]:
    """(in, out) channels of skip_conv_1..n: deepest encoder down-block input -> first decoder
    up-block input, and so on (worked out from the block channels, not from the adapter)."""
    enc_in = [VAE_CHANNELS[0], *VAE_CHANNELS[:-1]]  # conv_in output, then each block's output
    rev = list(reversed(VAE_CHANNELS))
    dec_in = [rev[0], *rev[:-1]]
    return [(enc_in[-1 - i], dec_in[i]) for i in range(len(VAE_CHANNELS))]


def _tiny_unet(seed: int):
    from diffusers import UNet2DConditionModel

    torch.manual_seed(seed)
    return UNet2DConditionModel(
        sample_size=16,
        in_channels=4,
        out_channels=4,
        layers_per_block=1,
        block_out_channels=UNET_CHANNELS,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=TEXT_DIM,
        attention_head_dim=4,
        norm_num_groups=4,
    )


def _write_tokenizer(path: Path) -> None:
    """A CLIP BPE tokenizer with a character vocabulary: no merges, no download."""
    from transformers import CLIPTokenizer

    path.mkdir(parents=True)
    chars = "abcdefghijklmnopqrstuvwxyz"
    tokens = ["<|startoftext|>", "<|endoftext|>", *chars, *(c + "</w>" for c in chars)]
    (path / "vocab.json").write_text(json.dumps({t: i for i, t in enumerate(tokens)}))
    (path / "merges.txt").write_text("#version: 0.2\n")
    tok = CLIPTokenizer(str(path / "vocab.json"), str(path / "merges.txt"), model_max_length=16)
    tok.save_pretrained(path)


def _write_text_encoder(path: Path) -> None:
    from transformers import CLIPTextConfig, CLIPTextModel

    torch.manual_seed(3)
    cfg = CLIPTextConfig(
        vocab_size=54,
        hidden_size=TEXT_DIM,
        intermediate_size=32,
        num_hidden_layers=1,
        num_attention_heads=2,
        max_position_embeddings=16,
        bos_token_id=0,
        eos_token_id=1,
        pad_token_id=1,
    )
    CLIPTextModel(cfg).save_pretrained(path)


def build_weights(root: Path, *, text: str = "encoder", skips: bool = True) -> Path:
    """A tiny Difix folder: vae/ (with skip convs), unet/, scheduler/, and the prompt as a text
    encoder + tokenizer (``text="encoder"``) or a saved embedding (``text="embeds"``)."""
    from diffusers import DDPMScheduler

    root.mkdir(parents=True, exist_ok=True)
    _tiny_vae(1).save_pretrained(root / "vae", safe_serialization=True)
    if skips:
        state_path = root / "vae" / "diffusion_pytorch_model.safetensors"
        state = load_file(str(state_path))
        gen = torch.Generator().manual_seed(2)
        for i, (c_in, c_out) in enumerate(_skip_conv_shapes(), start=1):
            state[f"decoder.skip_conv_{i}.weight"] = 0.1 * torch.randn(
                c_out, c_in, 1, 1, generator=gen
            )
        save_file(state, str(state_path))
    _tiny_unet(4).save_pretrained(root / "unet", safe_serialization=True)
    scheduler: Any = DDPMScheduler(
        beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012, clip_sample=False
    )
    scheduler.save_pretrained(root / "scheduler")
    if text == "encoder":
        _write_tokenizer(root / "tokenizer")
        _write_text_encoder(root / "text_encoder")
    else:
        gen = torch.Generator().manual_seed(5)
        save_file(
            {"prompt_embeds": torch.randn(1, 16, TEXT_DIM, generator=gen)},
            str(root / PROMPT_EMBEDS_FILE),
            metadata={"prompt": PROMPT},
        )
    return root


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Tiny models: threads only add start-up cost and fight the other jobs for the 2 cores."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_weights(tmp_path_factory.mktemp("difix") / "weights")


@pytest.fixture(scope="module")
def refiner(weights: Path) -> DifixRefiner:
    return DifixRefiner(weights)


def _images(seed: int, h: int = 32, w: int = 32) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.random((-(-h // 8), -(-w // 8), 3)).astype(np.float32)
    blocky = np.kron(base, np.ones((8, 8, 1), np.float32))  # survives resizing
    return np.ascontiguousarray(blocky[:h, :w])


def _request(render: np.ndarray, reference: np.ndarray) -> RefineRequest:
    h, w = render.shape[:2]
    intr = Intrinsics.from_fov(w, h, 60.0)
    cam = Camera(name="aux", intrinsics=intr, pose=Pose(R=np.eye(3)))
    alpha = np.ones((h, w), np.float32)
    alpha[:8] = 0.2
    return RefineRequest(
        rendered=render,
        rendered_alpha=alpha,
        rendered_depth_m=np.full((h, w), 2.0, np.float32),
        camera=cam,
        reference=reference,
        reference_mask=np.ones(reference.shape[:2], bool),
        reference_depth_m=np.full(reference.shape[:2], 2.0, np.float32),
        reference_camera=cam,
    )


# ---- pre- and post-processing ----------------------------------------------------------------


def test_processing_size_keeps_aspect_caps_the_side_and_rounds_to_the_multiple():
    assert processing_size(600, 960, 64, 1024) == (576, 960)
    assert processing_size(1200, 1920, 64, 1024) == (640, 1024)
    assert processing_size(64, 64, 4, 1024) == (64, 64)
    assert processing_size(10, 700, 64, 1024) == (64, 704)  # never below one multiple


def test_preprocess_gives_nchw_in_minus_one_to_one_and_keeps_rgb_order():
    img = np.zeros((40, 48, 3), np.float32)
    img[..., 0] = 1.0  # pure red
    img[..., 2] = 0.25
    t = preprocess(img, (32, 64))
    assert t.shape == (1, 3, 32, 64) and t.dtype == torch.float32
    assert torch.allclose(t[0, 0], torch.ones(32, 64))
    assert torch.allclose(t[0, 1], -torch.ones(32, 64))
    assert torch.allclose(t[0, 2], torch.full((32, 64), -0.5))
    wild = preprocess(np.full((8, 8, 3), 7.0, np.float32), (8, 8))
    assert float(wild.max()) == 1.0  # out-of-range inputs are clipped


def test_postprocess_inverts_preprocess_and_restores_the_size():
    img = _images(0, 48, 80)
    same = postprocess(preprocess(img, (48, 80)), (48, 80))
    np.testing.assert_allclose(same, img, atol=1e-6)
    back = postprocess(preprocess(img, (64, 128)), (48, 80))
    assert back.shape == (48, 80, 3) and back.dtype == np.float32
    assert back.min() >= 0.0 and back.max() <= 1.0
    assert np.abs(back - img).mean() < 0.05  # blocky content survives the round trip
    over = postprocess(torch.full((3, 8, 8), 3.0), (16, 16))
    assert over.shape == (16, 16, 3) and over.max() == 1.0


# ---- conditioning ------------------------------------------------------------------------------


def test_stack_views_interleaves_render_then_reference_per_sample():
    render = torch.arange(2).float().view(2, 1, 1, 1).expand(2, 3, 4, 4)
    reference = 10 + render
    x = stack_views(render, reference)
    assert x.shape == (4, 3, 4, 4)
    assert [float(v) for v in x[:, 0, 0, 0]] == [0.0, 10.0, 1.0, 11.0]
    assert torch.equal(render_frames(x, 2), render)
    assert stack_views(render, None) is render


def test_frame_attention_with_one_view_is_the_standard_attention():
    from diffusers.models.attention_processor import Attention, AttnProcessor2_0

    torch.manual_seed(0)
    attn = Attention(query_dim=8, heads=2, dim_head=4)
    x = torch.randn(4, 5, 8)
    standard = AttnProcessor2_0()(attn, x)
    torch.testing.assert_close(FrameAttnProcessor(1)(attn, x), standard)


def test_frame_attention_mixes_frames_of_a_sample_and_only_of_that_sample():
    from diffusers.models.attention_processor import Attention, AttnProcessor2_0

    torch.manual_seed(0)
    attn = Attention(query_dim=8, heads=2, dim_head=4)
    x = torch.randn(4, 5, 8)  # two samples of two frames
    out = FrameAttnProcessor(2)(attn, x)
    # the slow twin: concatenate each sample's frames along the tokens, attend, split
    for b in range(2):
        joint = x[2 * b : 2 * b + 2].reshape(1, 10, 8)
        want = AttnProcessor2_0()(attn, joint).reshape(2, 5, 8)
        torch.testing.assert_close(out[2 * b : 2 * b + 2], want)
    changed = x.clone()
    changed[1] += 1.0  # the first sample's reference
    out2 = FrameAttnProcessor(2)(attn, changed)
    assert not torch.allclose(out2[0], out[0])  # the render sees its reference
    torch.testing.assert_close(out2[2:], out[2:])  # the other sample does not


def test_one_step_x0_inverts_the_forward_noising():
    torch.manual_seed(0)
    x0 = torch.randn(2, 4, 3, 3)
    eps = torch.randn_like(x0)
    ab = 0.7
    xt = ab**0.5 * x0 + (1 - ab) ** 0.5 * eps
    torch.testing.assert_close(one_step_x0(xt, eps, ab, "epsilon"), x0)
    v = ab**0.5 * eps - (1 - ab) ** 0.5 * x0
    torch.testing.assert_close(one_step_x0(xt, v, ab, "v_prediction"), x0)
    with pytest.raises(ValueError, match="prediction_type"):
        one_step_x0(xt, eps, ab, "flow")


def test_skip_connections_change_the_decoded_image():
    vae = _tiny_vae(1).eval()
    x = preprocess(_images(1), (32, 32))
    with torch.no_grad():
        latents, skips = encode_with_skips(vae, x)
        plain = decode_with_skips(vae, latents, None, None)
        ref = vae.decode(latents / vae.config.scaling_factor).sample.clamp(-1, 1)
        convs = torch.nn.ModuleList(
            torch.nn.Conv2d(i, o, 1, bias=False) for i, o in _skip_conv_shapes()
        )
        with_skips = decode_with_skips(vae, latents, skips, convs)
    assert latents.shape == (1, 4, 16, 16)
    torch.testing.assert_close(plain, ref)  # without skips: the stock VAE decoder
    assert not torch.allclose(with_skips, plain)


# ---- the refiner -------------------------------------------------------------------------------


def test_refine_returns_the_render_size_in_range_and_leaves_inputs_alone(refiner):
    render, reference = _images(1, 30, 36), _images(2, 40, 48)  # a larger reference
    request = _request(render, reference)
    before = [a.copy() for a in (render, reference, request.rendered_alpha)]
    out = refiner.refine(request)
    assert out.image.shape == (30, 36, 3) and out.image.dtype == np.float32
    assert out.image.min() >= 0.0 and out.image.max() <= 1.0
    assert out.mask.shape == (30, 36) and out.mask.dtype == bool and out.mask.all()
    for a, b in zip(before, (render, reference, request.rendered_alpha), strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_reference_changes_the_output(refiner, weights):
    render = _images(1)
    a = refiner.refine(_request(render, _images(2))).image
    b = refiner.refine(_request(render, _images(3))).image
    again = refiner.refine(_request(render, _images(2))).image
    np.testing.assert_array_equal(a, again)  # deterministic
    assert np.abs(a - b).max() > 1e-4
    alone = DifixRefiner(weights, DifixConfig(use_reference=False)).refine(
        _request(render, _images(2))
    )
    assert np.abs(alone.image - a).max() > 1e-4


def test_frames_are_exchangeable_so_the_render_is_frame_zero(refiner):
    """Swapping render and reference swaps the outputs: each frame's result is its own."""
    model = refiner.model
    a = preprocess(_images(1), (32, 32))
    b = preprocess(_images(2), (32, 32))
    with torch.no_grad():
        ab = model.run(a, b, 199)
        ba = model.run(b, a, 199)
        # the same pair in a batch of two samples, in both orders, gives the same results
        both = model.run(torch.cat([a, b]), torch.cat([b, a]), 199)
    torch.testing.assert_close(both[0:1], ab, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(both[1:2], ba, atol=1e-5, rtol=1e-4)
    assert not torch.allclose(ab, ba)


def test_mask_min_alpha_leaves_out_unconfident_pixels(weights):
    r = DifixRefiner(weights, DifixConfig(mask_min_alpha=0.5))
    out = r.refine(_request(_images(1), _images(2)))
    assert not out.mask[:8].any() and out.mask[8:].all()


def test_saved_prompt_embedding_replaces_the_text_encoder(tmp_path, weights):
    path = write_prompt_embedding(weights, PROMPT)
    slim = build_weights(tmp_path / "slim", text="embeds")
    (slim / PROMPT_EMBEDS_FILE).unlink()
    (slim / PROMPT_EMBEDS_FILE).write_bytes(path.read_bytes())
    for sub in ("vae", "unet"):  # the same networks as the full folder
        for f in (weights / sub).iterdir():
            (slim / sub / f.name).write_bytes(f.read_bytes())
    full = load_difix(weights, PROMPT)
    lean = load_difix(slim, PROMPT)
    torch.testing.assert_close(lean.prompt_embeds, full.prompt_embeds)
    with pytest.raises(RefinerWeightsError, match="embeds the prompt"):
        load_difix(slim, "another prompt")
    path.unlink()


def test_load_refiner_difix_uses_the_local_folder(weights):
    r = load_refiner("difix", weights, config=DifixConfig(max_side_px=64))
    assert isinstance(r, DifixRefiner) and "max_side_px=64" in r.describe()
    with pytest.raises(ReconstructConfigError, match="DifixConfig"):
        load_refiner("difix", weights, config=object())


# ---- loading errors ----------------------------------------------------------------------------


@pytest.mark.parametrize("part", ["unet", "vae", "scheduler"])
def test_a_missing_part_is_named(tmp_path, weights, part):
    broken = tmp_path / "w"
    broken.mkdir()
    for sub in ("unet", "vae", "scheduler", "tokenizer", "text_encoder"):
        if sub != part:
            (broken / sub).symlink_to(weights / sub)
    with pytest.raises(RefinerWeightsError, match=rf"{part}/") as info:
        DifixRefiner(broken)
    assert str(broken) in str(info.value)


def test_missing_text_parts_and_missing_folder_are_named(tmp_path, weights):
    broken = tmp_path / "w"
    broken.mkdir()
    for sub in ("unet", "vae", "scheduler"):
        (broken / sub).symlink_to(weights / sub)
    with pytest.raises(RefinerWeightsError, match=PROMPT_EMBEDS_FILE):
        DifixRefiner(broken)
    with pytest.raises(RefinerWeightsError, match="does not exist"):
        DifixRefiner(tmp_path / "nowhere")
    with pytest.raises(RefinerWeightsError, match="needs a local weights directory"):
        load_refiner("difix")


def test_a_vae_without_skip_weights_still_loads_and_unmerged_lora_is_refused(tmp_path):
    plain = build_weights(tmp_path / "plain", text="embeds", skips=False)
    assert load_difix(plain).skip_convs is None
    state_path = plain / "vae" / "diffusion_pytorch_model.safetensors"
    state = load_file(str(state_path))
    state["decoder.conv_out.lora_A.vae_skip.weight"] = torch.zeros(4, 16, 3, 3)
    save_file(state, str(state_path))
    with pytest.raises(RefinerWeightsError, match="LoRA"):
        load_difix(plain)


def test_config_is_validated():
    with pytest.raises(ReconstructConfigError, match="timestep=1000"):
        DifixConfig(timestep=1000)
    with pytest.raises(ReconstructConfigError, match="max_side_px=10"):
        DifixConfig(max_side_px=10)
    with pytest.raises(ReconstructConfigError, match="mask_min_alpha=2"):
        DifixConfig(mask_min_alpha=2)
