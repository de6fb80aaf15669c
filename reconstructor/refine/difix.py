"""The Difix3D adapter: a single-step diffusion model that removes render artefacts.

Difix3D (Wu et al., "Difix3D+: Improving 3D Reconstructions with Single-Step Diffusion Models",
CVPR 2025) is SD-Turbo fine-tuned as an image-to-image model. One call, as implemented here:

1. pre-processing: both images (the render and the reference) are resized to the processing
   size (aspect kept, longest side at most ``max_side_px``, each side a multiple of the VAE's
   and the UNet's down-sampling, 64 for SD-Turbo) and scaled from [0, 1] to [-1, 1], RGB, NCHW;
2. the VAE encodes both (the latent mean times ``scaling_factor``; Difix samples the latent
   distribution, whose spread is negligible, so the mean keeps the adapter deterministic); the
   encoder's down-block inputs are kept as skip activations;
3. conditioning: the two latents are stacked as frames of one batch, ``(b v)`` with the render
   first (``stack_views``); in every transformer block of the UNet the self-attention takes the
   tokens of all frames of a sample together (``FrameAttnProcessor``), which is how the
   reference reaches the render. Cross-attention (the prompt) and the convolutions stay per
   frame;
4. one UNet step at timestep 199 (of 1000) on the clean latents, with the text embedding of the
   fixed prompt "remove degradation"; the scheduler's formula turns the prediction into the
   clean latent (``one_step_x0``; with DDPM and a single step this is exactly what
   ``scheduler.step`` returns);
5. the VAE decodes the render's frame only, adding ``skip_conv_i`` of the encoder's skip
   activations before each up block (Difix's encoder-decoder skip connections, gamma 1);
6. post-processing: [-1, 1] to [0, 1], resized back to the render's size.

Weights are a local directory in diffusers layout (never downloaded at run time)::

    weights/
      unet/config.json, diffusion_pytorch_model.safetensors
      vae/config.json, diffusion_pytorch_model.safetensors   # with decoder.skip_conv_{1..4}.*
      scheduler/scheduler_config.json
      text_encoder/ and tokenizer/        # or prompt_embeds.safetensors (write_prompt_embedding)

CPU only, float32. Needs the optional extra: ``pip install 'egosurg[difix]'``. See
docs/refiners.md for where the weights come from.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from reconstructor.errors import (
    ReconstructConfigError,
    RefinerNotFoundError,
    RefinerWeightsError,
)
from reconstructor.refine.base import Refined, Refiner, RefineRequest

log = logging.getLogger(__name__)

DEFAULT_PROMPT = "remove degradation"
DEFAULT_TIMESTEP = 199
PROMPT_EMBEDS_FILE = "prompt_embeds.safetensors"
PROMPT_EMBEDS_KEY = "prompt_embeds"
NUM_VIEWS = 2  # the render and its reference
INSTALL_HINT = "pip install 'egosurg[difix]'"


@dataclass(frozen=True, kw_only=True)
class DifixConfig:
    """Settings of ``DifixRefiner``. The defaults are Difix3D's."""

    prompt: str = DEFAULT_PROMPT
    timestep: int = DEFAULT_TIMESTEP  # of the scheduler's training steps (1000)
    max_side_px: int = 1024  # the longest side the model sees (CPU time grows with area)
    use_reference: bool = True  # False: the render alone (Difix without reference)
    mask_min_alpha: float = 0.0  # supervise where render alpha >= this; 0: every pixel

    def __post_init__(self) -> None:
        def bad(field: str, value: object, why: str) -> ReconstructConfigError:
            return ReconstructConfigError(f"DifixConfig.{field}={value!r}: {why}")

        if not self.prompt.strip():
            raise bad("prompt", self.prompt, "must not be empty")
        if not 0 <= self.timestep < 1000:
            raise bad("timestep", self.timestep, "must be in [0, 1000)")
        if not 64 <= self.max_side_px <= 4096:
            raise bad("max_side_px", self.max_side_px, "must be from 64 to 4096")
        if not isinstance(self.use_reference, bool):
            raise bad("use_reference", self.use_reference, "must be true or false")
        if not 0.0 <= self.mask_min_alpha <= 1.0:
            raise bad("mask_min_alpha", self.mask_min_alpha, "must be in [0, 1]")


# ---- pre- and post-processing ----------------------------------------------------------------


def processing_size(height: int, width: int, multiple: int, max_side_px: int) -> tuple[int, int]:
    """(height, width) the model sees: aspect kept, longest side <= ``max_side_px`` (unless one
    ``multiple`` is more), each side the nearest multiple of ``multiple`` (at least one)."""
    scale = min(1.0, max_side_px / max(height, width))
    return tuple(  # type: ignore[return-value]
        max(multiple, multiple * round(side * scale / multiple)) for side in (height, width)
    )


