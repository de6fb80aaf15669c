"""A refiner's output, checked and turned into training tensors.

Shared by the shell of auxiliary views around each camera (auxiliary.py) and the views at
eye height (eye_views.py), so both hold a plug-in refiner to the same contract.
"""

from __future__ import annotations

import numpy as np
import torch

from reconstructor.data.views import View
from reconstructor.errors import ReconstructError
from reconstructor.refine.base import Refined, Refiner


class RefinerOutputError(ReconstructError, ValueError):
    """A refiner returned an image or mask of the wrong shape."""


def checked_refined(
    refined: Refined, view: View, refiner: Refiner
) -> tuple[torch.Tensor, torch.Tensor]:
    """The refined image and mask as training tensors; non-finite pixels leave the mask."""
    h, w = view.height_px, view.width_px
    image = np.asarray(refined.image, dtype=np.float32)
    mask = np.asarray(refined.mask)
    if image.shape != (h, w, 3) or mask.shape != (h, w):
        raise RefinerOutputError(
            f"refiner {refiner.describe()!r} returned an image {image.shape} and mask "
            f"{mask.shape} for a {w}x{h} view; it must return ({h}, {w}, 3) and ({h}, {w})"
        )
    finite = np.asarray(np.isfinite(image).all(axis=2), dtype=bool)
    image = np.clip(np.where(finite[..., None], image, 0.0), 0.0, 1.0).astype(np.float32)
    keep = (mask.astype(bool) & finite).astype(np.float32)
    return torch.from_numpy(image), torch.from_numpy(keep)
