"""Image quality of a reconstruction against recorded views, beside the depth-reprojection baseline.

The near-field protocol (paper, "Evaluation Protocols"): train on the left images only and render
the held-out right cameras. Each right sensor sits 12 cm from a trained one, so this measures
how well the model generalises to nearby viewpoints. When a run trained on every sensor, the
same numbers on the training views measure the fit instead, and the table says so.

Writes ``eval.csv``, ``eval.md`` and one side-by-side picture per view (recorded | splats |
depth reprojection) into the run's folder.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from reconstructor.data.views import View
from reconstructor.evaluation.baselines import hole_fraction, reproject_depth_maps
from reconstructor.evaluation.metrics import psnr, ssim_value
from reconstructor.pipeline import Reconstruction
from reconstructor.splats.train import render

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ViewScore:
    view: str
    method: str
    psnr_db: float
    ssim: float


def evaluate(recon: Reconstruction, out_dir: Path | None = None) -> list[ViewScore]:
    """Scores per target view for the splats and the depth-reprojection baseline."""
    held_out = bool(recon.held_out_views)
    targets: list[View] = recon.held_out_views if held_out else recon.train_views
    protocol = "near-field (held-out right cameras)" if held_out else "training views (fit)"
    scores: list[ViewScore] = []
    for view in targets:
        mask = view.mask.numpy() > 0.5
        truth = view.image.numpy()
        with torch.no_grad():
            splat = render(recon.gaussians, view, recon.config.raster).image.clamp(0, 1).numpy()
        sources = [
            (recon.depth[f"SN{left.camera_serial}"], left.camera.pose)
            for left, _ in recon.timestamp.stereo_pairs()
            if f"SN{left.camera_serial}" in recon.depth
        ]
        base, holes = reproject_depth_maps(sources, view.camera)
        log.info("%s: depth reprojection leaves %.1f %% of the pixels empty", view.name,
                 100 * hole_fraction(holes, mask))  # fmt: skip
        for method, img in (("egosurg (splats)", splat), ("depth reprojection", base)):
            scores.append(
                ViewScore(view.name, method, psnr(img, truth, mask), ssim_value(img, truth, mask))
            )
        if out_dir is not None:
            _side_by_side(out_dir / f"eval_{view.name}.png", truth, splat, base)
    if out_dir is not None:
        write_tables(scores, out_dir, protocol)
    for method in dict.fromkeys(s.method for s in scores):
        rows = [s for s in scores if s.method == method]
        log.info(
            "%s, %s: PSNR %.2f dB, SSIM %.4f over %d views",
            protocol,
            method,
            np.mean([s.psnr_db for s in rows]),
            np.mean([s.ssim for s in rows]),
            len(rows),
        )
    return scores


def mean_scores(scores: list[ViewScore]) -> dict[str, tuple[float, float]]:
    """method -> (mean PSNR dB, mean SSIM)."""
    out = {}
    for method in dict.fromkeys(s.method for s in scores):
        rows = [s for s in scores if s.method == method]
        out[method] = (
            float(np.mean([s.psnr_db for s in rows])),
            float(np.mean([s.ssim for s in rows])),
        )
    return out


def write_tables(scores: list[ViewScore], out_dir: Path, protocol: str) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / "eval.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["protocol", "view", "method", "psnr_db", "ssim"])
        for s in scores:
            w.writerow([protocol, s.view, s.method, f"{s.psnr_db:.3f}", f"{s.ssim:.4f}"])
    lines = [
        f"Protocol: {protocol}",
        "",
        "| method | PSNR (dB) | SSIM | views |",
        "|---|---:|---:|---:|",
    ]
    n = len({s.view for s in scores})
    for method, (p_db, s_val) in mean_scores(scores).items():
        lines.append(f"| {method} | {p_db:.2f} | {s_val:.4f} | {n} |")
    (out_dir / "eval.md").write_text("\n".join(lines) + "\n")


def _side_by_side(path: Path, *images: np.ndarray) -> None:
    labels = ("recorded", "splats", "depth reprojection")
    tiles = []
    for label, img in zip(labels, images, strict=False):
        tile = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)[:, :, ::-1].copy()
        cv2.putText(tile, label, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 0), 3)
        cv2.putText(tile, label, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 1)
        tiles.append(tile)
    cv2.imwrite(str(path), np.concatenate(tiles, axis=1))
