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
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

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
    stereo: StereoConfig | None = None  # None: the defaults for the session's resolution
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
        if self.stereo is not None:
            return self
        return dataclasses.replace(self, stereo=StereoConfig.for_resolution(width_px))

    def to_toml(self) -> str:
        head = (
            f"# EgoSurg reconstruction config, format {CONFIG_FORMAT_VERSION}: the resolved "
            "settings of this run\n"
            f"format_version = {CONFIG_FORMAT_VERSION}\n"
        )
        return head + dataclass_to_toml(self)

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
        try:
            table = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ReconstructConfigError(f"{source} is not valid TOML: {exc}") from None
        table.pop("format_version", None)
        return apply_overrides(cls(), table, source)


def dataclass_to_toml(obj: Any, prefix: str = "") -> str:
    """Scalars first, then one ``[table]`` per nested dataclass (None values are left out)."""
    scalars, tables = [], []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            tables.append((f.name, value))
        elif value is not None:
            scalars.append(f"{f.name} = {_toml_value(value)}")
    out = "\n".join(scalars) + ("\n" if scalars else "")
    for name, value in tables:
        full = f"{prefix}{name}"
        out += f"\n[{full}]\n" + dataclass_to_toml(value, prefix=f"{full}.")
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, tuple | list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def apply_overrides(obj: Any, table: dict[str, Any], source: str, prefix: str = "") -> Any:
    """A copy of the dataclass ``obj`` with ``table``'s values, validated by its constructor."""
    hints = typing.get_type_hints(type(obj))
    fields = {f.name: f for f in dataclasses.fields(obj)}
    changes: dict[str, Any] = {}
    for key, value in table.items():
        name = f"{prefix}{key}"
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ReconstructConfigError(f"{source}: unknown key {name!r}; known keys: {known}")
        current = getattr(obj, key)
        nested = current if dataclasses.is_dataclass(current) else _dataclass_type(hints[key])
        if nested is not None:
            if not isinstance(value, dict):
                raise ReconstructConfigError(f"{source}: {name} must be a table [{name}]")
            base = current if dataclasses.is_dataclass(current) else nested()  # type: ignore[operator]
            changes[key] = apply_overrides(base, value, source, prefix=f"{name}.")
        else:
            changes[key] = _coerce(value, current, name, source)
    try:
        return dataclasses.replace(obj, **changes)
    except ReconstructConfigError as exc:
        raise ReconstructConfigError(f"{source}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise ReconstructConfigError(f"{source}: {prefix or 'config'}: {exc}") from None


def _dataclass_type(hint: Any) -> Any:
    args = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
    for a in args:
        if dataclasses.is_dataclass(a):
            return a
    return None


def _coerce(value: Any, current: Any, name: str, source: str) -> Any:
    if isinstance(current, bool) and not isinstance(value, bool):
        raise ReconstructConfigError(f"{source}: {name} must be true or false, got {value!r}")
    if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(current, tuple) and isinstance(value, list):
        return tuple(value)
    if current is not None and not isinstance(value, type(current)):
        raise ReconstructConfigError(
            f"{source}: {name} must be a {type(current).__name__}, got {value!r}"
        )
    return value
