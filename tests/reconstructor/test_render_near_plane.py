"""Rendering from a person's eye: what is nearer than the near plane (their own head) is left
out, through the real ``egosurg render`` command."""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from reconstructor.data.views import EYE_NEAR_M
from reconstructor.splats.gaussians import SH_C0, Gaussians
from reconstructor.splats.ply import write_ply
from tests.helpers import run_egosurg


def _blob(centres_m, colours, scale_m) -> Gaussians:
    n = len(centres_m)
    quats = torch.zeros((n, 4))
    quats[:, 0] = 1.0
    return Gaussians(
        means_m=torch.tensor(centres_m, dtype=torch.float32),
        quats_wxyz=quats,
        log_scales=torch.log(torch.tensor(scale_m, dtype=torch.float32))[:, None].repeat(1, 3),
        opacity_logits=torch.full((n,), math.log(0.99 / 0.01)),
        sh_dc=(torch.tensor(colours, dtype=torch.float32) - 0.5) / SH_C0,
        sh_rest=torch.zeros((n, 0, 3)),
    )


def test_the_near_plane_leaves_out_the_viewers_own_head(tmp_path):
    # an eye at 1.6 m looking along +x: a red blob 10 cm in front (the viewer's own face, as a
    # reconstruction holds it) hides a green wall 2 m away
    model = write_ply(
        tmp_path / "splats.ply",
        _blob([[0.1, 0.0, 1.6], [2.0, 0.0, 1.6]], [[1, 0, 0], [0, 1, 0]], [0.03, 0.5]),
    )
    camera = "eye=0,0,1.6 target=2,0,1.6"
    centre = {}
    for near in ("0", str(EYE_NEAR_M)):
        out = tmp_path / f"near{near}.png"
        done = run_egosurg(
            "render", str(model), "--camera", camera, "--size", "64x48", "--near-m", near,
            "--out", str(out),
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
        b, g, r = cv2.imread(str(out))[24, 32].astype(int)
        centre[near] = (r, g, b)
    r, g, _ = centre["0"]
    assert r > 200 and g < 60, centre  # the face fills the view
    r, g, _ = centre[str(EYE_NEAR_M)]
    assert g > 200 and r < 60, centre  # left out: the wall behind it


def test_a_near_plane_that_is_not_a_distance_is_refused(tmp_path):
    model = write_ply(tmp_path / "s.ply", _blob([[2.0, 0.0, 1.6]], [[0, 1, 0]], [0.5]))
    done = run_egosurg(
        "render", str(model), "--camera", "eye=0,0,1.6 target=2,0,1.6", "--near-m", "-1",
        "--out", str(tmp_path / "v.png"),
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "--near-m" in done.stderr and "metres" in done.stderr
    assert not np.any([p.name == "v.png" for p in tmp_path.iterdir()])
