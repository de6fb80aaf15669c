"""The Refiner seam: what the refinement stage hands a refiner, and what it gets back.

After warm-up the refinement stage (``reconstructor/refine/auxiliary.py``) renders the current model
from auxiliary poses near each input camera. Such renders show the model's gaps: black holes
where no Gaussian reached, smears where few views constrained it. A refiner corrects one
render, given the nearest input (reference) image, and the corrected image supervises training
as an extra view.

Built-in refiners (``load_refiner`` names):
- ``"guided"``: reference-guided correction, no weights (``reconstructor/refine/guided.py``);
- ``"difix"``: the Difix3D adapter over diffusers, with a local weights directory
  (``reconstructor/refine/difix.py``; optional extra ``egosurg[difix]``);
- ``"none"``: returns the render unchanged (an ablation: self-supervision only).

A plug-in registers a factory in the entry-point group ``egosurg.refiners``; it is called as
``factory(weights_path=..., config=...)`` and returns a ``Refiner``.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from protocol.camera import Camera


@dataclass(frozen=True)
class RefineRequest:
    """One auxiliary render and its reference. Images are float32 RGB in [0, 1].

    Both cameras are ideal pinholes (no distortion) in the same world frame; poses are
    world-to-camera (OpenCV axes).
    """

    rendered: np.ndarray  # (H, W, 3): the current model seen from ``camera``
    rendered_alpha: np.ndarray  # (H, W): the render's accumulated opacity, 0 where empty
    rendered_depth_m: np.ndarray  # (H, W): camera-z depth of the render, 0 where alpha ~ 0
    camera: Camera  # the auxiliary camera
    reference: np.ndarray  # (Hr, Wr, 3): the recorded image of the nearest input view
    reference_mask: np.ndarray  # (Hr, Wr) bool: where ``reference`` holds image content
    reference_depth_m: np.ndarray  # (Hr, Wr): the model's depth rendered from the reference
    reference_camera: Camera


@dataclass(frozen=True)
class Refined:
    """The corrected view, and where it may supervise training."""

    image: np.ndarray  # (H, W, 3) float32 in [0, 1]
    mask: np.ndarray  # (H, W) bool: pixels the loss may use (False: leave them out)


class Refiner(abc.ABC):
    """Corrects auxiliary renders. Must not modify the arrays it is given."""

    name: ClassVar[str] = "refiner"
    needs_weights: ClassVar[bool] = False

    @abc.abstractmethod
    def refine(self, request: RefineRequest) -> Refined: ...

    def describe(self) -> str:
        """One line naming the refiner and its settings, for logs and evaluation tables."""
        return self.name


class IdentityRefiner(Refiner):
    """The ``"none"`` refiner: the render unchanged, supervised where it is confident.

    An ablation (the auxiliary views then only repeat what the model already renders).
    """

    name = "none"
    needs_weights = False

    def __init__(self, min_alpha: float = 0.5) -> None:
        self.min_alpha = min_alpha

    def refine(self, request: RefineRequest) -> Refined:
        image = np.array(request.rendered, dtype=np.float32, copy=True)
        mask = np.asarray(request.rendered_alpha) > self.min_alpha
        return Refined(image=image, mask=mask)
