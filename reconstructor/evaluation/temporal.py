"""Temporal stability of rendered sequences: t-PSNR, t-SSIM and a flicker score.

The paper's temporal protocol reconstructs consecutive timestamps independently and renders each
from the same fixed camera; these scores compare each rendered frame with the next one and are
averaged over the adjacent pairs (nine for a ten-frame sequence).

- **t-PSNR** (dB, higher is steadier): PSNR between frames k and k + 1; identical frames give
  ``inf``.
- **t-SSIM** (higher is steadier): SSIM between frames k and k + 1 (``metrics.ssim_value``: the
  3DGS window, 11x11 Gaussian, sigma 1.5).
- **Flicker** (in [0, 1], lower is steadier). Per frame, the luminance
  ``Y = 0.299 R + 0.587 G + 0.114 B`` (Rec. 601, values in [0, 1]) is cut into 8x8 blocks (a
  partial block at the right or bottom edge is left out); each block has a mean ``mu`` (its
  brightness) and a standard deviation ``sigma`` (its local contrast, i.e. its structure). For
  one pair of frames::

      flicker = mean over blocks of ( |mu_k+1 - mu_k| + 2 |sigma_k+1 - sigma_k| ) / 2

  ``|Δmu|`` is at most 1 and ``|Δsigma|`` at most 0.5 (the largest standard deviation of values
  in [0, 1]), so each term is normalised to [0, 1] and so is their mean.

  Why blocks: what a viewer sees as flicker is a patch that brightens, darkens, gains or loses
  texture from one frame to the next (a splat popping in and out, a floater, a black hole that
  opens). Averaging over 8x8 pixels ignores per-pixel noise and sub-pixel jitter, which t-PSNR
  already punishes, and keeps the change of a patch's brightness and contrast. A person moving
  changes only the blocks they cover, so true scene motion raises the score far less than a
  frame-wide flicker does. 8x8 is the JPEG block size: about the smallest patch a viewer judges
  as a unit at the training resolution.

Images are (H, W, 3) arrays, float in [0, 1] or uint8 (scaled by 1/255).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from reconstructor.evaluation.metrics import ssim_value

BLOCK_PX = 8
_LUMA = np.array([0.299, 0.587, 0.114], np.float64)


def as_float_image(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float64 in [0, 1] from a uint8 or float image."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a.astype(np.float64) / 255.0
    return a.astype(np.float64)


def pair_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB between two frames (peak 1.0); ``inf`` when they are identical."""
    fa, fb = as_float_image(a), as_float_image(b)
    _same_shape(fa, fb)
    mse = float(np.mean((fa - fb) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def pair_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM between two frames (1.0 when identical)."""
    fa, fb = as_float_image(a), as_float_image(b)
    _same_shape(fa, fb)
    return ssim_value(fa.astype(np.float32), fb.astype(np.float32))


def block_stats(image: np.ndarray, block_px: int = BLOCK_PX) -> tuple[np.ndarray, np.ndarray]:
    """(mean, standard deviation) of the luminance of each block: two (H // b, W // b) arrays."""
    y = as_float_image(image) @ _LUMA
    h, w = (y.shape[0] // block_px) * block_px, (y.shape[1] // block_px) * block_px
    if h == 0 or w == 0:
        raise ValueError(f"an image of {y.shape[1]}x{y.shape[0]} px has no {block_px}-px block")
    blocks = y[:h, :w].reshape(h // block_px, block_px, w // block_px, block_px)
    mu = blocks.mean(axis=(1, 3))
    sigma = blocks.std(axis=(1, 3))
    return mu, sigma


def pair_flicker(a: np.ndarray, b: np.ndarray, block_px: int = BLOCK_PX) -> float:
    """The flicker score of one pair of frames (module docstring), in [0, 1]."""
    _same_shape(np.asarray(a), np.asarray(b))
    mu_a, sd_a = block_stats(a, block_px)
    mu_b, sd_b = block_stats(b, block_px)
    return float(np.mean(0.5 * np.abs(mu_b - mu_a) + np.abs(sd_b - sd_a)))


@dataclass(frozen=True)
class TemporalScores:
    """The three scores of one sequence, each averaged over its adjacent pairs."""

    t_psnr_db: float
    t_ssim: float
    flicker: float
    pairs: int


def temporal_scores(frames: Sequence[np.ndarray], block_px: int = BLOCK_PX) -> TemporalScores:
    """Scores of a sequence of at least two frames of one size."""
    if len(frames) < 2:
        raise ValueError(f"temporal scores need at least two frames, got {len(frames)}")
    p, s, f = [], [], []
    for a, b in itertools.pairwise(frames):
        p.append(pair_psnr(a, b))
        s.append(pair_ssim(a, b))
        f.append(pair_flicker(a, b, block_px))
    return TemporalScores(
        t_psnr_db=float(np.mean(p)),
        t_ssim=float(np.mean(s)),
        flicker=float(np.mean(f)),
        pairs=len(p),
    )


def _same_shape(a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape:
        raise ValueError(f"frames differ in shape: {a.shape} vs {b.shape}")