def preprocess(image: np.ndarray, size_hw: tuple[int, int]) -> torch.Tensor:
    """(H, W, 3) float RGB in [0, 1] -> (1, 3, h, w) float32 in [-1, 1] at ``size_hw``."""
    img = np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0)
    h, w = size_hw
    if img.shape[:2] != (h, w):
        shrink = h * w < img.shape[0] * img.shape[1]
        img = np.asarray(
            cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
        )
    t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None]
    return t.clamp(0.0, 1.0) * 2.0 - 1.0


def postprocess(image: torch.Tensor, size_hw: tuple[int, int]) -> np.ndarray:
    """(3, h, w) or (1, 3, h, w) model output in [-1, 1] -> (H, W, 3) float32 in [0, 1]."""
    t = image.detach().to(torch.float32)
    if t.ndim == 4:
        t = t[0]
    img = ((t.clamp(-1.0, 1.0) + 1.0) * 0.5).permute(1, 2, 0).cpu().numpy()
    h, w = size_hw
    if img.shape[:2] != (h, w):
        shrink = h * w < img.shape[0] * img.shape[1]
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


# ---- conditioning: the render and its reference as frames of one batch -------------------------


def stack_views(render: torch.Tensor, reference: torch.Tensor | None) -> torch.Tensor:
    """(B, C, h, w) render and reference -> (B * 2, C, h, w), frames ``(b v)``: for each sample
    the render, then its reference. Without a reference: the render alone (one frame)."""
    if reference is None:
        return render
    if reference.shape != render.shape:
        raise ValueError(f"reference {tuple(reference.shape)} != render {tuple(render.shape)}")
    return torch.stack([render, reference], dim=1).flatten(0, 1)


def render_frames(x: torch.Tensor, num_views: int) -> torch.Tensor:
    """(B * num_views, ...) frames ``(b v)`` -> (B, ...): each sample's first frame (the render)."""
    return x.unflatten(0, (-1, num_views))[:, 0]


