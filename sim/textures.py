"""Procedural, deterministic, tileable textures.

Every texture is an (N, N, 3) float32 albedo image in [0, 1] that tiles seamlessly, so surfaces
can be mapped by wrapping coordinates. Noise is made in the frequency domain (random phases under a
power-law envelope), which is periodic by construction and band-limited, so it does not alias when
a surface is seen from across the room. Some textures (walls, ceiling) are deliberately weak, like
painted walls, so stereo matching meets the same low-texture regions it meets on real footage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEXTURE_SIZE_PX = 512


@dataclass(frozen=True)
class Texture:
    """An albedo image and the size of one texel on the surface, in metres."""

    name: str
    albedo: np.ndarray  # (N, N, 3) float32
    texel_m: float
    emissive: bool = False


def fractal_noise(
    rng: np.random.Generator,
    n: int = TEXTURE_SIZE_PX,
    beta: float = 1.6,
    min_cycles: float = 1.0,
    max_cycles: float | None = None,
    anisotropy: float = 1.0,
) -> np.ndarray:
    """Periodic noise with a 1/f^beta spectrum, zero mean and unit standard deviation, (n, n)."""
    fy = np.fft.fftfreq(n)[:, None] * n
    fx = np.fft.rfftfreq(n)[None, :] * n
    f = np.sqrt((fx * anisotropy) ** 2 + fy**2)
    amp = np.where(f >= min_cycles, 1.0 / np.maximum(f, 1e-6) ** beta, 0.0)
    if max_cycles is not None:
        amp *= np.exp(-((f / max_cycles) ** 4))
    spectrum = amp * np.exp(2j * np.pi * rng.random(amp.shape))
    out = np.fft.irfft2(spectrum, s=(n, n))
    out -= out.mean()
    std = out.std()
    return (out / std if std > 0 else out).astype(np.float32)


def _rgb(base: tuple[float, float, float], shade: np.ndarray) -> np.ndarray:
    img = np.asarray(base, dtype=np.float32)[None, None, :] * shade[..., None]
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _grid_lines(n: int, period_px: int, width_px: int) -> np.ndarray:
    idx = np.arange(n)
    line = (idx % period_px) < width_px
    return (line[:, None] | line[None, :]).astype(np.float32)


def _rectangles(
    rng: np.random.Generator, n: int, count: int, min_px: int, max_px: int, values: np.ndarray
) -> np.ndarray:
    """Random axis-aligned rectangles with wrap-around, each filled with a random row of values."""
    img = np.zeros((n, n, values.shape[1]), np.float32)
    mask = np.zeros((n, n), bool)
    for _ in range(count):
        w, h = rng.integers(min_px, max_px, size=2)
        x, y = rng.integers(0, n, size=2)
        rows = np.arange(y, y + h) % n
        cols = np.arange(x, x + w) % n
        img[np.ix_(rows, cols)] = values[rng.integers(len(values))]
        mask[np.ix_(rows, cols)] = True
    return np.where(mask[..., None], img, np.nan)


def build_textures(seed: int) -> dict[str, Texture]:
    """All the materials of the room, deterministic for ``seed``."""
    rng = np.random.default_rng([seed, 0x7E57])
    n = TEXTURE_SIZE_PX
    tex: dict[str, Texture] = {}

    # Floor: speckled sheet vinyl with welded seams every 1.024 m.
    mottled = 1.0 + 0.10 * fractal_noise(rng, n, beta=1.4, min_cycles=2)
    speck_noise = fractal_noise(rng, n, beta=0.3, min_cycles=20, max_cycles=160)
    specks = np.where(speck_noise > 1.6, -0.35, 0.0) + np.where(speck_noise < -1.8, 0.25, 0.0)
    seams = _grid_lines(n, 256, 2)
    floor = _rgb((0.48, 0.55, 0.52), (mottled + specks) * (1.0 - 0.45 * seams))
    tex["floor"] = Texture("floor", floor, texel_m=0.004)

    # Walls: painted, nearly uniform: the low-texture case stereo has to survive.
    tex["wall"] = Texture(
        "wall", _rgb((0.80, 0.82, 0.78), 1.0 + 0.02 * fractal_noise(rng, n, 1.8)), texel_m=0.01
    )
    # Ceiling: 0.6 m acoustic tiles with fissures.
    fissure = fractal_noise(rng, n, beta=0.8, min_cycles=8, max_cycles=120)
    ceiling_shade = (1.0 + 0.05 * fissure) * (1.0 - 0.35 * _grid_lines(n, 128, 2))
    tex["ceiling"] = Texture("ceiling", _rgb((0.86, 0.86, 0.84), ceiling_shade), texel_m=0.0047)

    # Fabric for scrubs, gowns and drapes: a fine weave plus folds; tinted per object.
    idx = np.arange(n)
    weave = 0.06 * np.sin(2 * np.pi * idx / 4.0)[:, None] * np.sin(2 * np.pi * idx / 4.0)[None, :]
    folds = 0.16 * fractal_noise(rng, n, beta=1.8, min_cycles=2)
    grain = 0.08 * fractal_noise(rng, n, beta=0.6, min_cycles=30, max_cycles=200)
    tex["fabric"] = Texture("fabric", _rgb((1.0, 1.0, 1.0), 1.0 + weave + folds + grain), 0.002)

    tex["skin"] = Texture(
        "skin", _rgb((1.0, 1.0, 1.0), 1.0 + 0.06 * fractal_noise(rng, n, 1.2, 4)), 0.002
    )
    brushed = fractal_noise(rng, n, beta=1.0, min_cycles=3, anisotropy=12.0)
    tex["steel"] = Texture("steel", _rgb((0.62, 0.64, 0.66), 1.0 + 0.12 * brushed), 0.002)

    # Equipment plastic: panel seams, vents and labels on an off-white shell.
    labels = _rectangles(
        rng, n, 40, 6, 40, np.array([[0.2, 0.2, 0.25], [0.9, 0.5, 0.1], [0.3, 0.45, 0.7]])
    )
    shell = _rgb((1.0, 1.0, 1.0), (1.0 + 0.05 * fractal_noise(rng, n, 1.5, 2)))
    shell *= 1.0 - 0.5 * _grid_lines(n, 170, 2)[..., None]
    plastic = np.where(np.isnan(labels), shell, labels).astype(np.float32)
    tex["plastic"] = Texture("plastic", plastic, texel_m=0.003)

    tex["padding"] = Texture(
        "padding", _rgb((0.22, 0.23, 0.26), 1.0 + 0.15 * fractal_noise(rng, n, 1.1, 4)), 0.002
    )
    tex["rubber"] = Texture(
        "rubber", _rgb((0.07, 0.07, 0.08), 1.0 + 0.2 * fractal_noise(rng, n, 1.0, 4)), 0.002
    )

    # Instrument tray: many small bright and dark objects on a blue wrap: highly textured.
    tray_base = _rgb((0.35, 0.5, 0.7), 1.0 + 0.1 * fractal_noise(rng, n, 1.2, 4))
    items = _rectangles(
        rng, n, 160, 3, 28, np.array([[0.85, 0.86, 0.88], [0.15, 0.15, 0.17], [0.7, 0.7, 0.72]])
    )
    tex["tray"] = Texture("tray", np.where(np.isnan(items), tray_base, items), texel_m=0.0015)

    # Monitor screens: emissive, with panels, traces and text-like blocks.
    screen = np.full((n, n, 3), 0.03, np.float32)
    panels = _rectangles(
        rng,
        n,
        30,
        10,
        90,
        np.array([[0.1, 0.6, 0.2], [0.8, 0.8, 0.2], [0.2, 0.4, 0.9], [0.9, 0.3, 0.3]]),
    )
    screen = np.where(np.isnan(panels), screen, 0.6 * panels)
    for k in range(6):  # waveforms
        y = (40 + 80 * k + 18 * np.sin(2 * np.pi * idx * rng.uniform(2, 8) / n)).astype(int) % n
        screen[y, idx] = (0.2, 1.0, 0.3) if k % 2 == 0 else (1.0, 0.9, 0.2)
    tex["screen"] = Texture("screen", screen.astype(np.float32), 0.0012, emissive=True)

    tex["lamp"] = Texture("lamp", np.full((8, 8, 3), 1.0, np.float32), 0.05, emissive=True)
    tex["wand_sphere"] = Texture("wand_sphere", np.full((8, 8, 3), 1.0, np.float32), 0.05)
    return tex
