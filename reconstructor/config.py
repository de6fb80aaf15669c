"""The reconstructor's configuration: the paper's defaults as fields of frozen dataclasses.

Every run saves its resolved configuration as ``config.toml`` next to its outputs; the same file
(or any part of it) can be passed back with ``--config`` to repeat or vary a run. Unknown keys and
bad values are refused with the key's dotted name.

Example ``--config`` file::

    train_views = "left"
    [train]
    warmup_steps = 100
    refine_steps = 200

The paper's baselines and ablation ("Baselines and Ablation") are switches of this config:

- EgoSurg: the defaults (stereo-depth init, auxiliary views refined by ``auxiliary.refiner``);
- "EgoSurg without diffusion": ``[auxiliary] enabled = false``;
- "image-only 3DGS": ``init_method = "random"`` and ``[auxiliary] enabled = false``
  (``random_init_count`` Gaussians uniform in ``room_bounds_m``, or in the box the cameras
  look into; stereo still runs, for ``points.ply`` and the depth-reprojection baseline);
- "depth reprojection": computed by ``--evaluate`` beside every run.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from protocol.toml_config import dumps, parse_toml, read_table
from reconstructor.depth.fill import FillConfig
from reconstructor.depth.fusion import FusionConfig
from reconstructor.depth.stereo_config import StereoConfig
from reconstructor.errors import ReconstructConfigError
from reconstructor.raster import RasterConfig
from reconstructor.refine.auxiliary import AuxiliaryConfig
from reconstructor.splats.gaussians import GaussianInitConfig
from reconstructor.splats.train import TrainConfig

CONFIG_FORMAT_VERSION = 1
# "left": the near-field protocol (the right cameras held out)
TrainViews = Literal["all", "left"]
# "random": the image-only 3DGS baseline
InitMethod = Literal["depth", "random"]
TRAIN_VIEWS: tuple[TrainViews, ...] = typing.get_args(TrainViews)
INIT_METHODS: tuple[InitMethod, ...] = typing.get_args(InitMethod)


@dataclass(frozen=True, kw_only=True)
class ReconstructConfig:
    stereo: StereoConfig | None = None  # None: the defaults (match scale by the session's width)
    stereo_matcher: str = "sgbm"  # or an installed plug-in (entry point egosurg.stereo_matchers)
    stereo_weights: str = ""  # local weights path for a learned matcher
    fill: FillConfig = field(default_factory=FillConfig)  # depth for blank walls and ceilings
    fusion: FusionConfig = field(default_factory=FusionConfig)
    init: GaussianInitConfig = field(default_factory=GaussianInitConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    raster: RasterConfig = field(default_factory=RasterConfig)
    train_views: TrainViews = "all"  # "left": the near-field protocol (right cameras held out)
    train_max_width_px: int = 960  # HD1200 images train at SVGA size, like the paper's GPU runs
    auxiliary: AuxiliaryConfig = field(default_factory=AuxiliaryConfig)
    init_method: InitMethod = "depth"  # "random": the image-only 3DGS baseline
    random_init_count: int = 100_000  # Gaussians of init_method = "random"
    # (xmin, ymin, zmin, xmax, ymax, zmax) in world metres, or empty when unknown: the random
    # init's box, and where auxiliary cameras must stay
    room_bounds_m: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.train_views not in TRAIN_VIEWS:
            raise ReconstructConfigError(
                f"train_views={self.train_views!r}: choose one of {', '.join(TRAIN_VIEWS)}"
            )
        if self.train_max_width_px < 64:
            raise ReconstructConfigError(
                f"train_max_width_px={self.train_max_width_px}: must be at least 64"
            )
        if self.init_method not in INIT_METHODS:
            raise ReconstructConfigError(
                f"init_method={self.init_method!r}: choose one of {', '.join(INIT_METHODS)}"
            )
        count = self.random_init_count
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ReconstructConfigError(f"random_init_count={count!r}: must be an integer >= 1")
        b = self.room_bounds_m
        if b:
            ok = len(b) == 6 and all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                for v in b
            )
            if not ok or not all(b[i] < b[i + 3] for i in range(3)):
                raise ReconstructConfigError(
                    f"room_bounds_m={list(b)!r}: give [xmin, ymin, zmin, xmax, ymax, zmax] in "
                    "metres with each min below its max, or [] when unknown"
                )
            object.__setattr__(self, "room_bounds_m", tuple(float(v) for v in b))

    @property
    def room_box_m(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``room_bounds_m`` as (lo (3,), hi (3,)), or None when unknown."""
        if not self.room_bounds_m:
            return None
        b = np.asarray(self.room_bounds_m, dtype=np.float64)
        return b[:3], b[3:]

    def resolved(self, width_px: int) -> ReconstructConfig:
        """Fill in what depends on the session (the stereo defaults for its resolution)."""
        stereo = self.stereo or StereoConfig()
        return dataclasses.replace(self, stereo=stereo.for_width(width_px))

    def to_toml(self) -> str:
        return dumps(
            self,
            comment=f"EgoSurg reconstruction config, format {CONFIG_FORMAT_VERSION}: the resolved "
            "settings of this run",
            head={"format_version": CONFIG_FORMAT_VERSION},
        )

    @classmethod
    def read(cls, path: Path | str) -> ReconstructConfig:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ReconstructConfigError(f"cannot read the config {p}: {exc.strerror}") from None
        return cls.from_toml(text, source=str(p))

    @classmethod
    def from_toml(cls, text: str, source: str = "<config>") -> ReconstructConfig:
        table = parse_toml(text, source, error=ReconstructConfigError)
        table.pop("format_version", None)
        return cls().overridden(table, source)

    def overridden(self, table: dict[str, Any], source: str) -> ReconstructConfig:
        """A copy with ``table``'s values (a config file or any part of it); unknown keys and bad
        values are refused naming ``source`` and the key's dotted name."""
        return read_table(ReconstructConfig, table, source, base=self, error=ReconstructConfigError)
