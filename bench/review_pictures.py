"""The picture in docs/replay.md ("Pictures a team can read"): a replay frame with the real
cameras beside it (``egosurg replay --layout grid``) over a line-of-sight worst instant with its
plan (``egosurg sightline``), both made by the real commands on a case.

    .venv/bin/python bench/review_pictures.py CASE ROLES SITE --out docs/replay_frames.png \\
        [--role surgeon] [--viewer anaesthetist] [--target monitor-b] [--timezone UTC]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import av
import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.cli import main as egosurg


def run(*args: str) -> None:
    code = egosurg(list(args))
    if code != 0:
        raise SystemExit(f"egosurg {' '.join(args)}: exit {code}")


def middle_frame(mp4: Path) -> np.ndarray:
    with av.open(str(mp4)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    return frames[len(frames) // 2]


def stack(top: np.ndarray, bottom: np.ndarray) -> np.ndarray:
    w = max(top.shape[1], bottom.shape[1])
    pad = [np.pad(a, ((0, 0), (0, w - a.shape[1]), (0, 0)), constant_values=255)
           for a in (top, bottom)]  # fmt: skip
    gap = np.full((8, w, 3), 255, np.uint8)
    return np.concatenate([pad[0], gap, pad[1]], axis=0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("case")
    p.add_argument("roles")
    p.add_argument("site")
    p.add_argument("--out", required=True)
    p.add_argument("--role", default="surgeon")
    p.add_argument("--viewer", default="anaesthetist")
    p.add_argument("--target", default="monitor-b")
    p.add_argument("--timezone", default="UTC")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        mp4 = Path(tmp) / "grid.mp4"
        run("replay", args.case, "--role", args.role, "--roles", args.roles, "--out", str(mp4),
            "--size", "480x300", "--layout", "grid", "--timezone", args.timezone)  # fmt: skip
        los = Path(tmp) / "los"
        run("sightline", args.case, "--viewer", args.viewer, "--roles", args.roles, "--target",
            args.target, "--site", args.site, "--offset", "1m left-posterior", "--out", str(los),
            "--timezone", args.timezone)  # fmt: skip
        worst = sorted(los.glob("worst_*.png"))[0]
        picture = stack(middle_frame(mp4), cv2.imread(str(worst))[:, :, ::-1])
    cv2.imwrite(args.out, np.ascontiguousarray(picture[:, :, ::-1]))
    print(f"wrote {args.out} ({picture.shape[1]} x {picture.shape[0]} px)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