class FrameAttnProcessor:
    """Self-attention across the ``num_views`` frames of each sample, as Difix's UNet does it.

    The transformer blocks see ``(b v, n, d)`` tokens; this processor regroups them to
    ``(b, v n, d)`` so every token attends to the tokens of all frames of its sample, runs
    diffusers' standard processor, and restores the frame layout. With one frame it is the
    standard processor.
    """

    def __init__(self, num_views: int) -> None:
        from diffusers.models.attention_processor import AttnProcessor2_0

        if num_views < 1:
            raise ValueError(f"num_views must be at least 1, got {num_views}")
        self.num_views = num_views
        self.inner = AttnProcessor2_0()

    def __call__(
        self,
        attn: Any,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor | None = None,
        attention_mask: torch.Tensor | None = None,
        temb: torch.Tensor | None = None,
        *args: Any,
        **kwargs: Any,
    ) -> torch.Tensor:
        v = self.num_views
        if encoder_hidden_states is not None or hidden_states.ndim != 3 or v == 1:
            return self.inner(attn, hidden_states, encoder_hidden_states, attention_mask, temb)
        bv, n, d = hidden_states.shape
        if bv % v:
            raise ValueError(f"a batch of {bv} frames is not a whole number of {v}-view samples")
        grouped = hidden_states.reshape(bv // v, v * n, d)
        out = self.inner(attn, grouped, None, attention_mask, temb)
        return out.reshape(bv, n, -1)


def set_frame_attention(unet: Any, num_views: int) -> int:
    """Give every self-attention (``attn1``) of ``unet`` a ``FrameAttnProcessor``; returns how
    many were replaced. Cross-attention keeps its processor."""
    processors = {}
    replaced = 0
    for name, proc in unet.attn_processors.items():
        if name.endswith("attn1.processor"):
            processors[name] = FrameAttnProcessor(num_views)
            replaced += 1
        else:
            processors[name] = proc
    unet.set_attn_processor(processors)
    return replaced


# ---- the model -------------------------------------------------------------------------------


def encode_with_skips(vae: Any, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Images (N, 3, h, w) in [-1, 1] -> (latents (N, c, h/f, w/f) times the VAE's scaling
    factor, the input of each encoder down block: Difix's skip activations)."""
    enc = vae.encoder
    h = enc.conv_in(x)
    skips = []
    for block in enc.down_blocks:
        skips.append(h)
        h = block(h)
    h = enc.mid_block(h)
    h = enc.conv_out(enc.conv_act(enc.conv_norm_out(h)))
    if getattr(vae, "quant_conv", None) is not None:
        h = vae.quant_conv(h)
    mean = h.chunk(2, dim=1)[0]  # the latent distribution's mean
    return mean * vae.config.scaling_factor, skips


def decode_with_skips(
    vae: Any,
    latents: torch.Tensor,
    skips: list[torch.Tensor] | None,
    skip_convs: torch.nn.ModuleList | None,
    gamma: float = 1.0,
) -> torch.Tensor:
    """Latents (times the scaling factor) -> images in [-1, 1], adding ``skip_convs[i]`` of the
    encoder's skip activations (deepest first) before up block ``i``. None: the plain VAE."""
    dec = vae.decoder
    z = latents / vae.config.scaling_factor
    if getattr(vae, "post_quant_conv", None) is not None:
        z = vae.post_quant_conv(z)
    h = dec.conv_in(z)
    h = dec.mid_block(h, None)
    use_skips = skips is not None and skip_convs is not None
    for i, block in enumerate(dec.up_blocks):
        if use_skips:
            assert skips is not None and skip_convs is not None
            h = h + skip_convs[i](skips[-1 - i] * gamma)
        h = block(h, None)
    h = dec.conv_out(dec.conv_act(dec.conv_norm_out(h)))
    return h.clamp(-1.0, 1.0)


def one_step_x0(
    latents: torch.Tensor, model_out: torch.Tensor, alpha_bar: float, prediction_type: str
) -> torch.Tensor:
    """The clean latent from one UNet prediction at a timestep with cumulative alpha
    ``alpha_bar`` (DDPM's ``pred_original_sample``; Difix feeds the UNet the clean latent)."""
    a = math.sqrt(alpha_bar)
    s = math.sqrt(1.0 - alpha_bar)
    if prediction_type == "epsilon":
        return (latents - s * model_out) / a
    if prediction_type == "v_prediction":
        return a * latents - s * model_out
    if prediction_type == "sample":
        return model_out
    raise ValueError(f"unknown scheduler prediction_type {prediction_type!r}")


@dataclass
class DifixModel:
    """The loaded networks and constants of one weights directory."""

    vae: Any
    unet: Any
    skip_convs: torch.nn.ModuleList | None
    prompt_embeds: torch.Tensor  # (1, tokens, dim)
    alphas_cumprod: torch.Tensor  # (num_train_timesteps,)
    prediction_type: str
    size_multiple: int  # VAE down-sampling times UNet down-sampling

    def run(
        self, render: torch.Tensor, reference: torch.Tensor | None, timestep: int
    ) -> torch.Tensor:
        """(B, 3, h, w) render (and reference) in [-1, 1] -> (B, 3, h, w) refined render."""
        views = NUM_VIEWS if reference is not None else 1
        x = stack_views(render, reference)
        for module in self.unet.attn_processors.values():
            if isinstance(module, FrameAttnProcessor):
                module.num_views = views
        latents, skips = encode_with_skips(self.vae, x)
        prompt = self.prompt_embeds.expand(x.shape[0], -1, -1)
        t = torch.full((x.shape[0],), timestep, dtype=torch.long)
        pred = self.unet(latents, t, encoder_hidden_states=prompt).sample
        alpha_bar = float(self.alphas_cumprod[timestep])
        clean = one_step_x0(latents, pred, alpha_bar, self.prediction_type)
        own = render_frames(clean, views)
        own_skips = [render_frames(s, views) for s in skips]
        return decode_with_skips(self.vae, own, own_skips, self.skip_convs)


REQUIRED_PARTS = {
    "unet": "the UNet (config.json and diffusion_pytorch_model.safetensors)",
    "vae": "the VAE with Difix's skip convolutions",
    "scheduler": "scheduler_config.json",
}


def check_weights_dir(weights_dir: Path) -> None:
    """Raise ``RefinerWeightsError`` naming each missing part of a diffusers-layout folder."""
    if not weights_dir.is_dir():
        raise RefinerWeightsError(
            f"Difix weights directory {weights_dir} does not exist or is not a directory; give "
            "the folder holding unet/, vae/ and scheduler/ (see docs/refiners.md)"
        )
    missing = [
        f"{part}/ ({what})"
        for part, what in REQUIRED_PARTS.items()
        if not (weights_dir / part).is_dir()
    ]
    has_text = (weights_dir / "text_encoder").is_dir() and (weights_dir / "tokenizer").is_dir()
    if not has_text and not (weights_dir / PROMPT_EMBEDS_FILE).is_file():
        missing.append(f"text_encoder/ and tokenizer/, or {PROMPT_EMBEDS_FILE}")
    if missing:
        raise RefinerWeightsError(
            f"Difix weights directory {weights_dir} lacks {'; '.join(missing)}. Copy the whole "
            "diffusers-format download (e.g. nvidia/difix_ref) there (see docs/refiners.md)"
        )


def _state_dict_file(part_dir: Path) -> Path | None:
    for name in ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin"):
        if (part_dir / name).is_file():
            return part_dir / name
    return None


def _read_state(path: Path) -> dict[str, torch.Tensor]:
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path))
    return torch.load(path, map_location="cpu", weights_only=True)


def load_skip_convs(vae_dir: Path, num_blocks: int) -> torch.nn.ModuleList | None:
    """Difix's ``decoder.skip_conv_{1..n}`` from the VAE's weights file, or None if it has none
    (a stock VAE: the adapter then decodes without skips, and warns)."""
    path = _state_dict_file(vae_dir)
    if path is None:
        raise RefinerWeightsError(
            f"{vae_dir} has no diffusion_pytorch_model.safetensors (or .bin); copy the VAE weights"
        )
    state = _read_state(path)
    lora = [k for k in state if "lora" in k.lower()]
    if lora:
        raise RefinerWeightsError(
            f"{path} holds unmerged LoRA weights ({lora[0]}, ...); this adapter needs them merged "
            "into the VAE (save the VAE once with the LoRA fused, see docs/refiners.md)"
        )
    convs = []
    for i in range(1, num_blocks + 1):
        w = state.get(f"decoder.skip_conv_{i}.weight")
        if w is None:
            break
        out_c, in_c, kh, kw = w.shape
        bias = state.get(f"decoder.skip_conv_{i}.bias")
        conv = torch.nn.Conv2d(
            in_c, out_c, (kh, kw), padding=(kh // 2, kw // 2), bias=bias is not None
        )
        with torch.no_grad():
            conv.weight.copy_(w)
            if bias is not None and conv.bias is not None:
                conv.bias.copy_(bias)
        convs.append(conv)
    if not convs:
        log.warning("%s has no decoder.skip_conv_* weights: decoding without Difix's skips", path)
        return None
    if len(convs) != num_blocks:
        raise RefinerWeightsError(
            f"{path} has {len(convs)} decoder skip convolutions for {num_blocks} decoder blocks; "
            "the weights do not belong to this VAE configuration"
        )
    return torch.nn.ModuleList(convs).eval()


def encode_prompt(weights_dir: Path, prompt: str) -> torch.Tensor:
    """(1, tokens, dim) text embedding of ``prompt``: from text_encoder/ and tokenizer/ if
    present, else from ``prompt_embeds.safetensors`` (which must be of the same prompt)."""
    if (weights_dir / "text_encoder").is_dir() and (weights_dir / "tokenizer").is_dir():
        from transformers import CLIPTextModel, CLIPTokenizer

        tokenizer = CLIPTokenizer.from_pretrained(weights_dir / "tokenizer", local_files_only=True)
        encoder = CLIPTextModel.from_pretrained(
            weights_dir / "text_encoder", local_files_only=True, torch_dtype=torch.float32
        ).eval()
        tokens = tokenizer(
            prompt,
            max_length=tokenizer.model_max_length,
            padding="max_length",
            truncation=True,
            return_tensors="pt",
        ).input_ids
        with torch.inference_mode():
            return encoder(tokens)[0].to(torch.float32).clone()
    from safetensors import safe_open

    path = weights_dir / PROMPT_EMBEDS_FILE
    with safe_open(str(path), framework="pt") as f:
        stored = (f.metadata() or {}).get("prompt")
        if stored is not None and stored != prompt:
            raise RefinerWeightsError(
                f"{path} embeds the prompt {stored!r}, not {prompt!r}; recompute it with "
                "write_prompt_embedding, or keep text_encoder/ and tokenizer/ in the folder"
            )
        if PROMPT_EMBEDS_KEY not in f.keys():  # safe_open has no __contains__
            raise RefinerWeightsError(f"{path} has no tensor {PROMPT_EMBEDS_KEY!r}")
        embeds = f.get_tensor(PROMPT_EMBEDS_KEY).to(torch.float32)
    return embeds if embeds.ndim == 3 else embeds[None]


def write_prompt_embedding(weights_dir: Path, prompt: str = DEFAULT_PROMPT) -> Path:
    """Save the prompt's embedding as ``prompt_embeds.safetensors`` in ``weights_dir`` (from its
    text_encoder/ and tokenizer/); afterwards those two folders (1.4 GB) may be deleted."""
    from safetensors.torch import save_file

    weights_dir = Path(weights_dir)
    if not ((weights_dir / "text_encoder").is_dir() and (weights_dir / "tokenizer").is_dir()):
        raise RefinerWeightsError(f"{weights_dir} needs text_encoder/ and tokenizer/ for this")
    embeds = encode_prompt(weights_dir, prompt)
    path = weights_dir / PROMPT_EMBEDS_FILE
    save_file({PROMPT_EMBEDS_KEY: embeds.contiguous()}, str(path), metadata={"prompt": prompt})
    return path


def load_difix(weights_dir: Path, prompt: str = DEFAULT_PROMPT) -> DifixModel:
    """Load a Difix model from a local diffusers-layout folder (module docstring), CPU float32."""
    weights_dir = Path(weights_dir).expanduser()
    check_weights_dir(weights_dir)
    try:
        from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
    except ImportError as exc:
        raise RefinerNotFoundError(
            f"the difix refiner needs the optional extra ({exc}): {INSTALL_HINT}"
        ) from None
    try:
        vae = AutoencoderKL.from_pretrained(
            weights_dir / "vae", local_files_only=True, torch_dtype=torch.float32
        ).eval()
        unet = UNet2DConditionModel.from_pretrained(
            weights_dir / "unet", local_files_only=True, torch_dtype=torch.float32
        ).eval()
        sched_file = weights_dir / "scheduler" / "scheduler_config.json"
        scheduler = DDPMScheduler.from_config(json.loads(sched_file.read_text()))
    except (OSError, ValueError, json.JSONDecodeError) as exc:
        raise RefinerWeightsError(
            f"Difix weights in {weights_dir} cannot be loaded ({exc}); the folder must be a "
            "complete diffusers-format copy (see docs/refiners.md)"
        ) from None
    skip_convs = load_skip_convs(weights_dir / "vae", len(vae.decoder.up_blocks))
    replaced = set_frame_attention(unet, NUM_VIEWS)
    if replaced == 0:
        raise RefinerWeightsError(
            f"the UNet in {weights_dir / 'unet'} has no self-attention blocks: not a Difix UNet"
        )
    vae_factor = 2 ** (len(vae.config.block_out_channels) - 1)
    unet_factor = 2 ** (len(unet.config.block_out_channels) - 1)
    return DifixModel(
        vae=vae.requires_grad_(False),
        unet=unet.requires_grad_(False),
        skip_convs=skip_convs.requires_grad_(False) if skip_convs is not None else None,
        prompt_embeds=encode_prompt(weights_dir, prompt),
        alphas_cumprod=scheduler.alphas_cumprod.to(torch.float64),
        prediction_type=str(scheduler.config.prediction_type),
        size_multiple=vae_factor * unet_factor,
    )


class DifixRefiner(Refiner):
    """The Difix3D adapter (module docstring), on the CPU in float32."""

    name = "difix"
    needs_weights = True

    def __init__(self, weights_dir: Path, config: DifixConfig | None = None) -> None:
        if config is not None and not isinstance(config, DifixConfig):
            raise ReconstructConfigError(
                f"the difix refiner takes a DifixConfig, got a {type(config).__name__}"
            )
        self.config = config if config is not None else DifixConfig()
        self.weights_dir = Path(weights_dir).expanduser()
        self.model = load_difix(self.weights_dir, self.config.prompt)
        if not self.config.timestep < len(self.model.alphas_cumprod):
            raise ReconstructConfigError(
                f"DifixConfig.timestep={self.config.timestep}: the scheduler has only "
                f"{len(self.model.alphas_cumprod)} steps"
            )
        log.info("difix refiner loaded from %s", self.weights_dir)

    def describe(self) -> str:
        fields = ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )
        return f"{self.name}({self.weights_dir.name}, {fields})"

    def refine(self, request: RefineRequest) -> Refined:
        cfg = self.config
        h, w = np.shape(request.rendered)[:2]
        size = processing_size(h, w, self.model.size_multiple, cfg.max_side_px)
        render = preprocess(request.rendered, size)
        reference = preprocess(request.reference, size) if cfg.use_reference else None
        with torch.inference_mode():
            out = self.model.run(render, reference, cfg.timestep)
        image = postprocess(out[0], (h, w))
        if cfg.mask_min_alpha > 0.0:
            mask = np.asarray(request.rendered_alpha) >= cfg.mask_min_alpha
        else:
            mask = np.ones((h, w), bool)
        return Refined(image=image, mask=mask)
