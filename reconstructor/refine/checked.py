"""A refiner's request, and its output checked and turned into training tensors.

Shared by the shell of auxiliary views around each camera (auxiliary.py) and the views at
eye height (eye_views.py), so both hold a plug-in refiner to the same contract.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from protocol.camera import Pose
from reconstructor.data.views import View
from reconstructor.errors import RefinerOutputError
from reconstructor.raster import RenderOutput
from reconstructor.refine.base import Refined, Refiner, RefineRequest


def unrecorded_view(base: View, name: str, pose: Pose) -> View:
    """``base``'s camera moved to ``pose`` (world-to-camera), with no image or mask yet: the
    refiner's output becomes them."""
    return dataclasses.replace(
        base,
        name=name,
        image=torch.zeros(0, 0, 3),
        mask=torch.zeros(0, 0),
        viewmat=torch.from_numpy(pose.matrix.astype(np.float32)),
    )


def refine_request(
    render: RenderOutput,
    rendered: np.ndarray,
    view: View,
    reference: View,
    reference_depth_m: np.ndarray,
) -> RefineRequest:
    """The refiner's input: ``render`` of ``view`` (its image clamped to [0, 1] as ``rendered``)
    against the recorded ``reference`` view and the model's depth seen from it."""
    return RefineRequest(
        rendered=rendered,
        rendered_alpha=render.alpha.numpy(),
        rendered_depth_m=render.depth_m.numpy(),
        camera=view.camera,
        reference=reference.image.numpy(),
        reference_mask=reference.mask.numpy() > 0.5,
        reference_depth_m=reference_depth_m,
        reference_camera=reference.camera,
    )


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
