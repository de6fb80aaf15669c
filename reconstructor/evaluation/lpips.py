"""LPIPS (Zhang et al. 2018, v0.1), computed only when the user supplies the backbone's weights.

LPIPS compares two images through the features of an ImageNet network (AlexNet or VGG16): at
five ReLU layers the features are normalised to unit length along the channels, their squared
difference is weighted per channel by a learned linear head, averaged over the image and summed
over the layers. 0 means identical; larger means more different to a human eye.

Two sets of weights are needed:
- the backbone's ImageNet weights: no package ships them and there is no network, so the user
  passes a local file in torchvision's layout (``alexnet-owt-7be5be79.pth`` or
  ``vgg16-397923af.pth``: a state dict with ``features.N.weight`` / ``features.N.bias``);
  which network it is follows from its layers;
- the small linear heads, which the pip package ``lpips`` ships as ``lpips/weights/v0.1/*.pth``
  (``pip install --no-deps lpips``). Only those files are read: the package itself imports
  torchvision, which this project does not need; the backbones here are the same layers as
  torchvision's, under the same names.

Example::

    model = load_lpips("alexnet-owt-7be5be79.pth")
    d = model.distance(rendered, truth)        # (H, W, 3) float in [0, 1] or uint8
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
from torch import nn

from reconstructor.errors import LpipsNotInstalledError, LpipsWeightsError

NO_WEIGHTS = "n/a (no --lpips-weights)"

# torchvision's ``features`` layers, and the indices of the ReLUs LPIPS reads.
# AlexNet: (in, out, kernel, stride, padding) per conv, each followed by a ReLU; max-pools after
# convs 0, 1 and 4.
_ALEX_CONVS: tuple[tuple[int, int, int, int, int], ...] = (
    (3, 64, 11, 4, 2),
    (64, 192, 5, 1, 2),
    (192, 384, 3, 1, 1),
    (384, 256, 3, 1, 1),
    (256, 256, 3, 1, 1),
)
_ALEX_POOL_AFTER = (0, 1, 4)
_ALEX_TAPS = (1, 4, 7, 9, 11)
# VGG16: 3x3 convs with padding 1, each followed by a ReLU; 0 is a 2x2 max-pool
_VGG_CFG = (64, 64, 0, 128, 128, 0, 256, 256, 256, 0, 512, 512, 512, 0, 512, 512, 512, 0)
_VGG_TAPS = (3, 8, 15, 22, 29)
# the LPIPS input scaling (v0.1): inputs in [-1, 1] are shifted and scaled per channel
_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)


def _features(net: str) -> nn.Sequential:
    layers: list[nn.Module] = []
    if net == "alex":
        for i, (c_in, c_out, k, stride, pad) in enumerate(_ALEX_CONVS):
            layers += [nn.Conv2d(c_in, c_out, k, stride=stride, padding=pad), nn.ReLU()]
            if i in _ALEX_POOL_AFTER:
                layers.append(nn.MaxPool2d(kernel_size=3, stride=2))
        return nn.Sequential(*layers)
    c_in = 3
    for v in _VGG_CFG:
        if v == 0:
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(c_in, v, kernel_size=3, padding=1), nn.ReLU()]
            c_in = v
    return nn.Sequential(*layers)


def backbone_state_dict(net: str) -> dict[str, torch.Tensor]:
    """A randomly initialised backbone in torchvision's layout (``features.N.*``): for tests."""
    return {f"features.{k}": v for k, v in _features(net).state_dict().items()}


def _which_net(state: dict[str, torch.Tensor], path: Path) -> str:
    convs = {k for k in state if k.startswith("features.") and k.endswith(".weight")}
    if len(convs) == 5:
        return "alex"
    if len(convs) == 13:
        return "vgg"
    raise LpipsWeightsError(
        f"{path} holds {len(convs)} convolution layers under 'features.'; LPIPS needs "
        "torchvision's AlexNet (5) or VGG16 (13) weights, e.g. alexnet-owt-7be5be79.pth"
    )


def heads_path(net: str) -> Path:
    """The linear heads' weights inside the installed ``lpips`` package (not imported)."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        raise LpipsNotInstalledError(
            "LPIPS needs the linear heads shipped by the 'lpips' package: "
            "pip install --no-deps 'lpips>=0.1.4'"
        )
    path = Path(spec.origin).parent / "weights" / "v0.1" / f"{net}.pth"
    if not path.exists():
        raise LpipsNotInstalledError(f"the lpips package has no {path}; reinstall lpips>=0.1.4")
    return path


class Lpips(nn.Module):
    """LPIPS v0.1 with the given backbone and linear heads (no dropout: evaluation only)."""

    def __init__(self, net: str, backbone: dict[str, torch.Tensor], heads: dict[str, torch.Tensor]):
        super().__init__()
        self.net = net
        self.features = _features(net)
        self.features.load_state_dict(
            {
                k.removeprefix("features."): v
                for k, v in backbone.items()
                if k.startswith("features.")
            }
        )
        self.taps = _ALEX_TAPS if net == "alex" else _VGG_TAPS
        self.heads = [heads[f"lin{k}.model.1.weight"].float() for k in range(len(self.taps))]
        self.eval()
        self.requires_grad_(False)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """LPIPS of (N, 3, H, W) images in [-1, 1]: (N,)."""
        fa, fb = self._taps((a - _SHIFT) / _SCALE), self._taps((b - _SHIFT) / _SCALE)
        total = torch.zeros(a.shape[0])
        for x, y, w in zip(fa, fb, self.heads, strict=True):
            d = (_unit(x) - _unit(y)) ** 2
            total = total + torch.nn.functional.conv2d(d, w).mean(dim=(1, 2, 3))
        return total

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
            if i == self.taps[-1]:
                break
        return out

    def distance(self, a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
        """LPIPS of two (H, W, 3) images (float in [0, 1] or uint8); pixels outside ``mask``
        (H, W) are set to black in both, so they add no difference."""
        ta, tb = _to_input(a, mask), _to_input(b, mask)
        if ta.shape != tb.shape:
            raise ValueError(f"images differ in shape: {tuple(ta.shape)} vs {tuple(tb.shape)}")
        with torch.no_grad():
            return float(self(ta, tb)[0])


def _unit(x: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return x / (torch.sqrt((x * x).sum(dim=1, keepdim=True)) + eps)


def _to_input(image: np.ndarray, mask: np.ndarray | None) -> torch.Tensor:
    a = np.asarray(image)
    f = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
    if mask is not None:
        f = f * (np.asarray(mask) > 0.5)[..., None]
    return torch.from_numpy(np.ascontiguousarray(f * 2.0 - 1.0)).permute(2, 0, 1)[None]


def load_lpips(weights_path: str | Path) -> Lpips:
    """LPIPS with the backbone weights at ``weights_path`` (torchvision's AlexNet or VGG16)."""
    path = Path(weights_path)
    if not path.is_file():
        raise LpipsWeightsError(
            f"--lpips-weights {path} does not exist; pass torchvision's AlexNet or VGG16 "
            "ImageNet weights (e.g. alexnet-owt-7be5be79.pth), or leave the option out"
        )
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise LpipsWeightsError(f"{path} is not a readable torch weights file: {exc}") from None
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise LpipsWeightsError(f"{path} does not hold a state dict")
    net = _which_net(state, path)
    heads = torch.load(heads_path(net), map_location="cpu", weights_only=True)
    try:
        return Lpips(net, state, heads)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0]
        raise LpipsWeightsError(
            f"{path} does not fit torchvision's {net} layers: {first}"
        ) from None
