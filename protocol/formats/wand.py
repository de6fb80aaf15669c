"""The calibration wand: three spheres on a rod, described by ``wand.toml``.

Example ``wand.toml``::

    # EgoSurg calibration wand, format 1
    format_version = 1
    sphere_diameter_mm = 40.0
    # distance of each sphere centre from the first one, along the rod
    sphere_positions_mm = [0.0, 150.0, 450.0]

Spacing must be unequal (here 1:2) so the ends can be told apart in an image.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from protocol.errors import UserError
from protocol.toml_config import load_toml, read_table

WAND_FORMAT_VERSION = 1


class WandSpecError(UserError, ValueError):
    """A wand description that cannot be used."""


@dataclass(frozen=True, kw_only=True)
class WandSpec:
    sphere_diameter_mm: float = 40.0
    sphere_positions_mm: tuple[float, float, float] = (0.0, 150.0, 450.0)

    def __post_init__(self) -> None:
        pos = tuple(float(p) for p in self.sphere_positions_mm)
        if len(pos) != 3:
            raise WandSpecError(f"sphere_positions_mm needs 3 values, got {len(pos)}")
        if not (pos[0] < pos[1] < pos[2]):
            raise WandSpecError(f"sphere_positions_mm {list(pos)} must increase along the rod")
        if not 5.0 <= self.sphere_diameter_mm <= 200.0:
            raise WandSpecError(
                f"sphere_diameter_mm={self.sphere_diameter_mm} is not a plausible sphere size"
            )
        d1, d2 = pos[1] - pos[0], pos[2] - pos[1]
        if min(d1, d2) < 1.5 * self.sphere_diameter_mm:
            raise WandSpecError("spheres overlap or touch: space them further apart")
        if abs(d1 - d2) / max(d1, d2) < 0.2:
            raise WandSpecError(
                f"sphere spacings {d1:g} mm and {d2:g} mm are too similar to tell the ends apart; "
                "use unequal spacing such as 1:2"
            )
        object.__setattr__(self, "sphere_positions_mm", pos)

    @property
    def radius_m(self) -> float:
        return self.sphere_diameter_mm / 2000.0

    @property
    def distances_mm(self) -> tuple[float, float, float]:
        """Centre distances: (first-middle, middle-last, first-last)."""
        a, b, c = self.sphere_positions_mm
        return (b - a, c - b, c - a)

    def to_toml(self) -> str:
        pos = ", ".join(f"{p:g}" for p in self.sphere_positions_mm)
        return (
            f"# EgoSurg calibration wand, format {WAND_FORMAT_VERSION}\n"
            f"format_version = {WAND_FORMAT_VERSION}\n"
            f"sphere_diameter_mm = {self.sphere_diameter_mm:g}\n"
            "# distance of each sphere centre from the first one, along the rod\n"
            f"sphere_positions_mm = [{pos}]\n"
        )

    @classmethod
    def read(cls, path: Path | str) -> WandSpec:
        p = Path(path)
        if not p.exists():
            raise WandSpecError(f"{p}: no such wand file; 'egosurg sim wand-file' writes one")
        data, _ = load_toml(p, "the wand file", error=WandSpecError)
        version = data.get("format_version", WAND_FORMAT_VERSION)
        if version != WAND_FORMAT_VERSION:
            raise WandSpecError(f"{p}: wand format_version {version} is not supported (want 1)")
        wand = read_table(_WandFile, data, str(p), error=WandSpecError)
        return cls(
            sphere_diameter_mm=wand.sphere_diameter_mm,
            sphere_positions_mm=wand.sphere_positions_mm,
        )


@dataclass(frozen=True, kw_only=True)
class _WandFile:
    """What a wand.toml must hold: no default, since a wrong size scales every calibration."""

    format_version: int = WAND_FORMAT_VERSION
    sphere_diameter_mm: float
    sphere_positions_mm: tuple[float, float, float]
